#pragma once
// The loaded scene: meshes in world space, materials, emitters, cameras, integrator settings and
// the parameter store every differentiable value lives in.
#include <algorithm>
#include <memory>
#include <string>
#include <vector>

#include "engine/core/params.h"
#include "engine/scene/camera.h"
#include "engine/scene/geometry.h"
#include "kernels/bsdf/material.h"
#include "kernels/emitter/area.h"
#include "kernels/emitter/envmap.h"
#include "kernels/medium/medium.h"

namespace bl {

struct Mesh {
  std::string name;
  // World space. `positions` carries one extra padding element at the end because Embree may read
  // 16 bytes for the last 12-byte vertex; vertex_count() excludes it.
  std::vector<Vec3f> positions;
  std::vector<Vec3f> normals;  // per vertex, or empty (flat shading)
  std::vector<Vec2f> uvs;      // per vertex, or empty (uv = barycentrics)
  // Per vertex linear RGB in [0, 1] multiplying the material's colour (glTF's COLOR_0), or empty.
  std::vector<Vec3f> colors;
  std::vector<uint32_t> indices;
  std::vector<Vec3f> face_normals;  // unit (p1 − p0) × (p2 − p0) per triangle, built by Scene::prepare
  int material = -1;
  int emitter = -1;  // index into Scene::area_emitters, or -1
  // Media on either side (indices into Scene::media, -1 = vacuum). A shape naming neither is no
  // medium transition: rays crossing it stay in the medium they were in.
  int interior = -1, exterior = -1;
  bool medium_transition() const { return interior >= 0 || exterior >= 0; }
  size_t vertex_count() const { return positions.empty() ? 0 : positions.size() - 1; }
  size_t triangle_count() const { return indices.size() / 3; }
  float triangle_area(size_t t) const;
};

// The geometry parameters of a mesh (handles into the parameter store, −1 = none) and its rest
// state: positions p = pivot + t + R(r) · (s ⊙ (p₀ − pivot)) with p₀ the `positions` parameter
// (world space, initially as loaded), t = `translate`, r = `rotate` (axis-angle, radians),
// s = `scale`, pivot = the loaded vertices' centroid; vertex normals n = R · normalise(n₀ ⊘ s)
// with n₀ the rest normals. n₀ follows p₀ (smooth meshes): vertices at bitwise-equal positions
// with bitwise-equal loaded normals form a group (a uv seam shares its normal, a hard edge does
// not), whose area-weighted normal is a at the loaded positions and b now; a vertex's n₀ is its
// loaded normal turned by the smallest rotation taking a to b (rest_normal_from). So loaded
// normals (analytic, authored) stay exactly as they are until the positions move, and then turn
// with the surface.
struct MeshPose {
  int translate = -1, rotate = -1, scale = -1, positions = -1;
  Vec3f pivot;
  std::vector<Vec3f> rest_normals;         // n₀ now (the loaded normals until p₀ moves)
  std::vector<Vec3f> loaded_normals;       // smooth meshes with a positions parameter: as loaded
  std::vector<uint32_t> normal_group;      // per vertex, with loaded_normals
  std::vector<Vec3d> loaded_group_normal;  // per group: a, the unit area-weighted normal as loaded
  std::vector<double> rest_areas;          // per triangle, to detect triangles a step made degenerate
  std::vector<float> applied;              // the parameter values the mesh was last posed with
};

// A camera's pose parameters: `origin` (world position) and `rotate` (axis-angle about the
// origin, applied to the loaded frame).
struct CameraPose {
  int origin = -1, rotate = -1;
  Camera rest;
  std::vector<float> applied;
};

// Rotation matrix rows of axis-angle r (Rodrigues), and the left Jacobian J with
// R(r + δ) ≈ (I + [J δ]×) R(r): a world-frame rotation gradient g_ω becomes Jᵀ g_ω for r.
struct Rotation {
  Vec3d row[3];
  Vec3d apply(const Vec3d& v) const { return {dot(row[0], v), dot(row[1], v), dot(row[2], v)}; }
  Vec3d apply_transpose(const Vec3d& v) const { return row[0] * v.x + row[1] * v.y + row[2] * v.z; }
};
Rotation rotation_of(const Vec3d& r);

// A rest normal from its group's area-weighted normal m (unnormalised, see MeshPose): the loaded
// normal `loaded` turned by the smallest rotation taking the group's loaded unit normal `a` to
// m/|m|. A template so the gradient can take its Jacobian with duals.
template <class T>
Vec3<T> rest_normal_from(const Vec3<T>& m, const Vec3d& a, const Vec3d& loaded) {
  const Vec3<T> b = normalize(m);
  const Vec3<T> A(a), n(loaded);
  const Vec3<T> v = cross(A, b);
  const T c = dot(A, b);
  if (!(value_of(c) > -0.999999)) return b;  // turned half-way round: the loaded offset is meaningless
  const T k = dot(v, n) / (T(1.0) + c);
  return normalize(n * c + cross(v, n) + v * k);
}
// Per group of a smooth mesh's vertices: Σ (p₁ − p₀) × (p₂ − p₀) over the triangles touching it,
// from the rest positions p₀ ([N, 3]).
std::vector<Vec3d> group_area_normals(const MeshPose& pose, const Mesh& mesh, const std::vector<float>& p0);
// Adds to `grad` ([N, 3], the positions parameter's gradient) what reaches the rest positions p₀
// through the rest normals, given the gradient g_n0 with respect to each vertex's rest normal.
void add_rest_normal_gradient(const MeshPose& pose, const Mesh& mesh, const std::vector<float>& p0,
                              const std::vector<Vec3d>& g_n0, std::vector<float>& grad);
Vec3d left_jacobian_transpose(const Vec3d& r, const Vec3d& g);

struct IntegratorSettings {
  int spp = 16;
  int max_depth = 6;  // path segments, camera ray included; -1 = unlimited
  int rr_depth = 5;   // 0 = no Russian roulette
  uint64_t seed = 0;
  bool hide_emitters = false;
};

// Local geometry at a ray hit.
struct SurfacePoint {
  Vec3f p;
  Vec3f geometric_normal;  // unit, from the winding (p1 − p0) × (p2 − p0)
  Vec3f shading_normal;    // unit, interpolated vertex normal (or the geometric one)
  Vec2f uv;
  Vec3f color{1.f};  // interpolated vertex colour; white when the mesh has none
  int mesh = -1;
};

struct Scene {
  std::string source;  // file it was loaded from, for messages
  ParamStore params;
  std::vector<Material> materials;
  std::vector<Mesh> meshes;
  std::vector<AreaEmitter> area_emitters;
  Environment environment;
  std::vector<Camera> cameras;
  std::vector<Medium> media;
  IntegratorSettings settings;
  std::unique_ptr<Geometry> geometry;
  bool has_null_surfaces = false;        // derived by prepare()
  std::vector<MeshPose> mesh_poses;      // per mesh, after add_geometry_params()
  std::vector<CameraPose> camera_poses;  // per camera
  // Set when update_geometry re-posed something and cleared once prepare_geometry has rebuilt
  // what depends on it: a step that failed after moving another mesh still gets its rebuild.
  bool geometry_pending = false;

  // Builds derived data: BVH, emitter sampling tables, environment distribution. Call after
  // loading and whenever parameter values changed that sampling depends on.
  void prepare();
  // Everything parameter-dependent: meshes and cameras re-posed from their geometry parameters
  // when those changed (then the BVH and emitter tables are rebuilt), the environment
  // distribution and medium majorants. Throws InputError for non-finite poses or a triangle that
  // became degenerate.
  void prepare_sampling();
  // Creates <shape>.translate/rotate/scale/positions and <camera>.origin/rotate (loaders call it
  // once; a name already taken by another parameter is left to it).
  void add_geometry_params();
  // Re-poses meshes and cameras whose geometry parameters changed; whether any did.
  bool update_geometry();
  void prepare_geometry();       // face normals, emitter tables, BVH, cameras' frames
  void prepare_sampling_only();  // environment distribution and medium majorants
  // Cameras whose declared medium contradicts the geometry: the first surface a view ray meets is
  // a medium boundary seen from another medium's side (a camera declared inside "fog" but outside
  // its boundary fogs the whole view; one inside a boundary without "medium" sees no fog near it).
  // One warning line per such camera, for the loaders to print; needs prepare().
  std::vector<std::string> camera_medium_warnings() const;
  // Media whose inside is not closed: the shapes naming medium m as their interior, welded by
  // vertex position, have edges that only one triangle uses. A ray inside can leave through such a
  // gap without crossing a boundary and then carries the medium on to infinity (as in Mitsuba 3).
  // One warning line per such medium.
  std::vector<std::string> open_medium_warnings() const;
  // A hash of what the scene holds: every parameter's name and values (textures, grids,
  // radiances, poses) and every mesh's vertex arrays and indices, so whatever files they came
  // from. FNV-1a over the bytes, the same on every machine (MPI ranks compare it).
  uint64_t content_hash() const;
  SurfacePoint surface_point(const Hit& hit, const Ray& ray) const;
  int emitter_count() const { return int(area_emitters.size()) + (environment.present ? 1 : 0); }
  float emitter_select_probability() const { return emitter_count() > 0 ? 1.f / float(emitter_count()) : 0.f; }
  // The emitter a light sample takes, uniformly, from a 53-bit u (PathSampler::get_double): with a
  // float's 24 bits emitter i's share is a count of 2⁻²⁴ steps, ±1 of 2²⁴/N (±0.6% at N = 10⁵).
  int choose_emitter(double u) const { return std::min(int(u * double(emitter_count())), emitter_count() - 1); }
  // Samples a point on area emitter `index` uniformly by area: u0 (53 bits, PathSampler::get_double)
  // picks the triangle and places the point with u1.
  EmitterSample sample_area_emitter(int index, const Vec3f& ref, double u0, double u1) const;
  // Whether a non-null surface blocks o + t·d for t < tmax (null surfaces let rays through).
  bool occluded(const Vec3f& o, const Vec3f& d, float tmax) const;
  // The medium a ray travelling along `d` is in after crossing (or leaving) mesh `m` at a point
  // with geometric normal `ng`, coming from medium `current`.
  int medium_after(const Mesh& m, const Vec3f& d, const Vec3f& ng, int current) const {
    if (!m.medium_transition()) return current;
    return dot(d, ng) < 0.f ? m.interior : m.exterior;
  }
};

// Longest chain of null-surface crossings one ray segment may take (a guard against rays caught
// between coincident null surfaces).
inline constexpr int kMaxNullCrossings = 256;

// Checks a camera read from input (film size within the limits, finite frame and corner rays) and
// derives its frame; throws InputError naming `source`.
void validate_camera(Camera& cam, const std::string& source);

// Offsets a ray origin along the geometric normal, to the side `direction` leaves on, so the
// spawned ray does not re-hit its own surface.
inline Vec3f offset_origin(const Vec3f& p, const Vec3f& geometric_normal, const Vec3f& direction) {
  float scale = 1e-4f * (1.f + std::max(std::abs(p.x), std::max(std::abs(p.y), std::abs(p.z))));
  return p + geometric_normal * (dot(geometric_normal, direction) > 0.f ? scale : -scale);
}

// Walks a shadow segment o + t·d, t < tmax, starting in `medium` (−1: vacuum), across null
// surfaces (index-matched boundaries: only the medium changes) up to the first surface that is
// not null or the segment's end. on_piece(medium, origin, length) is called for every piece
// between crossings that lies in a medium and returns false to end the walk there (a
// transmittance that reached 0). Returns whether a non-null surface blocks the segment; more than
// kMaxNullCrossings crossings count as blocked. With `find_blockers` false the caller knows nothing
// blocks it, and rays are cast only when there are null surfaces to find.
template <class OnPiece>
bool walk_shadow_segment(const Scene& scene, Vec3f o, const Vec3f& d, float tmax, int medium, bool find_blockers,
                         OnPiece&& on_piece) {
  const bool intersect = find_blockers || scene.has_null_surfaces;
  for (int k = 0; k <= kMaxNullCrossings; ++k) {
    const Hit hit = intersect ? scene.geometry->intersect_shadow(Ray{o, d, 0.f, tmax}) : Hit{};
    if (hit.mesh >= 0 && !scene.materials[size_t(scene.meshes[size_t(hit.mesh)].material)].is_null) return true;
    if (medium >= 0 && !on_piece(medium, o, hit.mesh < 0 ? tmax : hit.t)) return false;
    if (hit.mesh < 0) return false;
    const Mesh& m = scene.meshes[size_t(hit.mesh)];
    const Vec3f ng = m.face_normals[size_t(hit.triangle)];
    medium = scene.medium_after(m, d, ng, medium);
    const Vec3f next = offset_origin(o + d * hit.t, ng, d);
    tmax -= length(next - o);
    o = next;
    if (!(tmax > 0.f)) return false;
  }
  return true;
}

}  // namespace bl
