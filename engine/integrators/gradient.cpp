#include "engine/integrators/gradient.h"

#include "engine/io/grid_view.h"
#include "engine/scene/openvdb_io.h"
#include "engine/scene/volume_io.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <limits>
#include <random>
#include <regex>
#include <sstream>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/core/weld.h"
#include "engine/dist/dist.h"
#include "engine/integrators/boundary.h"
#include "engine/integrators/interior.h"
#include "engine/integrators/taped.h"
#include "engine/io/progress.h"

namespace bl {

namespace fs = std::filesystem;

GradientMethod parse_method(const std::string& name) {
  if (name == "prb") return GradientMethod::Prb;
  if (name == "rb") return GradientMethod::Rb;
  if (name == "taped") return GradientMethod::Taped;
  throw InputError("unknown method '" + name + "' (expected prb, rb or taped)");
}

const char* method_name(GradientMethod m) {
  switch (m) {
    case GradientMethod::Prb:
      return "prb";
    case GradientMethod::Rb:
      return "rb";
    case GradientMethod::Taped:
      return "taped";
  }
  return "?";
}

namespace {
Vec3f pixel_of(const Image& img, size_t pixel) {
  return {img.data[pixel * 3], img.data[pixel * 3 + 1], img.data[pixel * 3 + 2]};
}
double functional(const Image& a, const Image& img) {
  double f = 0;
  for (size_t i = 0; i < img.data.size(); ++i) f += double(a.data[i]) * double(img.data[i]);
  return f;
}
}  // namespace

namespace {
// This rank's share of the gradient (all of it on one process).
GradientResult local_gradient(Scene& scene, const GradientRequest& rq) {
  if (!rq.accumulate) scene.params.zero_grad();
  GradientResult result;
  const Camera& cam = scene.cameras.at(size_t(rq.pass.camera));
  const double values = double(cam.width) * double(cam.height) * 3.0;
  if (rq.method == GradientMethod::Taped) return taped_gradient(scene, rq);
  if (rq.method == GradientMethod::Rb && !scene.media.empty())
    throw InputError(scene.source + ": rb does not support scenes with media yet (use --method prb or taped)");
  const AdjointMethod method = rq.method == GradientMethod::Prb ? AdjointMethod::Prb : AdjointMethod::Rb;
  PassOptions adj = rq.pass;
  adj.seed = rq.adjoint_seed;

  if (rq.adjoint_image) {
    const Image& a = *rq.adjoint_image;
    if (rq.adjoint_seed == rq.pass.seed) {
      PassStats s = backward(
          scene, adj, method, [&](size_t p, const Vec3f&) { return pixel_of(a, p); }, &result.image);
      result.adjoint_seconds = s.seconds;
    } else {
      PassStats ps;
      result.image = render(scene, rq.pass, &ps);
      result.primal_seconds = ps.seconds;
      result.adjoint_seconds =
          backward(scene, adj, method, [&](size_t p, const Vec3f&) { return pixel_of(a, p); }).seconds;
    }
    result.loss = functional(a, result.image);
    return result;
  }

  if (!rq.target) throw InputError("grad needs --target or --adjoint-image");
  const Image& t = *rq.target;
  if (rq.adjoint_seed == rq.pass.seed) {
    // Fused: the loss gradient of a pixel is known as soon as the pixel is rendered.
    PassStats s = backward(
        scene, adj, method,
        [&](size_t p, const Vec3f& value) {
          Vec3f g;
          loss_pixel(rq.loss, value, pixel_of(t, p), values, &g);
          return g;
        },
        &result.image);
    result.adjoint_seconds = s.seconds;
    // The loss value is summed afterwards in pixel order, so it does not depend on scheduling.
    result.loss = compute_loss(rq.loss, result.image, t).value;
  } else {
    PassStats ps;
    result.image = render(scene, rq.pass, &ps);
    result.primal_seconds = ps.seconds;
    LossResult lr = compute_loss(rq.loss, result.image, t);
    result.loss = lr.value;
    result.adjoint_seconds =
        backward(scene, adj, method, [&](size_t p, const Vec3f&) { return pixel_of(lr.adjoint, p); }).seconds;
  }
  return result;
}
}  // namespace

namespace {
bool wants(const ParamStore& p, int handle) { return handle >= 0 && p[handle].requires_grad; }
void add_vec(Param& p, const Vec3d& g) {
  for (int i = 0; i < 3; ++i) p.grad[size_t(i)] += float(g[i]);
}
Vec3d value3(const ParamStore& p, int handle, const Vec3d& fallback) {
  return handle >= 0 ? Vec3d(p[handle].value[0], p[handle].value[1], p[handle].value[2]) : fallback;
}
}  // namespace

namespace {
// The meshes whose pose or vertices want a gradient (every mesh when camera `camera` moves).
std::vector<int> moving_meshes(const Scene& scene, int camera, bool* camera_moves, const CameraPose** pose) {
  const ParamStore& P = scene.params;
  const CameraPose* cam_pose =
      size_t(camera) < scene.camera_poses.size() ? &scene.camera_poses[size_t(camera)] : nullptr;
  *camera_moves = cam_pose && (wants(P, cam_pose->origin) || wants(P, cam_pose->rotate));
  if (pose) *pose = cam_pose;
  std::vector<int> meshes;
  for (size_t i = 0; i < scene.mesh_poses.size(); ++i) {
    const MeshPose& m = scene.mesh_poses[i];
    if (*camera_moves || wants(P, m.translate) || wants(P, m.rotate) || wants(P, m.scale) || wants(P, m.positions))
      meshes.push_back(int(i));
  }
  return meshes;
}

// Whether segment a–b (film-plane coordinates) meets the rectangle |x| ≤ hx, |y| ≤ hy.
bool segment_meets_rectangle(double ax, double ay, double bx, double by, double hx, double hy) {
  double t0 = 0, t1 = 0;
  return clip_to_film(ax + hx, ay + hy, bx + hx, by + hy, 2 * hx, 2 * hy, &t0, &t1);
}
}  // namespace

void check_geometry_view(const Scene& scene, int camera) {
  const std::string where = scene.source + ": geometry gradients: ";
  bool camera_moves = false;
  const CameraPose* pose = nullptr;
  const std::vector<int> meshes = moving_meshes(scene, camera, &camera_moves, &pose);
  const Camera& cam = scene.cameras.at(size_t(camera));
  // A rotating camera turns the environment it sees directly: a bilinear map's radiance changes
  // smoothly with the direction (an interior term, path_geometry_gradient), but the nearest
  // lookup's texels are constant patches whose edges sweep across the film, jumps no term samples
  // (a constant environment does not change).
  if (camera_moves && wants(scene.params, pose->rotate) && scene.environment.present && scene.environment.is_map &&
      !scene.environment.bilinear && !scene.settings.hide_emitters)
    throw InputError(where + "the rotation of camera '" + cam.name +
                     "' with an environment map in view is not supported for the map's nearest lookup (its texel "
                     "edges move across the film); \"convention\": \"mitsuba\" (bilinear), a constant environment or "
                     "hide_emitters is");
  // The near plane cuts a moving triangle in view, or any when the camera moves: the cut is an
  // edge of the image that is no mesh edge, which the boundary terms do not sample.
  const double hx = double(cam.tan_x) * double(cam.near_clip), hy = double(cam.tan_y) * double(cam.near_clip);
  const Vec3d o(cam.origin), f(cam.forward), r(cam.right), u(cam.true_up);
  for (int mi : meshes) {
    const Mesh& m = scene.meshes[size_t(mi)];
    for (size_t t = 0; t < m.triangle_count(); ++t) {
      Vec3d p[3];
      double depth[3];
      for (int k = 0; k < 3; ++k) {
        p[k] = Vec3d(m.positions[m.indices[3 * t + size_t(k)]]) - o;
        depth[k] = dot(p[k], f) - double(cam.near_clip);
      }
      // The points where the edges cross the near plane (two, when the plane cuts the triangle).
      Vec3d cut[2];
      int n = 0;
      for (int k = 0; k < 3 && n < 2; ++k) {
        const double a = depth[k], b = depth[(k + 1) % 3];
        if ((a < 0) != (b < 0)) cut[n++] = p[k] + (p[(k + 1) % 3] - p[k]) * (a / (a - b));
      }
      if (n < 2) continue;
      if (segment_meets_rectangle(dot(cut[0], r), dot(cut[0], u), dot(cut[1], r), dot(cut[1], u), hx, hy))
        throw InputError(where + "the near plane of camera '" + cam.name + "' (near_clip " +
                         (std::ostringstream() << cam.near_clip).str() + ") cuts shape '" + m.name +
                         "' in view: the cut is an edge of the image the boundary terms do not sample yet (lower "
                         "near_clip, or move the camera)");
    }
  }
}

void add_geometry_gradient(Scene& scene, const Image& adjoint, const GradientRequest& rq) {
  ParamStore& P = scene.params;
  if (!P.wants_geometry()) return;
  check_interior_support(scene);
  const int camera = rq.pass.camera;
  bool camera_moves = false;
  const CameraPose* cam_pose = nullptr;
  const std::vector<int> meshes = moving_meshes(scene, camera, &camera_moves, &cam_pose);
  if (meshes.empty() && !camera_moves) return;
  const int spp = rq.geometry_spp > 0 ? rq.geometry_spp : std::max(rq.pass.spp, 1);
  const Camera& cam = scene.cameras.at(size_t(camera));
  BoundaryOptions bo;
  bo.camera = camera;
  bo.samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(spp);
  bo.seed = rq.adjoint_seed;
  bo.meshes = meshes;
  bo.progress = rq.pass.progress;
  bo.cancel = rq.pass.cancel;
  PathGeometryOptions po;
  po.camera = camera;
  po.spp = spp;
  po.seed = rq.adjoint_seed;
  po.meshes = meshes;
  po.camera_moves = camera_moves;
  po.edge_samples = rq.edge_samples;
  po.taped = rq.method == GradientMethod::Taped;  // the oracle's pull-back, on the same paths
  po.progress = rq.pass.progress;
  po.cancel = rq.pass.cancel;
  GeometryGradient g = meshes.empty() ? GeometryGradient{} : primary_boundary_gradient(scene, adjoint, bo);
  GeometryGradient paths = path_geometry_gradient(scene, adjoint, po);
  if (meshes.empty()) {
    g = paths;
  } else {
    // Before the sum: the camera's share of the primary term is the meshes' relative motion.
    if (camera_moves) {
      const CameraPoseGradient c = camera_pose_gradient(scene, g, cam);
      g.camera_origin = c.origin;
      g.camera_rotate = c.rotate;
    }
    g += paths;
  }
  for (size_t k = 0; k < g.meshes.size(); ++k) {
    const size_t i = size_t(g.meshes[k]);
    const MeshPose& pose = scene.mesh_poses[i];
    const Mesh& mesh = scene.meshes[i];
    const std::vector<Vec3d>& gv = g.vertices[k];
    const std::vector<Vec3d> none;
    const std::vector<Vec3d>& gn = k < g.normals.size() ? g.normals[k] : none;
    const Vec3d t = value3(P, pose.translate, Vec3d(0.0)), r = value3(P, pose.rotate, Vec3d(0.0)),
                s = value3(P, pose.scale, Vec3d(1.0));
    const Rotation R = rotation_of(r);
    const Vec3d pivot(pose.pivot), centre = pivot + t;
    Vec3d g_t(0.0), g_w(0.0), g_s(0.0);
    const bool want_positions = wants(P, pose.positions);
    // Smooth meshes: the rest normals follow the rest positions (MeshPose).
    const bool normals_follow = want_positions && !gn.empty() && !pose.loaded_normals.empty();
    std::vector<Vec3d> g_n0(normals_follow ? mesh.vertex_count() : 0, Vec3d(0.0));
    for (size_t v = 0; v < mesh.vertex_count(); ++v) {
      const Vec3d& d = gv[v];
      const Vec3d local = R.apply_transpose(d);
      g_t += d;
      g_w += cross(Vec3d(mesh.positions[v]) - centre, d);
      if (pose.positions >= 0) {
        const std::vector<float>& p0 = P[pose.positions].value;
        const Vec3d u0 = Vec3d(p0[3 * v], p0[3 * v + 1], p0[3 * v + 2]) - pivot;
        g_s += local * u0;
        if (want_positions)
          for (int c = 0; c < 3; ++c) P[pose.positions].grad[3 * v + size_t(c)] += float(local[c] * s[c]);
      }
      if (!gn.empty() && !pose.rest_normals.empty()) {
        const Vec3d& dn = gn[v];
        g_w += cross(Vec3d(mesh.normals[v]), dn);
        // n = R · normalise(n₀ ⊘ s): ∂/∂s_i = R (I − ŵŵᵀ)(−n₀_i / s_i² e_i) / |w|, w = n₀ ⊘ s.
        const Vec3d n0(pose.rest_normals[v]);
        const Vec3d w = n0 / s;
        const double wl = length(w);
        const Vec3d wh = w / wl, h = R.apply_transpose(dn);
        const Vec3d perp = h - wh * dot(wh, h);
        for (int c = 0; c < 3; ++c) g_s[c] -= perp[c] * n0[c] / (s[c] * s[c] * wl);
        // ∂n/∂n₀ = R (I − ŵŵᵀ) diag(1/s) / |w|.
        if (normals_follow) g_n0[v] = perp / (s * wl);
      }
    }
    if (normals_follow) add_rest_normal_gradient(pose, mesh, P[pose.positions].value, g_n0, P[pose.positions].grad);
    if (wants(P, pose.translate)) add_vec(P[pose.translate], g_t);
    if (wants(P, pose.rotate)) add_vec(P[pose.rotate], left_jacobian_transpose(r, g_w));
    if (wants(P, pose.scale)) add_vec(P[pose.scale], g_s);
  }
  if (camera_moves) {
    if (wants(P, cam_pose->origin)) add_vec(P[cam_pose->origin], g.camera_origin);
    if (wants(P, cam_pose->rotate))
      add_vec(P[cam_pose->rotate], left_jacobian_transpose(value3(P, cam_pose->rotate, Vec3d(0.0)), g.camera_rotate));
  }
}

GradientResult compute_gradient(Scene& scene, const GradientRequest& rq) {
  if (scene.params.wants_geometry()) {  // refuse before any work
    check_interior_support(scene);
    check_geometry_view(scene, rq.pass.camera);
  }
  GradientResult result = local_gradient(scene, rq);
  if (scene.params.wants_geometry() && dist::is_root()) {
    const Image adjoint =
        rq.adjoint_image ? *rq.adjoint_image : compute_loss(rq.loss, result.image, *rq.target).adjoint;
    const auto start = std::chrono::steady_clock::now();
    add_geometry_gradient(scene, adjoint, rq);
    result.adjoint_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  }
  if (!rq.accumulate) dist::reduce_gradients(scene.params);
  // Float overflow (a radiance near float's limit, an adjoint of 1e38) gives inf or NaN loss and
  // gradients that would be written as results: an error naming what overflowed instead.
  if (!std::isfinite(result.loss)) {
    // Name the side that is not finite: a render with NaN pixels points at the scene (its file).
    size_t bad = 0;
    for (float v : result.image.data) bad += !std::isfinite(v);
    const std::string what = rq.adjoint_image ? "the functional sum(dI * I)" : "the loss";
    if (bad)
      throw InputError(scene.source + ": the render has " + std::to_string(bad) +
                       " values that are NaN or infinite, so " + what + " is not finite");
    throw InputError(what + " is not finite: the render or the " +
                     std::string(rq.adjoint_image ? "adjoint image" : "target") + " exceeds float's range");
  }
  check_gradients_finite(scene.params);
  return result;
}

void check_gradients_finite(const ParamStore& params) {
  for (const Param& p : params.all())
    if (p.requires_grad)
      for (float g : p.grad)
        if (!std::isfinite(g))
          throw InputError("the gradient of '" + p.name +
                           "' is not finite: float overflow (a radiance or an adjoint image too large)");
}

void check_eps_range(const Param& p, double eps) {
  if (double(p.upper) - double(p.lower) > eps) return;
  std::ostringstream s;
  s << "--eps " << eps << " is not smaller than the width of the valid range [" << p.lower << ", " << p.upper
    << "] of '" << p.name << "'";
  throw InputError(s.str());
}

namespace {
// The regularized incomplete beta function I_x(a, b) by its continued fraction (modified Lentz),
// on the side of x where it converges fast.
double incomplete_beta(double a, double b, double x) {
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  if (x > (a + 1.0) / (a + b + 2.0)) return 1.0 - incomplete_beta(b, a, 1.0 - x);
  const double front =
      std::exp(std::lgamma(a + b) - std::lgamma(a) - std::lgamma(b) + a * std::log(x) + b * std::log1p(-x)) / a;
  const double tiny = 1e-300;
  double f = 1.0, c = 1.0, d = 0.0;
  for (int i = 0; i <= 1000; ++i) {
    const double m = double(i / 2);
    double term = 1.0;  // i = 0
    if (i > 0 && i % 2 == 0) term = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m));
    if (i % 2 == 1) term = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1));
    d = 1.0 + term * d;
    d = 1.0 / (std::abs(d) < tiny ? tiny : d);
    c = 1.0 + term / c;
    if (std::abs(c) < tiny) c = tiny;
    f *= c * d;
    if (std::abs(1.0 - c * d) < 1e-15) break;
  }
  return front * (f - 1.0);
}
}  // namespace

double student_t_two_sided_tail(double t, double dof) {
  if (!(dof > 0)) return std::numeric_limits<double>::quiet_NaN();
  return incomplete_beta(dof / 2.0, 0.5, dof / (dof + t * t));
}

double check_z_threshold(int seeds) {
  const double p = std::erfc(4.0 / std::sqrt(2.0));  // a normal's two-sided tail beyond 4σ
  if (seeds < 2) return 4.0;
  if (seeds > 100000) return 4.0;
  const double dof = double(seeds - 1);
  double lo = 4.0, hi = 1e7;  // t's quantile lies above the normal's
  for (int i = 0; i < 200; ++i) {
    const double mid = std::sqrt(lo * hi);
    (student_t_two_sided_tail(mid, dof) > p ? lo : hi) = mid;
  }
  return std::sqrt(lo * hi);
}

std::vector<uint32_t> positions_welding(const Scene& scene, int handle) {
  std::vector<uint32_t> first;
  for (const MeshPose& pose : scene.mesh_poses)
    if (pose.positions == handle) {
      const std::vector<float>& p0 = scene.params[handle].value;
      PositionWelder welder;  // as the edges weld (engine/core/weld.h)
      std::vector<uint32_t> first_of_id;
      first.resize(p0.size() / 3);
      for (uint32_t v = 0; v < first.size(); ++v) {
        const uint32_t id = welder.id(p0[3 * v], p0[3 * v + 1], p0[3 * v + 2]);
        if (id == first_of_id.size()) first_of_id.push_back(v);
        first[v] = first_of_id[id];
      }
    }
  return first;
}

namespace {
// The RMS over a check's directions of the finite differences' means: the typical size of ⟨∇, v⟩
// (E⟨g, v⟩² = |g|² for i.i.d. standard-normal v), against which errors are measured.
double fd_rms(const std::vector<CheckRow>& rows) {
  double largest = 0, sum = 0;  // scaled by the largest, so that no square overflows
  for (const CheckRow& r : rows) largest = std::max(largest, std::abs(r.finite_difference));
  if (largest == 0) return 0;
  for (const CheckRow& r : rows) sum += (r.finite_difference / largest) * (r.finite_difference / largest);
  return largest * std::sqrt(sum / double(rows.size()));
}
}  // namespace

CheckSteps check_steps(const Scene& scene, int h, int directions, double eps, uint64_t direction_seed) {
  const Param& param = scene.params[h];
  const std::vector<float>& theta = param.value;
  const std::string& name = param.name;
  const float lower = param.lower, upper = param.upper;
  check_eps_range(param, eps);
  std::mt19937_64 rng(direction_seed);
  std::normal_distribution<double> normal;
  const size_t count = static_cast<size_t>(directions);
  CheckSteps steps;
  steps.plus.resize(count), steps.minus.resize(count);
  // A vertex positions buffer: copies of a vertex at one position (a cube's split corners, a uv
  // seam) move together, as the geometry gradient assumes (boundary.h: welded edges). Moved
  // apart they open cracks between faces, a kink in the image (the crack's width is |step|) whose
  // central differences no derivative matches: a correct box.positions gradient failed at |z| 16
  // to 47 (pose scene, 256 seeds).
  const std::vector<uint32_t> weld = positions_welding(scene, h);
  for (int d = 0; d < directions; ++d) {
    // Elements are i.i.d. standard normal (not a unit vector): every element moves by about eps,
    // which keeps the perturbation far above float resolution even for million-texel buffers.
    std::vector<float>&p = steps.plus[size_t(d)], &m = steps.minus[size_t(d)];
    p.resize(theta.size()), m.resize(theta.size());
    std::vector<double> drawn(theta.size());
    for (size_t i = 0; i < theta.size(); ++i) {
      const double v = weld.empty() || weld[i / 3] == i / 3 ? normal(rng) : drawn[3 * weld[i / 3] + i % 3];
      drawn[i] = v;
      p[i] = float(double(theta[i]) + eps * v);
      m[i] = float(double(theta[i]) - eps * v);
      if (!std::isfinite(p[i]) || !std::isfinite(m[i]))
        throw InputError("--eps " + std::to_string(eps) + ": θ ± eps·v of '" + name + "' is not finite in float");
      p[i] = std::clamp(p[i], lower, upper), m[i] = std::clamp(m[i], lower, upper);
    }
    // Every element rounded back to θ (an eps below float resolution at θ): both renders would be
    // the same and the check would compare 0 with 0, and pass.
    if (p == m) {
      std::ostringstream s;
      s << "--eps " << eps << ": θ ± eps·v of '" << name
        << "' rounds to θ in float for every element (use a larger --eps)";
      throw InputError(s.str());
    }
  }
  return steps;
}

std::vector<CheckRow> directional_check(Scene& scene, const std::string& name, const GradientRequest& rq,
                                        int directions, double eps, uint64_t direction_seed, int seeds) {
  int h = scene.params.find(name);
  if (h < 0) throw InputError("unknown parameter '" + name + "' (see `backlight params`)");
  if (seeds < 1) throw InputError("--seeds must be ≥ 1");
  scene.params.require_grad({name});
  const std::vector<float> theta = scene.params[h].value;

  // Appearance parameters: the sampling tables are deliberately not rebuilt (see header). A
  // geometry parameter moves meshes or a camera: they are re-posed (and the BVH and emitter
  // tables rebuilt) for every render, or both renders would show the scene as it was.
  const bool geometry = scene.params[h].geometry;
  auto set_values = [&](const std::vector<float>& v) {
    scene.params[h].value = v;
    if (geometry) scene.prepare_sampling();
  };
  // θ goes back however the check ends: an error, a pass cancelled (Ctrl-C in Python), bad_alloc.
  struct Restore {
    std::function<void()> restore;
    ~Restore() {
      try {
        restore();
      } catch (...) {  // nothing to report it to from a destructor; θ itself is valid
      }
    }
  } restore_theta{[&] { set_values(theta); }};

  // The directions and their steps first. Steps are clamped into the valid range (a black texel
  // steps only upwards; the adjoint side predicts the change of the steps actually taken, below);
  // an eps as wide as the range itself is a mistake (|g| > 1, albedos of 1e30).
  const CheckSteps steps = check_steps(scene, h, directions, eps, direction_seed);
  const std::vector<std::vector<float>>&plus = steps.plus, &minus = steps.minus;
  const size_t count = static_cast<size_t>(directions);

  // Per seed: the adjoint's directional derivatives and the central differences of renders at that
  // seed (common random numbers), paired.
  std::vector<std::vector<double>> adjoint(count), fd(count);
  // One bar over the whole check (per seed: one gradient pass and two renders per direction),
  // instead of a bar per pass.
  Progress progress("check", uint64_t(seeds) * (1 + 2 * count), "passes", rq.pass.progress);
  for (int k = 0; k < seeds; ++k) {
    GradientRequest quiet = rq;
    quiet.pass.progress = false;
    quiet.pass.seed = rq.pass.seed + uint64_t(k);
    quiet.adjoint_seed = rq.adjoint_seed + uint64_t(k);
    set_values(theta);
    compute_gradient(scene, quiet);
    progress.advance(1);
    const std::vector<float> gradient = scene.params[h].grad;
    auto loss_at = [&](const std::vector<float>& v) {
      set_values(v);
      Image img = render(scene, quiet.pass);
      progress.advance(1);
      return rq.adjoint_image ? functional(*rq.adjoint_image, img) : compute_loss(rq.loss, img, *rq.target).value;
    };
    for (int d = 0; d < directions; ++d) {
      const std::vector<float>&p = plus[size_t(d)], &m = minus[size_t(d)];
      // The adjoint side predicts the change for the step float can actually represent,
      // ⟨∇loss, plus − minus⟩ / 2ε, so rounding of θ ± εv does not count as gradient error.
      double predicted = 0;
      for (size_t i = 0; i < theta.size(); ++i) predicted += double(gradient[i]) * (double(p[i]) - double(m[i]));
      adjoint[size_t(d)].push_back(predicted / (2 * eps));
      // A step may fail (a triangle made degenerate): restore_theta puts the scene back.
      const double loss_plus = loss_at(p), loss_minus = loss_at(m);
      const double difference = (loss_plus - loss_minus) / (2 * eps);
      if (!std::isfinite(difference)) {
        throw InputError("--eps " + std::to_string(eps) + ": the renders at θ ± eps·v of '" + name +
                         "' give a loss that is not finite (use a smaller --eps)");
      }
      fd[size_t(d)].push_back(difference);
    }
  }

  auto mean_and_stderr = [](const std::vector<double>& xs, double& mean, double& stderr_of_mean) {
    mean = 0;
    for (double x : xs) mean += x / double(xs.size());
    double var = 0;
    for (double x : xs) var += (x - mean) * (x - mean);
    stderr_of_mean = xs.size() > 1 ? std::sqrt(var / double(xs.size() - 1) / double(xs.size())) : 0.0;
  };
  std::vector<CheckRow> rows;
  for (int d = 0; d < directions; ++d) {
    CheckRow row;
    mean_and_stderr(adjoint[size_t(d)], row.adjoint, row.adjoint_stderr);
    mean_and_stderr(fd[size_t(d)], row.finite_difference, row.fd_stderr);
    row.relative_error =
        std::abs(row.adjoint - row.finite_difference) / std::max(std::abs(row.finite_difference), 1e-30);
    if (seeds > 1) {
      std::vector<double> paired(static_cast<size_t>(seeds));
      for (int k = 0; k < seeds; ++k) paired[size_t(k)] = adjoint[size_t(d)][size_t(k)] - fd[size_t(d)][size_t(k)];
      double mean = 0, se = 0;
      mean_and_stderr(paired, mean, se);
      row.difference_stderr = se;
      row.z = se > 0 ? mean / se : (mean == 0 ? 0.0 : std::numeric_limits<double>::infinity());
    }
    rows.push_back(row);
  }
  const double rms = fd_rms(rows);
  for (CheckRow& r : rows) r.rms_relative_error = std::abs(r.adjoint - r.finite_difference) / std::max(rms, 1e-30);
  return rows;
}

CheckSummary summarize_check(const std::vector<CheckRow>& rows, int seeds, double tolerance) {
  CheckSummary s;
  s.threshold = check_z_threshold(seeds);
  const double rms = fd_rms(rows);
  double worst = 0;
  for (const CheckRow& r : rows) {
    const double error = std::abs(r.adjoint - r.finite_difference) / std::max(rms, 1e-30);  // rms_relative_error
    const bool ok = error <= tolerance || (seeds > 1 && std::abs(r.z) < s.threshold);
    s.ok.push_back(ok);
    s.passed = s.passed && ok;
    if (seeds > 1) {
      const double caught = std::max(s.threshold * r.difference_stderr, tolerance * rms) / std::max(rms, 1e-30);
      s.resolution.push_back(caught);
      worst = std::max(worst, caught);
    } else {
      s.resolution.push_back(std::numeric_limits<double>::quiet_NaN());
    }
  }
  s.nothing_compared = std::all_of(rows.begin(), rows.end(),
                                   [](const CheckRow& r) { return r.adjoint == 0.0 && r.finite_difference == 0.0; });
  if (s.nothing_compared) {
    s.passed = false;
    s.ok.assign(rows.size(), false);
  }
  if (seeds > 1 && !rows.empty()) {
    s.resolution_overall = worst;
    // A pass that could not have seen a 25% error is no pass (helper-39: a sign error passed 16
    // seeds of a thin medium, and the README's own example passed at 110%).
    s.inconclusive = s.passed && worst > 0.25;
  }
  return s;
}

namespace {
// A grid parameter's values (or gradient) as a VolumeGrid in its medium's box.
VolumeGrid grid_values(const Scene& scene, const Param& p, const std::vector<float>& values) {
  VolumeGrid g;
  g.z = p.shape[0], g.y = p.shape[1], g.x = p.shape[2], g.channels = p.shape[3];
  g.data = values;
  for (const auto& m : scene.media)
    if (m.grid && (scene.params[m.density].name == p.name || scene.params[m.albedo].name == p.name))
      g.bbox_min = m.bbox_min, g.bbox_max = m.bbox_max;
  return g;
}

// <stem>.vdb, <stem>.vol and <stem>.png (mid-slices and maximum projection; for gradients, of
// |value|, scaled to the largest).
void write_grid_files(const Scene& scene, const Param& p, const std::vector<float>& values, const std::string& stem,
                      bool magnitude) {
  const VolumeGrid g = grid_values(scene, p, values);
  write_vdb(stem + ".vdb", g, p.name);
  write_vol(stem + ".vol", g);
  std::vector<float> shown = values;
  float vmax = 0.f;
  for (float& v : shown) vmax = std::max(vmax, v = magnitude ? std::abs(v) : v);
  if (magnitude) {  // Monte Carlo gradients have outliers: scale to the 99th percentile instead
    std::vector<float> sorted = shown;
    const size_t k = sorted.size() * 99 / 100;
    std::nth_element(sorted.begin(), sorted.begin() + ptrdiff_t(k), sorted.end());
    if (sorted[k] > 0.f) vmax = sorted[k];
  }
  write_grid_picture(stem + ".png", grid_sheet({&shown, g.x, g.y, g.z, g.channels}, vmax > 0.f ? vmax : 1.f));
}
}  // namespace

void dump_parameter_values(const Scene& scene, const std::string& dir) {
  const ParamStore& params = scene.params;
  ensure_output_folder(dir);
  // Temporaries of dumps killed before their rename (of processes no longer running) piled up,
  // 8 MB per grid (helper-45): those named after this scene's parameters or params.json go.
  std::string stems = "params";
  for (const auto& p : params.all()) stems += '|' + regex_escaped(p.name);
  remove_stale_temporaries(dir, false, stems);
  nlohmann::json small = nlohmann::json::object();
  for (const auto& p : params.all()) {
    if (p.shape.size() == 4) {
      write_grid_files(scene, p, p.value, (fs::path(dir) / p.name).string(), false);
    } else if (p.is_image()) {
      Image img(p.width(), p.height(), p.channels());
      img.data = p.value;
      write_image((fs::path(dir) / (p.name + ".exr")).string(), img);
    } else {
      small[p.name] = {{"shape", p.shape}, {"value", p.value}};
    }
  }
  write_text_atomic((fs::path(dir) / "params.json").string(), small.dump(1) + "\n");
}

void write_gradient_outputs(const Scene& scene, const GradientRequest& rq, const GradientResult& r,
                            const std::string& dir) {
  ensure_output_folder(dir);
  // gradients.json, written last, lists the set: a folder that has it holds a complete one. An
  // earlier run's goes first, so a write failing half-way does not leave it naming a mix of old
  // and new files; so do that run's gradient files (a parameter it differentiated and this one
  // does not kept its file next to a gradients.json that no longer named it), and the
  // temporaries of runs killed before their rename.
  std::error_code ec;
  fs::remove(fs::path(dir) / "gradients.json", ec);
  static const std::regex earlier(R"(^.+\.grad\.(exr|vdb|vol|png)$)");
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code e;
    if (it->is_regular_file(e) && std::regex_match(it->path().filename().string(), earlier)) fs::remove(it->path(), e);
  }
  remove_stale_temporaries(dir, false, R"(image|gradients|.+\.grad)");
  write_image((fs::path(dir) / "image.exr").string(), r.image);
  nlohmann::json j;
  j["method"] = method_name(rq.method);
  if (rq.adjoint_image) {
    j["functional"] = r.loss;
    // Per channel, summed in double: Σ a_c·I_c (e.g. to check an exact emitter gradient).
    std::vector<double> per_channel(3, 0.0);
    for (size_t i = 0; i < r.image.data.size(); ++i)
      per_channel[i % 3] += double(rq.adjoint_image->data[i]) * double(r.image.data[i]);
    j["functional_per_channel"] = per_channel;
  } else {
    j["loss"] = r.loss;
    j["loss_type"] = loss_name(rq.loss);
  }
  j["spp"] = rq.pass.spp;
  j["seed"] = rq.pass.seed;
  j["adjoint_seed"] = rq.adjoint_seed;
  j["max_depth"] = scene.settings.max_depth;
  j["rr_depth"] = scene.settings.rr_depth;
  j["timings"] = {{"primal_seconds", r.primal_seconds},
                  {"adjoint_seconds", r.adjoint_seconds},
                  {"total_seconds", r.primal_seconds + r.adjoint_seconds}};
  if (rq.method == GradientMethod::Taped)
    j["tape"] = {{"bytes", r.tape_bytes}, {"entries", r.tape_entries}, {"budget_bytes", r.tape_budget_bytes}};
  if (!r.peak_rss_bytes.empty()) {
    // One entry per MPI rank (one on a single process): the memory each process needed.
    nlohmann::json ranks = nlohmann::json::array();
    for (size_t i = 0; i < r.peak_rss_bytes.size(); ++i) {
      ranks.push_back({{"rank", i}, {"peak_rss_mb", r.peak_rss_bytes[i] / 1048576.0}});
      if (i < r.mpi_seconds.size()) ranks.back()["mpi_seconds"] = r.mpi_seconds[i];
    }
    j["ranks"] = ranks;
  }
  nlohmann::json params = nlohmann::json::object();
  for (const auto& p : scene.params.all()) {
    if (!p.requires_grad) continue;
    double norm = 0;
    for (float g : p.grad) norm += double(g) * double(g);
    nlohmann::json e{{"shape", p.shape}, {"size", p.size()}, {"grad_norm", std::sqrt(norm)}};
    // Up to 64 values inline; grids as .vdb/.vol/.png; images (whatever their size, as
    // `params --dump` writes them) and larger vectors as EXR: an image [H, W, C] as itself, a
    // list of vectors [N, C] (a mesh's positions) as an N×1 image of C channels, anything else
    // as a size×1 single-channel image.
    if (p.size() <= 64) e["grad"] = p.grad;
    if (p.shape.size() == 4) {
      if (p.size() > 64) {
        write_grid_files(scene, p, p.grad, (fs::path(dir) / (p.name + ".grad")).string(), true);
        e["file"] = p.name + ".grad.vdb";
        e["files"] = {p.name + ".grad.vdb", p.name + ".grad.vol", p.name + ".grad.png"};
      }
    } else if (p.is_image() || p.size() > 64) {
      std::string file = p.name + ".grad.exr";
      Image img;
      if (p.is_image())
        img = Image(p.width(), p.height(), p.channels());
      else if (p.shape.size() == 2 && p.shape[1] >= 1 && p.shape[1] <= 4)
        img = Image(p.shape[0], 1, p.shape[1]);
      else
        img = Image(int(p.size()), 1, 1);
      img.data = p.grad;
      write_image((fs::path(dir) / file).string(), img);
      e["file"] = file;
    }
    params[p.name] = e;
  }
  j["parameters"] = params;
  write_text_atomic((fs::path(dir) / "gradients.json").string(), j.dump(1) + "\n");
}

}  // namespace bl
