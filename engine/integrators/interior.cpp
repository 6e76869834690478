#include "engine/integrators/interior.h"

#include <algorithm>
#include <cmath>
#include <string>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "engine/core/dual.h"
#include "engine/core/errors.h"
#include "engine/core/tape.h"
#include "engine/integrators/edges.h"
#include "engine/integrators/path.h"
#include "engine/integrators/render.h"
#include "engine/io/progress.h"

namespace bl {

using namespace interior_detail;

namespace {

// One surface vertex of a path and what its derivative needs.
struct PathVertex {
  int mesh = -1, triangle = -1;
  Vec3d origin, direction;  // the ray that hit it (fixed direction)
  double sign = 1.0;        // −1: a two-sided surface seen from its back (the frame's normal flips)
  bool scattered = false;   // a BSDF sample continued the path from here
  Vec3d next_direction;
  Vec3f radiance_so_far;  // at the continuation (everything up to and including this vertex)
  int light = 0;          // light sample that contributed: 0 none, 1 area emitter, 2 environment
  int light_emitter = -1, light_triangle = -1;
  double light_b1 = 0, light_b2 = 0;
  Vec3d light_direction;
  Vec3f light_contribution;
  bool emitter_hit = false;  // an emitter hit here by the previous vertex's BSDF sample (MIS-weighted)
  Vec3f emitter_hit_contribution;
  bool escape = false;  // the continuation from here escaped to the environment (MIS-weighted)
  Vec3f escape_contribution;
  Vec3f beta{1.f};  // throughput arriving here
  Vec3f albedo, p, geometric_normal;
  Vec2f uv;
};

// Records a path's vertices while the path loop computes its radiance.
struct VertexRecorder : NoObserver {
  static constexpr bool kActive = true;
  bool light_derivatives(const Medium&, const ParamStore&) const { return false; }  // no medium derivatives here
  const Scene* scene = nullptr;
  std::vector<PathVertex>* path = nullptr;
  int current = 0;
  bool escaped = false;
  Vec3f next_beta{1.f};        // throughput of the next vertex
  bool camera_escape = false;  // the camera ray itself reached the environment, along:
  Vec3f camera_escape_direction;

  void reached(int vertex, int site) {
    current = vertex;
    escaped = site == kSiteEscape;
  }
  void surface(int vertex, const Ray& ray, const Hit& hit, const SurfacePoint& sp) {
    path->resize(size_t(vertex));
    PathVertex& v = path->back();
    v = PathVertex{};
    v.mesh = hit.mesh;
    v.triangle = hit.triangle;
    v.origin = Vec3d(ray.origin);
    v.direction = Vec3d(ray.direction);
    const Material& material = scene->materials[size_t(scene->meshes[size_t(hit.mesh)].material)];
    if (material.two_sided && dot(sp.shading_normal, -ray.direction) < 0.f) v.sign = -1.0;
    v.beta = next_beta;
    v.albedo = material.at<float>(scene->params, sp.uv, sp.color).albedo;
    v.p = sp.p;
    v.geometric_normal = sp.geometric_normal;
    v.uv = sp.uv;
  }
  void emission(const EmissionRef& ref, const Vec3f&, const Vec3f& contribution) {
    if (current <= 1) {  // seen from the camera: weight 1
      if (escaped) {
        camera_escape = true;
        camera_escape_direction = ref.direction;
      }
      return;
    }
    if (escaped) {
      PathVertex& v = (*path)[size_t(current - 2)];
      v.escape = true;
      v.escape_contribution = contribution;
    } else if (ref.area >= 0) {
      PathVertex& v = (*path)[size_t(current - 1)];
      v.emitter_hit = true;
      v.emitter_hit_contribution = contribution;
    }
  }
  void nee(const VertexRef& vref, const Vec3f&, const EmissionRef& e, const Vec3f&, const Vec3f&,
           const Vec3f& contribution) {
    PathVertex& v = (*path)[size_t(vref.vertex - 1)];
    v.light = e.area >= 0 ? 1 : 2;
    v.light_emitter = e.area;
    v.light_triangle = e.triangle;
    v.light_b1 = e.b1;
    v.light_b2 = e.b2;
    v.light_direction = Vec3d(e.direction);
    v.light_contribution = contribution;
  }
  void scatter(const VertexRef& vref, const Vec3f&, const Vec3f& f, float pdf, float q, const Vec3f& beta_before,
               const Vec3f& radiance_so_far, int, const Ray& next) {
    next_beta = beta_before * f * (1.f / (pdf * q));
    PathVertex& v = (*path)[size_t(vref.vertex - 1)];
    v.scattered = true;
    v.next_direction = Vec3d(next.direction);
    v.radiance_so_far = radiance_so_far;
  }
};

struct Accumulator {
  std::vector<std::vector<Vec3d>> vertices, normals;
  Vec3d camera_origin{0.0}, camera_rotate{0.0};
  std::vector<double> log_area;  // per area emitter: derivative with respect to log(total area)
};

double inner(const Vec3d& a, const Vec3f& c) { return a.x * double(c.x) + a.y * double(c.y) + a.z * double(c.z); }

template <int N>
Vec3<Dual<double, N>> variable(const Vec3d& v, int first) {
  using D = Dual<double, N>;
  return {D::variable(v.x, first), D::variable(v.y, first + 1), D::variable(v.z, first + 2)};
}

template <int N>
Vec3d tangent(const Dual<double, N>& f, int first) {
  return {f.d[size_t(first)], f.d[size_t(first + 1)], f.d[size_t(first + 2)]};
}

// Corner positions (and vertex normals, when the mesh has them) of a triangle, in double.
struct Corners {
  Vec3d p[3], n[3];
  uint32_t index[3];
  bool smooth = false;
};
Corners corners(const Mesh& mesh, int triangle) {
  Corners c;
  c.smooth = !mesh.normals.empty();
  for (int i = 0; i < 3; ++i) {
    c.index[i] = mesh.indices[3 * size_t(triangle) + size_t(i)];
    c.p[i] = Vec3d(mesh.positions[c.index[i]]);
    if (c.smooth) c.n[i] = Vec3d(mesh.normals[c.index[i]]);
  }
  return c;
}

// g · the derivative of a log-factor `l` with respect to the corners of an emitter's triangle
// (inputs first .. first + 8) and the log of the emitter's area (the last input), when the
// emitter's mesh gets gradients.
template <int N>
void add_to_emitter(Accumulator& acc, const std::vector<int>& slot, int mesh, int emitter, const Corners& c,
                    const Dual<double, N>& l, int first, double g) {
  if (slot[size_t(mesh)] < 0) return;
  std::vector<Vec3d>& gv = acc.vertices[size_t(slot[size_t(mesh)])];
  for (int i = 0; i < 3; ++i) gv[c.index[i]] += tangent(l, first + 3 * i) * g;
  acc.log_area[size_t(emitter)] += l.d[size_t(N - 1)] * g;
}

// A textured diffuse albedo at a vertex whose uv slides: the scalar ∂F/∂u, ∂F/∂v of the log of
// the albedo (per channel, weighted by what passed through it: the light sample there and
// everything after the continuation), and ∂uv/∂(b1, b2) from the triangle's uvs (uv = (b1, b2)
// without them). Returns false where there is nothing to pull back.
struct AlbedoSlope {
  double gu = 0, gv = 0;                    // ∂F/∂u, ∂F/∂v
  double uv1[2] = {0, 0}, uv2[2] = {0, 0};  // ∂uv/∂b1, ∂uv/∂b2
  double channel[3] = {0, 0, 0};            // per channel: the weight of log albedo_c, and its slopes
  Vec3d du{0.0}, dv{0.0};
};
bool albedo_slope(const Scene& scene, const PathVertex& v, const Vec3f& radiance, const Vec3d& a, AlbedoSlope& out) {
  const Mesh& mesh = scene.meshes[size_t(v.mesh)];
  const Material& material = scene.materials[size_t(mesh.material)];
  if (!material.albedo.bitmap) return false;
  Vec3f passed = v.light != 0 ? v.light_contribution : Vec3f(0.f);
  if (v.scattered) passed = passed + (radiance - v.radiance_so_far);
  Vec3f du, dv;
  material.albedo.uv_gradient(scene.params, v.uv, du, dv);
  bool any = false;
  for (int c = 0; c < 3; ++c) {
    if (!(v.albedo[c] > 0.f)) continue;
    const double w = a[c] * double(passed[c]) / double(v.albedo[c]);
    out.channel[c] = a[c] * double(passed[c]);
    out.gu += w * double(du[c]);
    out.gv += w * double(dv[c]);
    any = any || w != 0;
  }
  out.du = Vec3d(du);
  out.dv = Vec3d(dv);
  const uint32_t* i = &mesh.indices[3 * size_t(v.triangle)];
  if (mesh.uvs.empty()) {
    out.uv1[0] = 1.0, out.uv2[1] = 1.0;
  } else {
    out.uv1[0] = double(mesh.uvs[i[1]].x) - double(mesh.uvs[i[0]].x);
    out.uv1[1] = double(mesh.uvs[i[1]].y) - double(mesh.uvs[i[0]].y);
    out.uv2[0] = double(mesh.uvs[i[2]].x) - double(mesh.uvs[i[0]].x);
    out.uv2[1] = double(mesh.uvs[i[2]].y) - double(mesh.uvs[i[0]].y);
  }
  return any;
}

// Whether a factor's logarithm, recomputed in double, is finite. Where it is not, the float
// primal took the configuration for light transport by rounding alone: a light sample from a
// point on the emitter's own plane (a two-sided emitter's reflective back: cos_y exactly 0 here,
// a contribution of ~1e-14 there), or a grazing direction whose cosine changed sign. Such a
// contribution is rounding noise with no derivative: nothing is added for it (its NaN made the
// whole gradient of a moving two-sided light not finite on most seeds).
template <class D>
bool finite_log(const D& l) {
  return std::isfinite(value_of(l));
}

// Pulls one path's derivatives back from its last vertex to the camera.
void backpropagate(const Scene& scene, const std::vector<PathVertex>& path, const std::vector<MovingHit<double>>& hits,
                   const std::vector<Vec3d>& boundary_x, const Vec3f& radiance, const Vec3d& a,
                   const std::vector<int>& slot, bool interior, bool camera_moves, Accumulator& acc) {
  const double select = double(scene.emitter_select_probability());
  const int n = int(path.size());
  // Vertices before the first one on a moving mesh stay where they are (their rays come from the
  // still camera through still surfaces): their own factors have no derivative, only a light
  // sample on a moving emitter does.
  int first_moving = camera_moves ? 0 : n;
  for (int k = 0; k < first_moving; ++k)
    if (slot[size_t(path[size_t(k)].mesh)] >= 0) first_moving = k;
  Vec3d carry_x(0.0);       // d/d(origin of the ray that hit vertex k), handed to vertex k − 1
  Vec3d carry_m_prev(0.0);  // d/d(shading normal of vertex k − 1) from vertex k's MIS weight
  for (int k = n - 1; k >= 0; --k) {
    const PathVertex& v = path[size_t(k)];
    const Mesh& mesh = scene.meshes[size_t(v.mesh)];
    const Corners c = corners(mesh, v.triangle);
    const MovingHit<double>& h = hits[size_t(k)];
    Vec3d adj_x = carry_x + boundary_x[size_t(k)], adj_m = carry_m_prev, adj_origin(0.0);
    carry_x = Vec3d(0.0);
    carry_m_prev = Vec3d(0.0);

    const bool moves = k >= first_moving;
    double adj_b[2] = {0, 0};  // the barycentrics, through a textured albedo's uv
    AlbedoSlope slope;
    if (interior && moves && albedo_slope(scene, v, radiance, a, slope)) {
      adj_b[0] = slope.gu * slope.uv1[0] + slope.gv * slope.uv1[1];
      adj_b[1] = slope.gu * slope.uv2[0] + slope.gv * slope.uv2[1];
    }
    if (interior && moves && v.scattered) {
      const double g = inner(a, radiance - v.radiance_so_far);
      if (g != 0.0) {
        const auto l = log_continuation(variable<3>(h.m, 0), v.sign, v.next_direction);
        if (finite_log(l)) adj_m += tangent(l, 0) * g;
      }
    }
    if (interior && moves && v.escape) {
      const double g = inner(a, v.escape_contribution);
      if (g != 0.0) {
        const double p_light = select * double(scene.environment.pdf(Vec3f(v.next_direction)));
        const auto l = log_environment_hit_weight(variable<3>(h.m, 0), v.sign, v.next_direction, p_light);
        if (finite_log(l)) adj_m += tangent(l, 0) * g;
      }
    }
    if (interior && moves && v.light == 2) {
      const double g = inner(a, v.light_contribution);
      if (g != 0.0) {
        const double p_light = select * double(scene.environment.pdf(Vec3f(v.light_direction)));
        const auto l = log_environment_sample(variable<3>(h.m, 0), v.sign, v.light_direction, p_light);
        if (finite_log(l)) adj_m += tangent(l, 0) * g;
      }
    } else if (interior && v.light == 1 &&
               (moves || slot[size_t(scene.area_emitters[size_t(v.light_emitter)].mesh)] >= 0)) {
      const double g = inner(a, v.light_contribution);
      if (g != 0.0) {
        using D = Dual<double, 16>;
        const AreaEmitter& e = scene.area_emitters[size_t(v.light_emitter)];
        const Mesh& em = scene.meshes[size_t(e.mesh)];
        const Corners q = corners(em, v.light_triangle);
        const Vec3<D> qd[3] = {variable<16>(q.p[0], 6), variable<16>(q.p[1], 9), variable<16>(q.p[2], 12)};
        const D l = log_light_sample(variable<16>(h.x, 0), variable<16>(h.m, 3), v.sign, qd, v.light_b1, v.light_b2,
                                     D::variable(std::log(double(e.total_area)), 15), select);
        if (finite_log(l)) {
          adj_x += tangent(l, 0) * g;
          adj_m += tangent(l, 3) * g;
          add_to_emitter(acc, slot, e.mesh, v.light_emitter, q, l, 6, g);
        }
      }
    }
    if (interior && moves && v.emitter_hit && k > 0) {
      const double g = inner(a, v.emitter_hit_contribution);
      if (g != 0.0) {
        using D = Dual<double, 19>;
        const AreaEmitter& e = scene.area_emitters[size_t(mesh.emitter)];
        const Vec3<D> pd[3] = {variable<19>(c.p[0], 9), variable<19>(c.p[1], 12), variable<19>(c.p[2], 15)};
        const D l = log_emitter_hit_weight(variable<19>(hits[size_t(k - 1)].m, 0), path[size_t(k - 1)].sign,
                                           v.direction, variable<19>(v.origin, 3), variable<19>(h.x, 6), pd,
                                           D::variable(std::log(double(e.total_area)), 18), select);
        if (finite_log(l)) {
          carry_m_prev += tangent(l, 0) * g;
          adj_origin += tangent(l, 3) * g;
          adj_x += tangent(l, 6) * g;
          add_to_emitter(acc, slot, v.mesh, mesh.emitter, c, l, 9, g);
        }
      }
    }

    // The hit itself: x and m as functions of the ray's origin and direction, the triangle's
    // corners and vertex normals (nothing to pull back where none of them moves).
    if (!moves || (adj_x.x == 0 && adj_x.y == 0 && adj_x.z == 0 && adj_m.x == 0 && adj_m.y == 0 && adj_m.z == 0 &&
                   adj_b[0] == 0 && adj_b[1] == 0)) {
      carry_x = adj_origin;
      continue;
    }
    const HitAdjoint r = moving_hit_adjoint(v.origin, v.direction, c.p, c.smooth ? c.n : nullptr, adj_x, adj_m, adj_b);
    adj_origin += r.origin;
    if (k == 0) {
      acc.camera_origin += adj_origin;
      acc.camera_rotate += cross(v.direction, r.direction);  // d turns by ω × d
    } else {
      carry_x = adj_origin;  // the origin is x_{k−1} offset along its normal by a constant
    }
    if (slot[size_t(v.mesh)] >= 0) {
      const size_t s = size_t(slot[size_t(v.mesh)]);
      for (int i = 0; i < 3; ++i) {
        acc.vertices[s][c.index[i]] += r.p[i];
        if (c.smooth) acc.normals[s][c.index[i]] += r.n[i];
      }
    }
  }
}

// The taped oracle of backpropagate: the same path as one computation recorded on a tape
// (engine/core/tape.h: reverse-mode AD in float) — corners, vertex normals, the camera's origin and
// rotation and the emitters' log-areas as leaves, each hit moving_hit<Var> of a ray leaving the
// previous hit, each factor the same log-factor template, the boundary term's ∂F/∂x as a linear
// term — then one reverse sweep. No closed-form pull-back and no duals: what backpropagate derives
// by hand, this gets from the chain rule, so the two must agree to float precision.
struct TapedLeaf {
  int kind = 0;  // 0 vertex position, 1 vertex normal, 2 camera origin, 3 camera rotation, 4 emitter log-area
  int slot = 0;
  uint32_t index = 0;
  int component = 0;
};

// Per thread, reused by every path: the tape (its chunks stay allocated), the leaves, the sweep's
// adjoints, the emitters' log-areas and the path's taped hits.
struct TapedScratch {
  Tape tape;
  std::vector<TapedLeaf> leaves;
  std::vector<float> adjoint;
  std::vector<Var> log_area;
  std::vector<char> have_log_area;
  std::vector<MovingHit<Var>> x;
};

void backpropagate_taped(const Scene& scene, const std::vector<PathVertex>& path,
                         const std::vector<MovingHit<double>>& hits, const std::vector<Vec3d>& boundary_x,
                         const Vec3f& radiance, const Vec3d& a, const std::vector<int>& slot, bool interior,
                         bool camera_moves, TapedScratch& scratch, Accumulator& acc) {
  const double select = double(scene.emitter_select_probability());
  Tape& tape = scratch.tape;
  std::vector<TapedLeaf>& leaves = scratch.leaves;
  tape.clear();
  leaves.clear();
  current_tape = &tape;
  auto leaf = [&](double value, TapedLeaf l) {
    leaves.push_back(l);
    return Var(float(value), tape.push(Tape::kLeaf, 1.f, uint32_t(leaves.size() - 1), 0.f));
  };
  auto vec = [&](const Vec3d& v, bool active, int kind, int s, uint32_t index) {
    if (!active) return Vec3<Var>(v);
    return Vec3<Var>{leaf(v.x, {kind, s, index, 0}), leaf(v.y, {kind, s, index, 1}), leaf(v.z, {kind, s, index, 2})};
  };
  struct TriangleVars {
    Vec3<Var> p[3], n[3];
    bool smooth = false;
  };
  auto triangle = [&](int mesh, int tri) {
    const Corners c = corners(scene.meshes[size_t(mesh)], tri);
    const int s = slot[size_t(mesh)];
    TriangleVars t;
    t.smooth = c.smooth;
    for (int i = 0; i < 3; ++i) {
      t.p[i] = vec(c.p[i], s >= 0, 0, s, c.index[i]);
      if (c.smooth) t.n[i] = vec(c.n[i], s >= 0, 1, s, c.index[i]);
    }
    return t;
  };
  std::vector<Var>& log_area = scratch.log_area;
  std::vector<char>& have_log_area = scratch.have_log_area;
  log_area.resize(scene.area_emitters.size());
  have_log_area.assign(scene.area_emitters.size(), 0);
  auto area_of = [&](int e) {
    if (!have_log_area[size_t(e)]) {
      const AreaEmitter& emitter = scene.area_emitters[size_t(e)];
      log_area[size_t(e)] = slot[size_t(emitter.mesh)] >= 0 ? leaf(std::log(double(emitter.total_area)), {4, e, 0, 0})
                                                            : Var(float(std::log(double(emitter.total_area))));
      have_log_area[size_t(e)] = 1;
    }
    return log_area[size_t(e)];
  };
  const Vec3<Var> camera_omega = vec(Vec3d(0.0), camera_moves, 3, 0, 0);
  Var total(0.f);
  std::vector<MovingHit<Var>>& x = scratch.x;
  x.resize(path.size());
  for (size_t k = 0; k < path.size(); ++k) {
    const PathVertex& v = path[k];
    const Vec3d d = v.direction;
    Vec3<Var> origin, direction(d);
    if (k == 0) {
      origin = vec(v.origin, camera_moves, 2, 0, 0);
      direction = direction + cross(camera_omega, direction);  // the camera turns by ω: d + ω × d
    } else {
      origin = x[k - 1].x + Vec3<Var>(v.origin - hits[k - 1].x);  // offset along the normal: a constant
    }
    const TriangleVars t = triangle(v.mesh, v.triangle);
    x[k] = moving_hit(origin, direction, t.p[0], t.p[1], t.p[2], t.smooth ? t.n : nullptr);
    const MovingHit<Var>& h = x[k];
    if (interior && v.scattered) {
      const double g = inner(a, radiance - v.radiance_so_far);
      if (g != 0.0) total = total + log_continuation(h.m, v.sign, v.next_direction) * float(g);
    }
    if (interior && v.escape) {
      const double g = inner(a, v.escape_contribution);
      const double p_light = select * double(scene.environment.pdf(Vec3f(v.next_direction)));
      if (g != 0.0) total = total + log_environment_hit_weight(h.m, v.sign, v.next_direction, p_light) * float(g);
    }
    if (interior && v.light == 2) {
      const double g = inner(a, v.light_contribution);
      const double p_light = select * double(scene.environment.pdf(Vec3f(v.light_direction)));
      if (g != 0.0) total = total + log_environment_sample(h.m, v.sign, v.light_direction, p_light) * float(g);
    } else if (interior && v.light == 1) {
      const double g = inner(a, v.light_contribution);
      if (g != 0.0) {
        const TriangleVars q = triangle(scene.area_emitters[size_t(v.light_emitter)].mesh, v.light_triangle);
        total =
            total + log_light_sample(h.x, h.m, v.sign, q.p, v.light_b1, v.light_b2, area_of(v.light_emitter), select) *
                        float(g);
      }
    }
    if (interior && v.emitter_hit && k > 0) {
      const double g = inner(a, v.emitter_hit_contribution);
      if (g != 0.0) {
        const int e = scene.meshes[size_t(v.mesh)].emitter;
        total = total + log_emitter_hit_weight(x[k - 1].m, path[k - 1].sign, d, origin, h.x, t.p, area_of(e), select) *
                            float(g);
      }
    }
    AlbedoSlope slope;
    if (interior && albedo_slope(scene, v, radiance, a, slope)) {
      // log albedo_c(uv(b1, b2)), its slopes in u and v recorded as the texture's partials.
      const Var u = h.b1 * float(slope.uv1[0]) + h.b2 * float(slope.uv2[0]);
      const Var w = h.b1 * float(slope.uv1[1]) + h.b2 * float(slope.uv2[1]);
      for (int ch = 0; ch < 3; ++ch) {
        if (slope.channel[ch] == 0) continue;
        const Var albedo = record(v.albedo[ch], u, float(slope.du[ch]), w, float(slope.dv[ch]));
        total = total + log(albedo) * float(slope.channel[ch]);
      }
    }
    const Vec3d& b = boundary_x[k];
    if (b.x != 0 || b.y != 0 || b.z != 0) total = total + dot(h.x, Vec3<Var>(b));
  }
  current_tape = nullptr;
  if (!total.active()) return;
  std::vector<float>& adjoint = scratch.adjoint;
  adjoint.assign(tape.size(), 0.f);
  adjoint[total.index] = 1.f;
  reverse_sweep(tape, adjoint, [&](uint32_t id, float g) {
    const TapedLeaf& l = leaves[id];
    switch (l.kind) {
      case 0:
        acc.vertices[size_t(l.slot)][l.index][l.component] += double(g);
        break;
      case 1:
        acc.normals[size_t(l.slot)][l.index][l.component] += double(g);
        break;
      case 2:
        acc.camera_origin[l.component] += double(g);
        break;
      case 3:
        acc.camera_rotate[l.component] += double(g);
        break;
      default:
        acc.log_area[size_t(l.slot)] += double(g);
        break;
    }
  });
}

// Secondary visibility at path vertex k (x = its point): one point p on an edge that is a
// discontinuity seen from x (edge_sample below picks the edge), ω = (p − x)/r, n the unit normal of
// the plane through x and the edge, and one path on each side (±side_angle along n) from x. With the parameterization
// of the interior term, the integrand of the BSDF-sampled estimate jumps across ω and its directions are fixed, so its
// flux is [h⁻ − h⁺] · n·(ṗ − ẋ)/r; a light sample moves with its emitter instead, so where a side sees an area emitter
// directly its light-sampled share h_N (MIS weight w_light) crosses the edge at the relative angular velocity n·(ṗ −
// ẋ)/r − n·(ẏ − ẋ)/r_y. h is β f L.
struct EdgeSampling {
  const Scene* scene = nullptr;
  const edges::EdgeTable* moving = nullptr;  // edges of the meshes that get gradients
  const edges::EdgeTable* all = nullptr;     // every mesh's edges (x moves, or an emitter moves)
  const std::vector<int>* slot = nullptr;
  double side_angle = 1e-5;
  bool emitter_moves = false;
  uint64_t seed = 0;
  int samples = 1;  // edge samples per vertex
  bool hierarchy = true;
  const edges::EdgeTree* moving_tree = nullptr;
  const edges::EdgeTree* all_tree = nullptr;
};

// One point at parameter t on edge e, sampled with density 1/inv_pdf per unit length.
void one_edge_sample(const EdgeSampling& es, const PathVertex& v, const MovingHit<double>& h, const Vec3d& a,
                     const edges::EdgeTable& table, const edges::MeshEdge& e, double t, double inv_pdf, uint64_t pixel,
                     uint64_t stream, int vertex, Accumulator& acc, Vec3d& adj_x) {
  constexpr uint64_t kSideSeed = 0x5ec0ed6e7ull;
  const Scene& scene = *es.scene;
  const Vec3d x(v.p), p0(e.p0), p1(e.p1);
  const Vec3d p = p0 + (p1 - p0) * t;
  const double r = length(p - x);
  const Vec3d plane = cross(p0 - x, p1 - x);
  const double plane_len = length(plane);
  if (!(r > 0 && plane_len > 0)) return;  // the edge passes through x
  const Vec3d omega = (p - x) / r, n = plane / plane_len;
  const Vec3d normal = unit_normal(h.m, v.sign);
  const double cos_x = dot(normal, omega);
  // Diffuse: nothing arrives from below, and a one-sided surface seen from its back reflects nothing.
  if (!(cos_x > 0) || !(dot(normal, -v.direction) > 0)) return;
  const Vec3f f = v.albedo * float(cos_x * kInvPiD);
  if (is_zero(f)) return;
  const float p_bsdf = float(cos_x * kInvPiD);
  const float select = scene.emitter_select_probability();
  const Vec3f origin = offset_origin(v.p, v.geometric_normal, Vec3f(omega));
  const Vec3d o(origin);
  const Vec3d plane_o = cross(p0 - o, p1 - o);
  const double plane_o_len = length(plane_o), r_o = length(p - o);
  if (!(plane_o_len > 0 && r_o > 0)) return;
  const Vec3d n_o = plane_o / plane_o_len, omega_o = (p - o) / r_o;
  // Hidden behind something nearer, the edge is no discontinuity of what x sees: no side paths.
  if (scene.occluded(origin, Vec3f(omega_o), float(r_o * (1.0 - 1e-3)))) return;
  const PathSampler side(es.seed ^ kSideSeed, pixel, stream);
  const double jacobian = length(cross(normalize(p1 - p0), omega)) / r * inv_pdf;  // arc length / pdf
  NoObserver none;
  Ray rays[2];
  Hit hits[2];
  for (int side_index = 0; side_index < 2; ++side_index) {
    const Vec3f d(normalize(omega_o + n_o * ((side_index == 0 ? -1.0 : 1.0) * es.side_angle)));
    rays[side_index] = Ray{origin, d};
    hits[side_index] = scene.geometry->intersect(rays[side_index]);
  }
  // A fold seen from x, near an outline it runs along: a side off the mesh sees the outline's jump.
  if (edges::fold_from(scene, e, v.p) && !(edges::on_faces(e, hits[0]) && edges::on_faces(e, hits[1]))) return;
  double fixed = 0;  // ⟨a, h_fixed⁻ − h_fixed⁺⟩
  for (int side_index = 0; side_index < 2; ++side_index) {
    const double sign = side_index == 0 ? -1.0 : 1.0;
    const Ray& ray = rays[side_index];
    const Vec3f d = ray.direction;
    const Hit& hit = hits[side_index];
    const Vec3f bsdf_part =
        v.beta * f * trace_path<float>(scene, PathStart{ray, vertex + 1, p_bsdf, -1, &hit}, side, none);
    double h_fixed = inner(a, bsdf_part);
    // The light-sampled share of what this side sees directly.
    if (hit.mesh < 0) {
      if (scene.environment.present) {
        const EnvLookup look = scene.environment.lookup(d);
        const float w = power_heuristic(select * scene.environment.pdf(d, look), p_bsdf);
        h_fixed += inner(a, v.beta * f * scene.environment.eval<float>(scene.params, look) * w);
      }
    } else {
      const Mesh& m = scene.meshes[size_t(hit.mesh)];
      if (m.emitter >= 0) {
        const SurfacePoint sp = scene.surface_point(hit, ray);
        const float cos_shading = dot(sp.shading_normal, -d);
        const AreaEmitter& emitter = scene.area_emitters[size_t(m.emitter)];
        const float p_light = select * emitter.pdf(hit.t, std::abs(dot(sp.geometric_normal, d)));
        const Vec3f le = emitter.eval<float>(scene.params, sp.uv, cos_shading);
        const double h_light = inner(a, v.beta * f * le * power_heuristic(p_light, p_bsdf));
        if (h_light != 0.0) {
          // Its point moves with the emitter's triangle: −(±) c n·(ẏ − ẋ), c = h_light·J/r_y.
          const double c = (sign < 0 ? 1.0 : -1.0) * h_light * jacobian / double(hit.t);
          if ((*es.slot)[size_t(hit.mesh)] >= 0) {
            std::vector<Vec3d>& g = acc.vertices[size_t((*es.slot)[size_t(hit.mesh)])];
            const double b[3] = {1.0 - double(hit.b1) - double(hit.b2), double(hit.b1), double(hit.b2)};
            for (int i = 0; i < 3; ++i) g[m.indices[3 * size_t(hit.triangle) + size_t(i)]] -= n * (c * b[i]);
          }
          adj_x += n * c;
          h_fixed += h_light;  // it crosses with the edge as well: n·(ṗ − ẋ)/r below
        }
      }
    }
    fixed += sign < 0 ? h_fixed : -h_fixed;
  }
  const double c_e = fixed * jacobian / r;
  if (c_e == 0.0) return;
  adj_x -= n * c_e;
  const int s = (*es.slot)[size_t(e.mesh)];
  if (s >= 0) edges::add_to_edge(table, e, n * (c_e * (1 - t)), n * (c_e * t), acc.vertices[size_t(s)]);
}

void edge_sample(const EdgeSampling& es, const PathVertex& v, const MovingHit<double>& h, bool x_moves, const Vec3d& a,
                 uint64_t pixel, uint64_t stream, int vertex, std::vector<double>& cdf, std::vector<uint32_t>& index,
                 Accumulator& acc, Vec3d& adj_x) {
  constexpr uint64_t kEdgeSeed = 0x5ec0ed6e6ull;
  const Scene& scene = *es.scene;
  const bool everything = x_moves || es.emitter_moves;
  const edges::EdgeTable& table = everything ? *es.all : *es.moving;
  const PathSampler edge_rng(es.seed ^ kEdgeSeed, pixel, stream);
  if (es.hierarchy) {
    const edges::EdgeTree& tree = everything ? *es.all_tree : *es.moving_tree;
    for (int j = 0; j < es.samples; ++j) {
      uint32_t pick = 0;
      double probability = 0;
      if (!edges::sample_edge(table, tree, v.p, edge_rng.get_double(2 * j), &pick, &probability)) continue;
      const edges::MeshEdge& e = table.edges[pick];
      if (!edges::candidate_from(scene, e, v.p)) continue;  // no discontinuity seen from x
      const double len = double(length(e.p1 - e.p0));
      one_edge_sample(es, v, h, a, table, e, double(edge_rng.get(2 * j + 1)), len / probability / es.samples, pixel,
                      stream ^ (uint64_t(j) << 40), vertex, acc, adj_x);
    }
    return;
  }
  // Linear scan (for tests and benchmarks): uniform in length over the candidates from x.
  cdf.clear();
  index.clear();
  double total = 0;
  for (uint32_t i = 0; i < uint32_t(table.edges.size()); ++i)
    if (edges::candidate_from(scene, table.edges[i], v.p)) {
      total += double(length(table.edges[i].p1 - table.edges[i].p0));
      cdf.push_back(total);
      index.push_back(i);
    }
  if (!(total > 0)) return;
  for (int j = 0; j < es.samples; ++j) {
    const double u = edge_rng.get_double(2 * j) * total;
    const size_t pick = std::min(size_t(std::upper_bound(cdf.begin(), cdf.end(), u) - cdf.begin()), cdf.size() - 1);
    one_edge_sample(es, v, h, a, table, table.edges[index[pick]], double(edge_rng.get(2 * j + 1)), total / es.samples,
                    pixel, stream ^ (uint64_t(j) << 40), vertex, acc, adj_x);
  }
}

}  // namespace

GeometryGradient path_geometry_gradient(const Scene& scene, const Image& adjoint, const PathGeometryOptions& options) {
  const Camera& cam = scene.cameras.at(size_t(options.camera));
  GeometryGradient result = empty_geometry_gradient(scene, cam, adjoint, options.meshes, "geometry gradient", true);
  check_interior_support(scene);
  std::vector<int> slot(scene.meshes.size(), -1);
  for (size_t k = 0; k < result.meshes.size(); ++k) slot[size_t(result.meshes[k])] = int(k);
  result.samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(std::max(options.spp, 0));
  if (options.spp <= 0) return result;

  tbb::enumerable_thread_specific<Accumulator> per_thread([&] {
    Accumulator acc;
    acc.vertices.resize(result.vertices.size());
    acc.normals.resize(result.normals.size());
    for (size_t k = 0; k < acc.vertices.size(); ++k) {
      acc.vertices[k].assign(result.vertices[k].size(), Vec3d(0.0));
      acc.normals[k].assign(result.normals[k].size(), Vec3d(0.0));
    }
    acc.log_area.assign(scene.area_emitters.size(), 0.0);
    return acc;
  });
  constexpr uint64_t kPathSeed = 0x1e7e510f9ull;
  const double inv_spp = 1.0 / double(options.spp);
  const int max_depth = scene.settings.max_depth;
  edges::EdgeTable moving_edges, all_edges;
  edges::EdgeTree moving_tree, all_tree;
  EdgeSampling es;
  if (options.boundary) {
    moving_edges = edges::edge_topology(scene, result.meshes);
    std::vector<int> every(scene.meshes.size());
    for (size_t i = 0; i < every.size(); ++i) every[i] = int(i);
    all_edges = edges::edge_topology(scene, every);
    moving_tree = edges::build_edge_tree(scene, moving_edges);
    all_tree = edges::build_edge_tree(scene, all_edges);
    for (int mi : result.meshes) es.emitter_moves = es.emitter_moves || scene.meshes[size_t(mi)].emitter >= 0;
    result.edges = int(all_edges.edges.size());
  }
  es.scene = &scene;
  es.moving = &moving_edges;
  es.all = &all_edges;
  es.slot = &slot;
  es.side_angle = double(options.side_angle);
  es.seed = options.seed;
  es.samples = std::max(options.edge_samples, 1);
  es.hierarchy = options.edge_hierarchy;
  es.moving_tree = &moving_tree;
  es.all_tree = &all_tree;
  tbb::enumerable_thread_specific<TapedScratch> taped_scratch;  // options.taped only
  Progress progress("geometry", uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(options.spp), "paths",
                    options.progress);
  tbb::parallel_for(tbb::blocked_range<int>(0, cam.height), [&](const tbb::blocked_range<int>& rows) {
    if (cancelled(options.cancel)) return;
    Accumulator& acc = per_thread.local();
    std::vector<PathVertex> path;
    std::vector<MovingHit<double>> hits;
    std::vector<Vec3d> boundary_x;
    std::vector<double> cdf;
    std::vector<uint32_t> index;
    VertexRecorder recorder;
    recorder.scene = &scene;
    recorder.path = &path;
    for (int py = rows.begin(); py != rows.end(); ++py) {
      if (cancelled(options.cancel)) return;
      for (int px = 0; px < cam.width; ++px) {
        const Vec3d a = Vec3d(adjoint.at(px, py, 0), adjoint.at(px, py, 1), adjoint.at(px, py, 2)) * inv_spp;
        if (a.x == 0 && a.y == 0 && a.z == 0) continue;
        const uint64_t pixel = uint64_t(py) * uint64_t(cam.width) + uint64_t(px);
        for (int s = 0; s < options.spp; ++s) {
          const PathSampler sampler(options.seed ^ kPathSeed, pixel, uint64_t(s));
          const PathStart start{
              cam.generate(float(px) + sampler.get(Dim::kPixelX), float(py) + sampler.get(Dim::kPixelY)), 1, 0.f,
              cam.medium};
          path.clear();
          recorder.current = 0;
          recorder.escaped = false;
          recorder.next_beta = Vec3f(1.f);
          recorder.camera_escape = false;
          const Vec3f radiance = trace_path<float>(scene, start, sampler, recorder);
          const size_t n = path.size();
          // The sky seen by the camera turns with it: the radiance along d + ω × d, whose
          // derivative in ω is d × ∇_d (a linear term in ω, the same closed form for the taped mode).
          // Only a bilinear map has one (check_geometry_view refuses the nearest lookup's).
          if (n == 0 && recorder.camera_escape && options.camera_moves && options.interior) {
            const Vec3d d(recorder.camera_escape_direction);
            acc.camera_rotate += cross(d, scene.environment.direction_gradient(scene.params, Vec3f(d), a));
          }
          if (n == 0) continue;
          hits.resize(n);
          boundary_x.assign(n, Vec3d(0.0));
          bool x_moves = options.camera_moves;
          for (size_t k = 0; k < n; ++k) {
            const PathVertex& v = path[k];
            const Corners c = corners(scene.meshes[size_t(v.mesh)], v.triangle);
            hits[k] = moving_hit(v.origin, v.direction, c.p[0], c.p[1], c.p[2], c.smooth ? c.n : nullptr);
            x_moves = x_moves || slot[size_t(v.mesh)] >= 0;
            const int vertex = int(k) + 1;
            if (options.boundary && (max_depth < 0 || vertex < max_depth))
              edge_sample(es, v, hits[k], x_moves, a, pixel, uint64_t(s) << 8 | uint64_t(std::min(vertex, 255)), vertex,
                          cdf, index, acc, boundary_x[k]);
          }
          if (options.taped)
            backpropagate_taped(scene, path, hits, boundary_x, radiance, a, slot, options.interior,
                                options.camera_moves, taped_scratch.local(), acc);
          else
            backpropagate(scene, path, hits, boundary_x, radiance, a, slot, options.interior, options.camera_moves,
                          acc);
        }
      }
      progress.advance(uint64_t(cam.width) * uint64_t(options.spp));
    }
  });
  progress.finish();

  std::vector<double> log_area(scene.area_emitters.size(), 0.0);
  for (const Accumulator& acc : per_thread) {
    for (size_t k = 0; k < acc.vertices.size(); ++k) {
      for (size_t i = 0; i < acc.vertices[k].size(); ++i) result.vertices[k][i] += acc.vertices[k][i];
      for (size_t i = 0; i < acc.normals[k].size(); ++i) result.normals[k][i] += acc.normals[k][i];
    }
    result.camera_origin += acc.camera_origin;
    result.camera_rotate += acc.camera_rotate;
    for (size_t e = 0; e < log_area.size(); ++e) log_area[e] += acc.log_area[e];
  }
  // d log A = Σ_t n̂_t · dc_t / (2A) over the emitter's triangles, c_t = (p1 − p0) × (p2 − p0).
  for (size_t e = 0; e < log_area.size(); ++e) {
    const AreaEmitter& emitter = scene.area_emitters[e];
    if (log_area[e] == 0.0 || slot[size_t(emitter.mesh)] < 0) continue;
    const Mesh& m = scene.meshes[size_t(emitter.mesh)];
    std::vector<Vec3d>& g = result.vertices[size_t(slot[size_t(emitter.mesh)])];
    const double scale = log_area[e] / (2.0 * double(emitter.total_area));
    for (size_t t = 0; t < m.triangle_count(); ++t) {
      const Corners c = corners(m, int(t));
      const Vec3d e1 = c.p[1] - c.p[0], e2 = c.p[2] - c.p[0];
      const Vec3d cr = cross(e1, e2);
      const double len = length(cr);
      if (!(len > 0)) continue;
      const Vec3d gc = cr * (scale / len);
      const Vec3d g1 = cross(e2, gc), g2 = cross(gc, e1);
      g[c.index[1]] += g1;
      g[c.index[2]] += g2;
      g[c.index[0]] -= g1 + g2;
    }
  }
  return result;
}

void check_interior_support(const Scene& scene) {
  const std::string where = scene.source + ": geometry gradients (interior term): ";
  if (!scene.media.empty()) throw InputError(where + "media are not supported yet");
  for (const Mesh& m : scene.meshes) {
    const Material& material = scene.materials[size_t(m.material)];
    if (material.is_null) throw InputError(where + "null surfaces are not supported yet (shape '" + m.name + "')");
    if (material.type != BsdfType::Diffuse)
      throw InputError(where + "only diffuse surfaces are supported yet (shape '" + m.name + "')");
    if (!m.colors.empty()) throw InputError(where + "vertex colours are not supported yet (shape '" + m.name + "')");
  }
  for (const AreaEmitter& e : scene.area_emitters)
    if (e.radiance.bitmap)
      throw InputError(where + "bitmap radiance on area emitters is not supported yet (shape '" +
                       scene.meshes[size_t(e.mesh)].name + "')");
}

}  // namespace bl
