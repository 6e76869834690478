#include "engine/integrators/boundary.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <unordered_map>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "engine/core/errors.h"
#include "engine/integrators/edges.h"
#include "engine/integrators/path.h"
#include "engine/integrators/render.h"
#include "engine/io/progress.h"

namespace bl {

namespace {

using edges::add_to_edge;
using edges::candidate_from;
using edges::edge_topology;
using edges::EdgeTable;
using edges::fold_from;
using edges::MeshEdge;
using edges::on_faces;

// Film position of world point p and the rows of its Jacobian, in double (no near-plane test).
void project_raw(const Camera& cam, const Vec3d& p, double* x, double* y, Vec3d* jx, Vec3d* jy) {
  const Vec3d d = p - Vec3d(cam.origin), right(cam.right), up(cam.true_up), forward(cam.forward);
  const double cx = dot(d, right), cy = dot(d, up), cz = dot(d, forward);
  const double kx = double(cam.width) / (2.0 * double(cam.tan_x)), ky = double(cam.height) / (2.0 * double(cam.tan_y));
  *x = 0.5 * double(cam.width) + kx * cx / cz;
  *y = 0.5 * double(cam.height) - ky * cy / cz;
  *jx = (right * cz - forward * cx) * (kx / (cz * cz));
  *jy = (up * cz - forward * cy) * (-ky / (cz * cz));
}

// One end of a projected edge: its film position and how it moves with the edge's own vertex at
// this end and with the other one (non-zero when this end was clipped to the near plane: the
// clipped point slides along the edge as either vertex moves).
struct EndProjection {
  double x = 0, y = 0;
  Vec3d jx_own, jy_own, jx_other, jy_other;
};

// Projects the end `own` of the edge (own, other), clipped to the near plane when behind it.
// False when the whole edge is behind.
bool project_end(const Camera& cam, const Vec3f& own_f, const Vec3f& other_f, EndProjection* e) {
  const Vec3d own(own_f), other(other_f), forward(cam.forward), origin(cam.origin);
  const double c = double(cam.near_clip);
  const double z_own = dot(own - origin, forward), z_other = dot(other - origin, forward);
  if (z_own > c) {
    project_raw(cam, own, &e->x, &e->y, &e->jx_own, &e->jy_own);
    e->jx_other = e->jy_other = Vec3d(0.0);
    return true;
  }
  if (!(z_other > c)) return false;
  // q = own + λ (other − own) on the near plane; dq = (1 − λ) M δown + λ M δother with
  // M = I − (other − own) forwardᵀ / Δ, Δ = z_other − z_own.
  const double delta = z_other - z_own, lambda = (c - z_own) / delta;
  const Vec3d edge = other - own;
  Vec3d jx, jy;
  project_raw(cam, own + edge * lambda, &e->x, &e->y, &jx, &jy);
  jx = jx - forward * (dot(jx, edge) / delta);
  jy = jy - forward * (dot(jy, edge) / delta);
  e->jx_own = jx * (1 - lambda);
  e->jy_own = jy * (1 - lambda);
  e->jx_other = jx * lambda;
  e->jy_other = jy * lambda;
  return true;
}

using Accumulator = std::vector<std::vector<Vec3d>>;

// Mesh index → its entry in result.vertices (−1: not wanted).
std::vector<int> slots_of(const Scene& scene, const GeometryGradient& result) {
  std::vector<int> slot(scene.meshes.size(), -1);
  for (size_t k = 0; k < result.meshes.size(); ++k) slot[size_t(result.meshes[k])] = int(k);
  return slot;
}

// Per-thread gradient buffers shaped like result.vertices, allocated once per worker thread.
tbb::enumerable_thread_specific<Accumulator> per_thread_buffers(const GeometryGradient& result) {
  return tbb::enumerable_thread_specific<Accumulator>([&result] {
    Accumulator acc(result.vertices.size());
    for (size_t k = 0; k < acc.size(); ++k) acc[k].assign(result.vertices[k].size(), Vec3d(0.0));
    return acc;
  });
}

void reduce_into(tbb::enumerable_thread_specific<Accumulator>& per_thread, GeometryGradient& result) {
  for (const Accumulator& acc : per_thread)
    for (size_t k = 0; k < acc.size(); ++k)
      for (size_t v = 0; v < acc[k].size(); ++v) result.vertices[k][v] += acc[k][v];
}

}  // namespace

bool clip_to_film(double ax, double ay, double bx, double by, double w, double h, double* t0, double* t1) {
  double lo = 0, hi = 1;
  const double dx = bx - ax, dy = by - ay;
  const double p[4] = {-dx, dx, -dy, dy}, q[4] = {ax, w - ax, ay, h - ay};
  for (int k = 0; k < 4; ++k) {
    if (p[k] == 0) {
      if (q[k] < 0) return false;
      continue;
    }
    const double r = q[k] / p[k];
    if (p[k] < 0)
      lo = std::max(lo, r);
    else
      hi = std::min(hi, r);
  }
  *t0 = lo;
  *t1 = hi;
  return hi > lo;
}

GeometryGradient primary_boundary_gradient(const Scene& scene, const Image& adjoint, const BoundaryOptions& options) {
  const Camera& cam = scene.cameras.at(size_t(options.camera));
  GeometryGradient result = empty_geometry_gradient(scene, cam, adjoint, options.meshes, "boundary gradient");
  const std::vector<int> slot = slots_of(scene, result);

  // Project and clip every candidate; the sampling table is over clipped projected lengths.
  const EdgeTable table = edge_topology(scene, result.meshes, &cam.origin);
  struct Projected {
    uint32_t edge;
    EndProjection a, b;  // the ends at the edge's p0 and p1
    double t0, t1;       // the part inside the film
    bool fold;           // both faces turned the same way from the camera (fold_from)
  };
  std::vector<Projected> projected;
  std::vector<double> cdf;
  double total = 0;
  for (uint32_t i = 0; i < uint32_t(table.edges.size()); ++i) {
    const MeshEdge& e = table.edges[i];
    Projected pr{};
    pr.edge = i;
    pr.fold = fold_from(scene, e, cam.origin);
    if (!project_end(cam, e.p0, e.p1, &pr.a) || !project_end(cam, e.p1, e.p0, &pr.b)) continue;
    if (!clip_to_film(pr.a.x, pr.a.y, pr.b.x, pr.b.y, double(cam.width), double(cam.height), &pr.t0, &pr.t1)) continue;
    const double len = std::hypot(pr.b.x - pr.a.x, pr.b.y - pr.a.y) * (pr.t1 - pr.t0);
    if (!(len > 0.0)) continue;
    projected.push_back(pr);
    cdf.push_back(total += len);
  }
  result.edges = int(projected.size());
  result.edge_length = total;
  const uint64_t n = options.samples ? options.samples : uint64_t(cam.width) * uint64_t(cam.height);
  result.samples = n;
  if (projected.empty() || n == 0) return result;

  auto per_thread = per_thread_buffers(result);
  // Random numbers of edge sample k: a stream of its own (pixel k, sample index kEdgeStream);
  // dimensions 0 and 1 (the camera's in a render) pick the edge and the point on it.
  constexpr uint64_t kEdgeStream = 0xed9e5a3b1c00ull;
  const double weight_scale = total / double(n);
  Progress progress("boundary", n, "samples", options.progress);
  tbb::parallel_for(tbb::blocked_range<uint64_t>(0, n, 256), [&](const tbb::blocked_range<uint64_t>& range) {
    if (cancelled(options.cancel)) return;
    Accumulator& acc = per_thread.local();
    NoObserver none;
    struct Advance {  // counts the range however the loop leaves it (its `continue`s)
      Progress& progress;
      uint64_t n;
      ~Advance() { progress.advance(n); }
    } advance{progress, range.size()};
    for (uint64_t k = range.begin(); k != range.end(); ++k) {
      const PathSampler sampler(options.seed, k, kEdgeStream);
      // 53 bits, as for light samples (engine/core/distribution.h): edges by the 10⁵ are ~1e-6 each.
      const double u = sampler.get_double(Dim::kPixelX) * total;
      const size_t pick = std::min(size_t(std::upper_bound(cdf.begin(), cdf.end(), u) - cdf.begin()), cdf.size() - 1);
      const Projected& pr = projected[pick];
      const double s = pr.t0 + double(sampler.get(Dim::kPixelY)) * (pr.t1 - pr.t0);
      const double ex = pr.b.x - pr.a.x, ey = pr.b.y - pr.a.y;
      const double x = pr.a.x + s * ex, y = pr.a.y + s * ey;
      const int px = int(std::floor(x)), py = int(std::floor(y));
      if (px < 0 || py < 0 || px >= cam.width || py >= cam.height) continue;
      const double inv = 1.0 / std::sqrt(ex * ex + ey * ey);
      const double nx = -ey * inv, ny = ex * inv;
      const double eps = double(options.side_offset);
      const Ray ray_minus = cam.generate(float(x - eps * nx), float(y - eps * ny)),
                ray_plus = cam.generate(float(x + eps * nx), float(y + eps * ny));
      const Hit hit_minus = scene.geometry->intersect(ray_minus), hit_plus = scene.geometry->intersect(ray_plus);
      const MeshEdge& edge = table.edges[pr.edge];
      // A fold near an outline: a side off the mesh sees the outline's jump, not the fold's.
      if (pr.fold && !(on_faces(edge, hit_minus) && on_faces(edge, hit_plus))) continue;
      const Vec3f minus = trace_path<float>(scene, PathStart{ray_minus, 1, 0.f, cam.medium, &hit_minus}, sampler, none);
      const Vec3f plus = trace_path<float>(scene, PathStart{ray_plus, 1, 0.f, cam.medium, &hit_plus}, sampler, none);
      const Vec3f delta = minus - plus;
      const double w =
          (double(adjoint.at(px, py, 0)) * double(delta.x) + double(adjoint.at(px, py, 1)) * double(delta.y) +
           double(adjoint.at(px, py, 2)) * double(delta.z)) *
          weight_scale;
      if (w == 0.0) continue;
      // dF += w · n·((1 − s) dx_a + s dx_b), each end's film motion dx linear in both vertices.
      const Vec3d ga =
          ((pr.a.jx_own * nx + pr.a.jy_own * ny) * (1 - s) + (pr.b.jx_other * nx + pr.b.jy_other * ny) * s) * w;
      const Vec3d gb =
          ((pr.a.jx_other * nx + pr.a.jy_other * ny) * (1 - s) + (pr.b.jx_own * nx + pr.b.jy_own * ny) * s) * w;
      const MeshEdge& e = table.edges[pr.edge];
      add_to_edge(table, e, ga, gb, acc[size_t(slot[size_t(e.mesh)])]);
    }
  });
  progress.finish();
  reduce_into(per_thread, result);
  return result;
}

GeometryGradient empty_geometry_gradient(const Scene& scene, const Camera& cam, const Image& adjoint,
                                         std::vector<int> meshes, const char* what, bool normals) {
  if (adjoint.width != cam.width || adjoint.height != cam.height || adjoint.channels != 3)
    throw InputError(std::string(what) + ": the adjoint image is " + std::to_string(adjoint.width) + "x" +
                     std::to_string(adjoint.height) + "x" + std::to_string(adjoint.channels) + ", the camera's film " +
                     std::to_string(cam.width) + "x" + std::to_string(cam.height) + "x3");
  if (meshes.empty())
    for (int i = 0; i < int(scene.meshes.size()); ++i) meshes.push_back(i);
  GeometryGradient result;
  result.meshes = meshes;
  result.vertices.resize(meshes.size());
  if (normals) result.normals.resize(meshes.size());
  for (size_t k = 0; k < meshes.size(); ++k) {
    const Mesh& m = scene.meshes[size_t(meshes[k])];
    result.vertices[k].assign(m.vertex_count(), Vec3d(0.0));
    if (normals && !m.normals.empty()) result.normals[k].assign(m.vertex_count(), Vec3d(0.0));
  }
  return result;
}

PoseGradient pose_gradient(const Mesh& mesh, const std::vector<Vec3d>& vertex_gradient, const Vec3f& pivot) {
  PoseGradient g{Vec3d(0.0), Vec3d(0.0), Vec3d(0.0)};
  for (size_t v = 0; v < mesh.vertex_count(); ++v) {
    const Vec3d& d = vertex_gradient[v];
    const Vec3d r = Vec3d(mesh.positions[v] - pivot);
    g.translate += d;
    g.scale += r * d;
    g.rotate += cross(r, d);
  }
  return g;
}

PoseGradient pose_gradient(const Mesh& mesh, const std::vector<Vec3d>& vertex_gradient,
                           const std::vector<Vec3d>& normal_gradient, const Vec3f& pivot) {
  PoseGradient g = pose_gradient(mesh, vertex_gradient, pivot);
  if (normal_gradient.empty() || mesh.normals.empty()) return g;
  for (size_t v = 0; v < mesh.vertex_count(); ++v) {
    const Vec3d& d = normal_gradient[v];
    const Vec3d n(mesh.normals[v]);
    g.rotate += cross(n, d);  // the normal turns by ω × n
    // n' = normalise(n ⊘ s): ∂n'/∂s_i = −n_i (e_i − n n_i) at s = 1.
    const double dn = dot(d, n);
    g.scale -= Vec3d(n.x * (d.x - dn * n.x), n.y * (d.y - dn * n.y), n.z * (d.z - dn * n.z));
  }
  return g;
}

GeometryGradient& operator+=(GeometryGradient& a, const GeometryGradient& b) {
  if (a.meshes != b.meshes) throw InputError("geometry gradients over different meshes cannot be added");
  if (a.normals.size() < b.normals.size()) a.normals.resize(b.normals.size());
  for (size_t k = 0; k < a.meshes.size(); ++k) {
    for (size_t v = 0; v < a.vertices[k].size(); ++v) a.vertices[k][v] += b.vertices[k][v];
    if (k < b.normals.size() && !b.normals[k].empty()) {
      if (a.normals[k].empty()) a.normals[k].assign(b.normals[k].size(), Vec3d(0.0));
      for (size_t v = 0; v < a.normals[k].size(); ++v) a.normals[k][v] += b.normals[k][v];
    }
  }
  a.camera_origin += b.camera_origin;
  a.camera_rotate += b.camera_rotate;
  a.samples += b.samples;
  return a;
}

CameraPoseGradient camera_pose_gradient(const Scene& scene, const GeometryGradient& g, const Camera& cam) {
  if (g.meshes.size() != scene.meshes.size())
    throw InputError("camera pose gradient: the boundary gradient must cover every mesh");
  CameraPoseGradient c{Vec3d(0.0), Vec3d(0.0)};
  for (size_t k = 0; k < g.meshes.size(); ++k) {
    const PoseGradient p = pose_gradient(scene.meshes[size_t(g.meshes[k])], g.vertices[k], cam.origin);
    c.origin -= p.translate;
    c.rotate -= p.rotate;
  }
  return c;
}

}  // namespace bl
