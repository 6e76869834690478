#include "engine/integrators/boundary.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <unordered_map>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "engine/core/errors.h"
#include "engine/integrators/path.h"

namespace bl {

namespace {

// An edge of a mesh after welding: its two end positions and, per adjacent face, that face's
// vertex indices at the two ends (copies of the same position when the mesh splits vertices).
struct MeshEdge {
  int mesh = 0;
  Vec3f p0, p1;
  uint32_t first_copy = 0, faces = 0;  // into EdgeTable::copies, `faces` pairs
  uint32_t f0 = 0, f1 = 0;             // the two faces of a two-face edge
  bool always = false;                 // boundary, non-manifold or crease: a candidate from everywhere
};

struct EdgeTable {
  std::vector<MeshEdge> edges;
  std::vector<uint32_t> copies;  // pairs (vertex at p0, vertex at p1) per adjacent face
};

// Welding key: a position's bits, −0 taken as +0 (a sphere's pole copies differ only there).
// Positions that are merely close do not weld (a sphere's seam: cos 2π ≠ 1 in float); their
// edges count as boundary edges, which costs samples but no bias where both sides see the same.
struct PositionKey {
  uint32_t x, y, z;
  bool operator==(const PositionKey& o) const { return x == o.x && y == o.y && z == o.z; }
};
struct PositionHash {
  size_t operator()(const PositionKey& k) const { return size_t(mix64((uint64_t(k.x) << 32 | k.y) ^ mix64(k.z))); }
};

uint32_t weld_id(const Vec3f& p, std::unordered_map<PositionKey, uint32_t, PositionHash>& ids) {
  const float x = p.x + 0.f, y = p.y + 0.f, z = p.z + 0.f;  // −0 + 0 = +0
  PositionKey key;
  std::memcpy(&key.x, &x, 4);
  std::memcpy(&key.y, &y, 4);
  std::memcpy(&key.z, &z, 4);
  return ids.emplace(key, uint32_t(ids.size())).first->second;
}

bool front_facing(const Mesh& m, uint32_t face, const Vec3f& eye) {
  return dot(m.face_normals[face], eye - m.positions[m.indices[3 * size_t(face)]]) > 0.f;
}

// Whether the shading is discontinuous across an edge between two faces (vertex indices of the
// faces' copies of its ends).
bool shading_crease(const Mesh& m, uint32_t f0, uint32_t f1, const uint32_t* c0, const uint32_t* c1) {
  const Vec3f &n0 = m.face_normals[f0], &n1 = m.face_normals[f1];
  if (dot(n0, n1) > 1.f - 1e-6f) return false;  // coplanar: the same plane on both sides
  if (m.normals.empty()) return true;           // flat shading
  for (int k = 0; k < 2; ++k) {
    const Vec3f &a = m.normals[c0[k]], &b = m.normals[c1[k]];
    if (a.x != b.x || a.y != b.y || a.z != b.z) return true;  // split normals
  }
  return false;
}

// Whether an edge is a discontinuity seen from `eye`: always for boundary, non-manifold and
// crease edges, for the others when one face is front- and the other back-facing.
bool candidate_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye) {
  if (e.always) return true;
  const Mesh& m = scene.meshes[size_t(e.mesh)];
  return front_facing(m, e.f0, eye) != front_facing(m, e.f1, eye);
}

// The edges of the meshes in `wanted` that can be a discontinuity seen from somewhere (all but
// those between two coplanar faces with continuous shading), or, given an eye, those that are one
// seen from it.
EdgeTable edge_topology(const Scene& scene, const std::vector<int>& wanted, const Vec3f* eye = nullptr) {
  EdgeTable table;
  for (int mi : wanted) {
    const Mesh& m = scene.meshes[size_t(mi)];
    if (scene.materials[size_t(m.material)].is_null) continue;  // invisible
    std::unordered_map<PositionKey, uint32_t, PositionHash> ids;
    std::vector<uint32_t> welded(m.vertex_count());
    for (size_t v = 0; v < welded.size(); ++v) welded[v] = weld_id(m.positions[v], ids);
    // (welded end a < welded end b, face, corner) for every face edge, grouped by ends.
    struct Record {
      uint64_t key;
      uint32_t face, corner;
    };
    std::vector<Record> records;
    records.reserve(m.indices.size());
    for (uint32_t f = 0; f < uint32_t(m.triangle_count()); ++f) {
      if (!(m.triangle_area(f) > 0.f)) continue;  // degenerate: no visible face
      for (uint32_t c = 0; c < 3; ++c) {
        const uint32_t a = welded[m.indices[3 * size_t(f) + c]], b = welded[m.indices[3 * size_t(f) + (c + 1) % 3]];
        if (a == b) continue;
        records.push_back({uint64_t(std::min(a, b)) << 32 | std::max(a, b), f, c});
      }
    }
    std::sort(records.begin(), records.end(),
              [](const Record& x, const Record& y) { return x.key != y.key ? x.key < y.key : x.face < y.face; });
    for (size_t i = 0; i < records.size();) {
      size_t j = i;
      while (j < records.size() && records[j].key == records[i].key) ++j;
      // Ends in the welded order: end 0 is the smaller welded id.
      const uint32_t end0 = uint32_t(records[i].key >> 32);
      MeshEdge e;
      e.mesh = mi;
      e.first_copy = uint32_t(table.copies.size());
      e.faces = uint32_t(j - i);
      for (size_t k = i; k < j; ++k) {
        const uint32_t f = records[k].face, c = records[k].corner;
        uint32_t va = m.indices[3 * size_t(f) + c], vb = m.indices[3 * size_t(f) + (c + 1) % 3];
        if (welded[va] != end0) std::swap(va, vb);
        table.copies.push_back(va);
        table.copies.push_back(vb);
      }
      const uint32_t* copies = table.copies.data() + e.first_copy;
      e.p0 = m.positions[copies[0]];
      e.p1 = m.positions[copies[1]];
      bool keep = true;
      e.always = e.faces != 2;  // boundary or non-manifold
      if (e.faces == 2) {
        e.f0 = records[i].face;
        e.f1 = records[i + 1].face;
        e.always = shading_crease(m, e.f0, e.f1, copies, copies + 2);
        keep = e.always || dot(m.face_normals[e.f0], m.face_normals[e.f1]) <= 1.f - 1e-6f;  // can be a silhouette
      }
      if (keep && eye) keep = candidate_from(scene, e, *eye);
      if (keep)
        table.edges.push_back(e);
      else
        table.copies.resize(e.first_copy);
      i = j;
    }
  }
  return table;
}

// Liang–Barsky: the parameter range [t0, t1] of a + t·(b − a), t ∈ [0, 1], inside [0, w]×[0, h].
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

// Checks the adjoint image against the camera and sets up zero gradients for `meshes` (all when
// empty).
BoundaryGradient empty_result(const Scene& scene, const Camera& cam, const Image& adjoint, std::vector<int> meshes) {
  if (adjoint.width != cam.width || adjoint.height != cam.height || adjoint.channels != 3)
    throw InputError("boundary gradient: the adjoint image is " + std::to_string(adjoint.width) + "x" +
                     std::to_string(adjoint.height) + "x" + std::to_string(adjoint.channels) + ", the camera's film " +
                     std::to_string(cam.width) + "x" + std::to_string(cam.height) + "x3");
  if (meshes.empty())
    for (int i = 0; i < int(scene.meshes.size()); ++i) meshes.push_back(i);
  BoundaryGradient result;
  result.meshes = meshes;
  result.vertices.resize(meshes.size());
  for (size_t k = 0; k < meshes.size(); ++k)
    result.vertices[k].assign(scene.meshes[size_t(meshes[k])].vertex_count(), Vec3d(0.0));
  return result;
}

using Accumulator = std::vector<std::vector<Vec3d>>;

// Adds the end gradients ga (at the edge's p0) and gb (at p1) to every face's copy of them.
void add_to_edge(const EdgeTable& table, const MeshEdge& e, const Vec3d& ga, const Vec3d& gb, std::vector<Vec3d>& g) {
  const uint32_t* copies = table.copies.data() + e.first_copy;
  const double share = 1.0 / double(e.faces);
  for (uint32_t f = 0; f < e.faces; ++f) {
    g[copies[2 * f]] += ga * share;
    g[copies[2 * f + 1]] += gb * share;
  }
}

// Mesh index → its entry in result.vertices (−1: not wanted).
std::vector<int> slots_of(const Scene& scene, const BoundaryGradient& result) {
  std::vector<int> slot(scene.meshes.size(), -1);
  for (size_t k = 0; k < result.meshes.size(); ++k) slot[size_t(result.meshes[k])] = int(k);
  return slot;
}

// Per-thread gradient buffers shaped like result.vertices, allocated once per worker thread.
tbb::enumerable_thread_specific<Accumulator> per_thread_buffers(const BoundaryGradient& result) {
  return tbb::enumerable_thread_specific<Accumulator>([&result] {
    Accumulator acc(result.vertices.size());
    for (size_t k = 0; k < acc.size(); ++k) acc[k].assign(result.vertices[k].size(), Vec3d(0.0));
    return acc;
  });
}

void reduce_into(tbb::enumerable_thread_specific<Accumulator>& per_thread, BoundaryGradient& result) {
  for (const Accumulator& acc : per_thread)
    for (size_t k = 0; k < acc.size(); ++k)
      for (size_t v = 0; v < acc[k].size(); ++v) result.vertices[k][v] += acc[k][v];
}

}  // namespace

BoundaryGradient primary_boundary_gradient(const Scene& scene, const Image& adjoint, const BoundaryOptions& options) {
  const Camera& cam = scene.cameras.at(size_t(options.camera));
  BoundaryGradient result = empty_result(scene, cam, adjoint, options.meshes);
  const std::vector<int> slot = slots_of(scene, result);

  // Project and clip every candidate; the sampling table is over clipped projected lengths.
  const EdgeTable table = edge_topology(scene, result.meshes, &cam.origin);
  struct Projected {
    uint32_t edge;
    EndProjection a, b;  // the ends at the edge's p0 and p1
    double t0, t1;       // the part inside the film
  };
  std::vector<Projected> projected;
  std::vector<double> cdf;
  double total = 0;
  for (uint32_t i = 0; i < uint32_t(table.edges.size()); ++i) {
    const MeshEdge& e = table.edges[i];
    Projected pr{};
    pr.edge = i;
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
  tbb::parallel_for(tbb::blocked_range<uint64_t>(0, n, 256), [&](const tbb::blocked_range<uint64_t>& range) {
    Accumulator& acc = per_thread.local();
    NoObserver none;
    for (uint64_t k = range.begin(); k != range.end(); ++k) {
      const PathSampler sampler(options.seed, k, kEdgeStream);
      const double u = double(sampler.get(Dim::kPixelX)) * total;
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
      const Vec3f minus = trace_path<float>(
          scene, PathStart{cam.generate(float(x - eps * nx), float(y - eps * ny)), 1, 0.f, cam.medium}, sampler, none);
      const Vec3f plus = trace_path<float>(
          scene, PathStart{cam.generate(float(x + eps * nx), float(y + eps * ny)), 1, 0.f, cam.medium}, sampler, none);
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
  reduce_into(per_thread, result);
  return result;
}

BoundaryGradient secondary_boundary_gradient(const Scene& scene, const Image& adjoint,
                                             const SecondaryOptions& options) {
  const Camera& cam = scene.cameras.at(size_t(options.camera));
  BoundaryGradient result = empty_result(scene, cam, adjoint, options.meshes);
  if (!scene.media.empty() || scene.has_null_surfaces)
    throw InputError(scene.source + ": the secondary boundary term does not support media or null surfaces yet");
  const std::vector<int> slot = slots_of(scene, result);
  const EdgeTable table = edge_topology(scene, result.meshes);
  result.edges = int(table.edges.size());
  result.samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(std::max(options.spp, 0));
  if (table.edges.empty() || options.spp <= 0) return result;

  auto per_thread = per_thread_buffers(result);
  // Streams: the camera path (its own seed), and per (sample, vertex) one for the edge choice and
  // one for the two side paths.
  constexpr uint64_t kPathSeed = 0x5ec0ed6e5ull, kEdgeSeed = 0x5ec0ed6e6ull, kSideSeed = 0x5ec0ed6e7ull;
  const int max_depth = scene.settings.max_depth;
  const double inv_spp = 1.0 / double(options.spp);
  const double eps = double(options.side_angle);
  tbb::parallel_for(tbb::blocked_range<int>(0, cam.height), [&](const tbb::blocked_range<int>& rows) {
    Accumulator& acc = per_thread.local();
    std::vector<double> cdf;
    std::vector<uint32_t> index;
    NoObserver none;
    for (int py = rows.begin(); py != rows.end(); ++py)
      for (int px = 0; px < cam.width; ++px) {
        const Vec3d a(adjoint.at(px, py, 0), adjoint.at(px, py, 1), adjoint.at(px, py, 2));
        if (a.x == 0 && a.y == 0 && a.z == 0) continue;
        const uint64_t pixel = uint64_t(py) * uint64_t(cam.width) + uint64_t(px);
        for (int s = 0; s < options.spp; ++s) {
          const PathSampler sampler(options.seed ^ kPathSeed, pixel, uint64_t(s));
          Ray ray = cam.generate(float(px) + sampler.get(Dim::kPixelX), float(py) + sampler.get(Dim::kPixelY));
          Vec3f beta(1.f);
          for (int vertex = 1; max_depth < 0 || vertex < max_depth; ++vertex) {
            const Hit hit = scene.geometry->intersect(ray);
            if (hit.mesh < 0) break;
            const SurfacePoint sp = scene.surface_point(hit, ray);
            const Material& material = scene.materials[size_t(scene.meshes[size_t(hit.mesh)].material)];
            const Vec3f wo_world = -ray.direction;
            const BsdfValue<float> bsdf = material.at<float>(scene.params, sp.uv, sp.color);
            Vec3f normal = sp.shading_normal;
            if (material.two_sided && dot(normal, wo_world) < 0.f) normal = -normal;
            const Frame frame(normal);
            const Vec3f wo = frame.to_local(wo_world);
            const uint64_t stream = uint64_t(s) << 8 | uint64_t(std::min(vertex, 255));

            // One edge sample at this vertex.
            [&] {
              cdf.clear();
              index.clear();
              double total = 0;
              for (uint32_t i = 0; i < uint32_t(table.edges.size()); ++i)
                if (candidate_from(scene, table.edges[i], sp.p)) {
                  total += double(length(table.edges[i].p1 - table.edges[i].p0));
                  cdf.push_back(total);
                  index.push_back(i);
                }
              if (!(total > 0)) return;
              const PathSampler edge_rng(options.seed ^ kEdgeSeed, pixel, stream);
              const double u = double(edge_rng.get(0)) * total;
              const size_t pick =
                  std::min(size_t(std::upper_bound(cdf.begin(), cdf.end(), u) - cdf.begin()), cdf.size() - 1);
              const MeshEdge& e = table.edges[index[pick]];
              const double t = double(edge_rng.get(1));
              const Vec3d x(sp.p), p0(e.p0), p1(e.p1);
              const Vec3d p = p0 + (p1 - p0) * t;
              const double r = length(p - x);
              const Vec3d plane = cross(p0 - x, p1 - x);
              const double plane_len = length(plane);
              if (!(r > 0 && plane_len > 0)) return;  // the edge passes through x
              const Vec3d omega = (p - x) / r, n = plane / plane_len;
              const Vec3f f = bsdf.eval(wo, frame.to_local(Vec3f(omega)));
              if (is_zero(f)) return;
              // The side rays leave from the offset origin: aim them across the edge as seen from there.
              const Vec3f origin = offset_origin(sp.p, sp.geometric_normal, Vec3f(omega));
              const Vec3d o(origin);
              const Vec3d plane_o = cross(p0 - o, p1 - o);
              const double plane_o_len = length(plane_o), r_o = length(p - o);
              if (!(plane_o_len > 0 && r_o > 0)) return;
              const Vec3d n_o = plane_o / plane_o_len, omega_o = (p - o) / r_o;
              const PathSampler side(options.seed ^ kSideSeed, pixel, stream);
              auto incident = [&](double sign) {
                const Vec3f d(normalize(omega_o + n_o * (sign * eps)));
                return trace_path<float>(scene, PathStart{Ray{origin, d}, vertex + 1, 0.f, -1}, side, none);
              };
              const Vec3f weighted = beta * f * (incident(-1.0) - incident(1.0));
              const double arc = length(cross(normalize(p1 - p0), omega)) / r;
              const double w = (a.x * double(weighted.x) + a.y * double(weighted.y) + a.z * double(weighted.z)) * arc *
                               total / r * inv_spp;
              if (w != 0.0) add_to_edge(table, e, n * (w * (1 - t)), n * (w * t), acc[size_t(slot[size_t(e.mesh)])]);
            }();

            // Continue by BSDF sampling.
            const Vec2f ub{sampler.get(Dim::at(vertex, Dim::kBsdfU)), sampler.get(Dim::at(vertex, Dim::kBsdfV))};
            const BsdfSample bs = bsdf.sample(wo, sampler.get(Dim::at(vertex, Dim::kLobe)), ub);
            if (!(bs.pdf > 0.f)) break;
            const Vec3f fs = bsdf.eval(wo, bs.wi);
            if (is_zero(fs)) break;
            beta = beta * fs * (1.f / bs.pdf);
            const Vec3f wi_world = frame.to_world(bs.wi);
            ray = Ray{offset_origin(sp.p, sp.geometric_normal, wi_world), wi_world};
          }
        }
      }
  });
  reduce_into(per_thread, result);
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

CameraPoseGradient camera_pose_gradient(const Scene& scene, const BoundaryGradient& g, const Camera& cam) {
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
