// Geometry parameters: shape poses, vertex positions and camera poses (scene.h: MeshPose,
// CameraPose), applied to the meshes and cameras whenever their values change.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <sstream>
#include <string>
#include <unordered_map>

#include "engine/core/dual.h"
#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/scene/scene.h"

namespace bl {

Rotation rotation_of(const Vec3d& r) {
  const double theta = length(r);
  Rotation R;
  if (!(theta > 0)) {
    R.row[0] = {1, 0, 0};
    R.row[1] = {0, 1, 0};
    R.row[2] = {0, 0, 1};
    return R;
  }
  const Vec3d k = r / theta;
  const double c = std::cos(theta), s = std::sin(theta), v = 1 - c;
  R.row[0] = {c + k.x * k.x * v, k.x * k.y * v - k.z * s, k.x * k.z * v + k.y * s};
  R.row[1] = {k.y * k.x * v + k.z * s, c + k.y * k.y * v, k.y * k.z * v - k.x * s};
  R.row[2] = {k.z * k.x * v - k.y * s, k.z * k.y * v + k.x * s, c + k.z * k.z * v};
  return R;
}

// J(r) = I + a [r]× + b [r]×², a = (1 − cos θ)/θ², b = (θ − sin θ)/θ³; Jᵀ g = g − a r×g + b r×(r×g).
Vec3d left_jacobian_transpose(const Vec3d& r, const Vec3d& g) {
  const double theta = length(r);
  double a = 0.5, b = 1.0 / 6.0;
  if (theta > 1e-4) {
    a = (1 - std::cos(theta)) / (theta * theta);
    b = (theta - std::sin(theta)) / (theta * theta * theta);
  }
  return g - cross(r, g) * a + cross(r, cross(r, g)) * b;
}

namespace {

Param vector_param(const std::string& name, const Vec3f& v, float lower) {
  Param p;
  p.name = name;
  p.shape = {3};
  p.value = {v.x, v.y, v.z};
  p.lower = lower;
  p.upper = 1e30f;
  p.geometry = true;
  return p;
}

// A pose parameter `<owner>.<key>` of a shape or camera. Its name must be free: a camera, shape,
// material or medium sharing the owner's name could already hold it (a camera "left" and a wall
// "left" both want "left.rotate"), and one of them would silently lose its parameter.
int add_pose_param(ParamStore& store, Param p, const std::string& where, const std::string& owner) {
  if (store.find(p.name) >= 0)
    throw InputError(where + ": " + owner + ": its pose parameter '" + p.name +
                     "' is already another object's (shapes, cameras, materials and media sharing a name "
                     "share parameter names): rename one of them");
  return store.add(std::move(p), where);
}

Vec3d vec_of(const Param& p) { return {p.value[0], p.value[1], p.value[2]}; }

void append(std::vector<float>& out, const Param* p) {
  if (p) out.insert(out.end(), p->value.begin(), p->value.end());
}

}  // namespace

void Scene::add_geometry_params() {
  if (!mesh_poses.empty() || !camera_poses.empty()) return;
  mesh_poses.resize(meshes.size());
  for (size_t i = 0; i < meshes.size(); ++i) {
    Mesh& m = meshes[i];
    MeshPose& pose = mesh_poses[i];
    if (m.name.empty()) continue;  // nothing to name its parameters by
    Vec3d c(0.0);
    for (size_t v = 0; v < m.vertex_count(); ++v) c += Vec3d(m.positions[v]);
    pose.pivot = m.vertex_count() ? Vec3f(c / double(m.vertex_count())) : Vec3f(0.f);
    pose.rest_normals = m.normals;
    pose.rest_areas.resize(m.triangle_count());
    for (size_t t = 0; t < m.triangle_count(); ++t) pose.rest_areas[t] = double(m.triangle_area(t));
    const std::string owner = "shape '" + m.name + "'";
    pose.translate = add_pose_param(params, vector_param(m.name + ".translate", Vec3f(0.f), -1e30f), source, owner);
    pose.rotate = add_pose_param(params, vector_param(m.name + ".rotate", Vec3f(0.f), -1e30f), source, owner);
    pose.scale = add_pose_param(params, vector_param(m.name + ".scale", Vec3f(1.f), 1e-6f), source, owner);
    Param positions;
    positions.name = m.name + ".positions";
    positions.shape = {int(m.vertex_count()), 3};
    positions.value.reserve(3 * m.vertex_count());
    for (size_t v = 0; v < m.vertex_count(); ++v) {
      positions.value.push_back(m.positions[v].x);
      positions.value.push_back(m.positions[v].y);
      positions.value.push_back(m.positions[v].z);
    }
    positions.lower = -1e30f;
    positions.geometry = true;
    pose.positions = add_pose_param(params, std::move(positions), source, owner);
    if (!m.normals.empty()) {
      // Normal groups: bitwise-equal position and loaded normal.
      struct Key {
        uint32_t b[6];
        bool operator==(const Key& o) const { return std::memcmp(b, o.b, sizeof b) == 0; }
      };
      struct KeyHash {
        size_t operator()(const Key& k) const {
          uint64_t h = 0x9e3779b97f4a7c15ull;
          for (uint32_t x : k.b) h = (h ^ x) * 0xbf58476d1ce4e5b9ull;
          return size_t(h ^ (h >> 29));
        }
      };
      std::unordered_map<Key, uint32_t, KeyHash> ids;
      pose.normal_group.resize(m.vertex_count());
      for (size_t v = 0; v < m.vertex_count(); ++v) {
        Key k;
        std::memcpy(k.b, &m.positions[v], 12);
        std::memcpy(k.b + 3, &m.normals[v], 12);
        pose.normal_group[v] = ids.try_emplace(k, uint32_t(ids.size())).first->second;
      }
      pose.loaded_normals = m.normals;
      for (const Vec3d& g : group_area_normals(pose, m, params[pose.positions].value))
        pose.loaded_group_normal.push_back(normalize(g));
    }
  }
  camera_poses.resize(cameras.size());
  for (size_t i = 0; i < cameras.size(); ++i) {
    CameraPose& pose = camera_poses[i];
    pose.rest = cameras[i];
    if (cameras[i].name.empty()) continue;
    const std::string owner = "camera '" + cameras[i].name + "'";
    pose.origin =
        add_pose_param(params, vector_param(cameras[i].name + ".origin", cameras[i].origin, -1e30f), source, owner);
    pose.rotate = add_pose_param(params, vector_param(cameras[i].name + ".rotate", Vec3f(0.f), -1e30f), source, owner);
  }
  // The values as loaded are what the meshes and cameras show: nothing to apply.
  for (size_t i = 0; i < meshes.size(); ++i) {
    const MeshPose& pose = mesh_poses[i];
    std::vector<float>& a = mesh_poses[i].applied;
    for (int h : {pose.translate, pose.rotate, pose.scale, pose.positions}) append(a, h >= 0 ? &params[h] : nullptr);
  }
  for (CameraPose& pose : camera_poses)
    for (int h : {pose.origin, pose.rotate}) append(pose.applied, h >= 0 ? &params[h] : nullptr);
}

namespace {
// Whether a group's rest normal follows its positions: both area-weighted normals exist.
bool group_normal_defined(const Vec3d& a, const Vec3d& m) {
  return std::isfinite(a.x + a.y + a.z) && dot(m, m) > 0 && std::isfinite(m.x + m.y + m.z);
}
}  // namespace

std::vector<Vec3d> group_area_normals(const MeshPose& pose, const Mesh& mesh, const std::vector<float>& p0) {
  uint32_t groups = 0;
  for (uint32_t g : pose.normal_group) groups = std::max(groups, g + 1);
  std::vector<Vec3d> out(groups, Vec3d(0.0));
  auto at = [&](uint32_t i) { return Vec3d(p0[3 * size_t(i)], p0[3 * size_t(i) + 1], p0[3 * size_t(i) + 2]); };
  for (size_t t = 0; t < mesh.triangle_count(); ++t) {
    const uint32_t* i = &mesh.indices[3 * t];
    const Vec3d c = cross(at(i[1]) - at(i[0]), at(i[2]) - at(i[0]));
    for (int k = 0; k < 3; ++k) out[pose.normal_group[i[k]]] += c;
  }
  return out;
}

void add_rest_normal_gradient(const MeshPose& pose, const Mesh& mesh, const std::vector<float>& p0,
                              const std::vector<Vec3d>& g_n0, std::vector<float>& grad) {
  if (pose.loaded_normals.empty()) return;
  const std::vector<Vec3d> groups = group_area_normals(pose, mesh, p0);
  // Per group: g_m = Σ over its vertices of (∂n₀/∂m)ᵀ g_n₀ (duals give the 3×3 Jacobian).
  using D = Dual<double, 3>;
  std::vector<Vec3d> g_m(groups.size(), Vec3d(0.0));
  for (size_t v = 0; v < mesh.vertex_count(); ++v) {
    const Vec3d& g = g_n0[v];
    if (g.x == 0 && g.y == 0 && g.z == 0) continue;
    const uint32_t k = pose.normal_group[v];
    const Vec3d& m = groups[k];
    if (!group_normal_defined(pose.loaded_group_normal[k], m)) continue;  // the loaded normal, held
    const Vec3<D> n = rest_normal_from(Vec3<D>{D::variable(m.x, 0), D::variable(m.y, 1), D::variable(m.z, 2)},
                                       pose.loaded_group_normal[k], Vec3d(pose.loaded_normals[v]));
    for (int c = 0; c < 3; ++c) g_m[k][c] += g.x * n.x.d[size_t(c)] + g.y * n.y.d[size_t(c)] + g.z * n.z.d[size_t(c)];
  }
  // m = Σ c_t, c_t = (p₁ − p₀) × (p₂ − p₀): g·dc = de₁·(e₂ × g) + de₂·(g × e₁).
  auto at = [&](uint32_t i) { return Vec3d(p0[3 * size_t(i)], p0[3 * size_t(i) + 1], p0[3 * size_t(i) + 2]); };
  auto add = [&](uint32_t i, const Vec3d& d) {
    for (int c = 0; c < 3; ++c) grad[3 * size_t(i) + size_t(c)] += float(d[c]);
  };
  for (size_t t = 0; t < mesh.triangle_count(); ++t) {
    const uint32_t* i = &mesh.indices[3 * t];
    const Vec3d g = g_m[pose.normal_group[i[0]]] + g_m[pose.normal_group[i[1]]] + g_m[pose.normal_group[i[2]]];
    if (g.x == 0 && g.y == 0 && g.z == 0) continue;
    const Vec3d e1 = at(i[1]) - at(i[0]), e2 = at(i[2]) - at(i[0]);
    const Vec3d d1 = cross(e2, g), d2 = cross(g, e1);
    add(i[1], d1);
    add(i[2], d2);
    add(i[0], -(d1 + d2));
  }
}

bool Scene::update_geometry() {
  bool moved = false;
  std::vector<float> now;
  for (size_t i = 0; i < mesh_poses.size(); ++i) {
    MeshPose& pose = mesh_poses[i];
    now.clear();
    for (int h : {pose.translate, pose.rotate, pose.scale, pose.positions}) append(now, h >= 0 ? &params[h] : nullptr);
    if (now == pose.applied) continue;
    Mesh& m = meshes[i];
    const std::string where = source + ": shape '" + m.name + "'";
    for (float v : now)
      if (!std::isfinite(v)) throw InputError(where + ": a pose or vertex position is not finite");
    const Vec3d t = pose.translate >= 0 ? vec_of(params[pose.translate]) : Vec3d(0.0);
    const Vec3d r = pose.rotate >= 0 ? vec_of(params[pose.rotate]) : Vec3d(0.0);
    const Vec3d s = pose.scale >= 0 ? vec_of(params[pose.scale]) : Vec3d(1.0);
    const Rotation R = rotation_of(r);
    const Vec3d pivot(pose.pivot);
    const std::vector<float>* p0 = pose.positions >= 0 ? &params[pose.positions].value : nullptr;
    // From here the mesh changes: until the new pose is complete it matches no values (a step
    // that fails below leaves it to be posed again, whatever values come next).
    pose.applied.clear();
    geometry_pending = true;
    if (p0 && !pose.loaded_normals.empty()) {
      const std::vector<Vec3d> groups = group_area_normals(pose, m, *p0);
      for (size_t v = 0; v < m.vertex_count(); ++v) {
        const uint32_t g = pose.normal_group[v];
        const Vec3d& a = pose.loaded_group_normal[g];
        // Exactly the loaded normal while the group's normal is exactly as loaded, and where it is
        // undefined (a vertex no triangle uses, or whose triangles' areas cancel).
        const Vec3d b = normalize(groups[g]);
        pose.rest_normals[v] = (b.x == a.x && b.y == a.y && b.z == a.z) || !group_normal_defined(a, groups[g])
                                   ? pose.loaded_normals[v]
                                   : Vec3f(rest_normal_from(groups[g], a, Vec3d(pose.loaded_normals[v])));
      }
    }
    for (size_t v = 0; v < m.vertex_count(); ++v) {
      const Vec3d rest = p0 ? Vec3d((*p0)[3 * v], (*p0)[3 * v + 1], (*p0)[3 * v + 2]) : Vec3d(m.positions[v]);
      m.positions[v] = Vec3f(pivot + t + R.apply((rest - pivot) * s));
      if (!pose.rest_normals.empty()) m.normals[v] = Vec3f(R.apply(normalize(Vec3d(pose.rest_normals[v]) / s)));
    }
    for (size_t v = 0; v < m.vertex_count(); ++v) {  // the loaders' limit (a scale of 1e29 passed it)
      const Vec3f& q = m.positions[v];
      if (!(std::abs(q.x) <= limits::kCoordinate && std::abs(q.y) <= limits::kCoordinate &&
            std::abs(q.z) <= limits::kCoordinate))
        throw InputError(where + ": vertex " + std::to_string(v) +
                         " is not finite or beyond 1e18 in magnitude after the pose");
    }
    for (size_t k = 0; k < m.triangle_count(); ++k) {
      const float area = m.triangle_area(k);
      if (pose.rest_areas[k] > 0 && !(area > 0.f)) {
        // Far from the origin float cannot tell a small triangle's corners apart: say so rather
        // than blame the pose's shape (a translation of 1e16 flattens a box of size 0.5).
        float far = 0.f;
        for (int c = 0; c < 3; ++c) {
          const Vec3f& q = m.positions[m.indices[3 * k + size_t(c)]];
          far = std::max({far, std::abs(q.x), std::abs(q.y), std::abs(q.z)});
        }
        std::string why = "zero area";
        if (double(far) * double(far) * 1e-12 > pose.rest_areas[k]) {
          std::ostringstream s;
          s << "zero area: at coordinates of magnitude " << far << " float cannot resolve it";
          why = s.str();
        }
        throw InputError(where + ": triangle " + std::to_string(k) + " became degenerate (" + why + ")");
      }
    }
    pose.applied = now;
    moved = true;
  }
  for (size_t i = 0; i < camera_poses.size(); ++i) {
    CameraPose& pose = camera_poses[i];
    now.clear();
    for (int h : {pose.origin, pose.rotate}) append(now, h >= 0 ? &params[h] : nullptr);
    if (now == pose.applied) continue;
    Camera& cam = cameras[i];
    for (float v : now)
      if (!std::isfinite(v)) throw InputError(source + ": camera '" + cam.name + "': its pose is not finite");
    const Vec3d origin = pose.origin >= 0 ? vec_of(params[pose.origin]) : Vec3d(pose.rest.origin);
    const Rotation R = rotation_of(pose.rotate >= 0 ? vec_of(params[pose.rotate]) : Vec3d(0.0));
    geometry_pending = true;
    cam.origin = Vec3f(origin);
    cam.target = Vec3f(origin + R.apply(Vec3d(pose.rest.target - pose.rest.origin)));
    cam.up = Vec3f(R.apply(Vec3d(pose.rest.up)));
    pose.applied = now;
    moved = true;
  }
  return moved;
}

}  // namespace bl
