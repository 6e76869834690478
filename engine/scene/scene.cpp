#include "engine/scene/scene.h"
#include "engine/scene/openvdb_io.h"
#include "engine/scene/volume_io.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <iomanip>
#include <limits>
#include <sstream>
#include <unordered_map>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/dist/dist.h"
#include "engine/scene/scene_load.h"

namespace bl {

void validate_camera(Camera& cam, const std::string& source) {
  const std::string where = source + ": camera '" + cam.name + "'";
  limits::check_image_size(where, uint64_t(std::max(0, cam.width)), uint64_t(std::max(0, cam.height)));
  if (cam.width < 1 || cam.height < 1) throw InputError(where + ": the film needs at least one pixel");
  for (const Vec3f& v : {cam.origin, cam.target, cam.up})
    if (!is_finite(v) || std::abs(v.x) > limits::kCoordinate || std::abs(v.y) > limits::kCoordinate ||
        std::abs(v.z) > limits::kCoordinate)
      throw InputError(where + ": position or direction not finite or beyond 1e18 in magnitude");
  if (!(cam.fov_degrees > 0.f && cam.fov_degrees < 180.f)) throw InputError(where + ": fov must be in (0, 180)");
  cam.update();
  // A frame from nearly coincident or overflowing inputs can still come out NaN; Embree aborts on
  // such rays, so every derived vector is checked here, once.
  if (!is_finite(cam.forward) || !is_finite(cam.right) || !is_finite(cam.true_up) || !std::isfinite(cam.tan_x) ||
      !std::isfinite(cam.tan_y) || length(cam.right) < 0.5f)
    throw InputError(where + ": degenerate view frame (origin, target and up must span a frame)");
  for (float px : {0.f, float(cam.width)})
    for (float py : {0.f, float(cam.height)}) {
      const Ray r = cam.generate(px, py);
      if (!is_finite(r.direction) || !std::isfinite(r.tmin))
        throw InputError(where + ": the film's corner rays are not finite");
    }
}

float Mesh::triangle_area(size_t t) const {
  const Vec3f& a = positions[indices[3 * t]];
  const Vec3f& b = positions[indices[3 * t + 1]];
  const Vec3f& c = positions[indices[3 * t + 2]];
  return 0.5f * length(cross(b - a, c - a));
}

void Scene::prepare() {
  update_geometry();
  prepare_geometry();
  prepare_sampling_only();
}

void Scene::prepare_geometry() {
  for (auto& cam : cameras) validate_camera(cam, source);
  for (auto& m : meshes) {
    m.face_normals.resize(m.triangle_count());
    for (size_t t = 0; t < m.triangle_count(); ++t) {
      const Vec3f &a = m.positions[m.indices[3 * t]], &b = m.positions[m.indices[3 * t + 1]],
                  &c = m.positions[m.indices[3 * t + 2]];
      const Vec3f n = cross(b - a, c - a);
      const float len = length(n);
      m.face_normals[t] = len > 0.f ? n / len : Vec3f(0.f, 0.f, 1.f);  // degenerate: never hit in practice
    }
  }
  for (auto& e : area_emitters) {
    const Mesh& m = meshes[size_t(e.mesh)];
    std::vector<double> areas(m.triangle_count());
    double total = 0;
    for (size_t t = 0; t < areas.size(); ++t) total += areas[t] = m.triangle_area(t);
    // No area to emit from: every light sample's pdf would divide by zero (an image of NaN).
    if (!(total > 0.0))
      throw InputError(source + ": emitter '" + m.name + "': its triangles have no area (every one is degenerate)");
    if (!std::isfinite(float(total)))
      throw InputError(source + ": emitter '" + m.name + "': its total area exceeds float's range");
    e.total_area = float(total);
    e.triangles.build(areas);
  }
  geometry = std::make_unique<Geometry>();
  geometry->build(meshes);
  has_null_surfaces = false;
  for (const auto& m : meshes) has_null_surfaces |= materials[size_t(m.material)].is_null;
  geometry_pending = false;
}

void Scene::prepare_sampling() {
  if (update_geometry() || geometry_pending) prepare_geometry();
  prepare_sampling_only();
}

void Scene::prepare_sampling_only() {
  if (environment.present && environment.is_map) {
    // Each factor is within its range (texels and scale ≤ 1e30), their product need not be: an
    // infinite radiance would write inf pixels with exit 0.
    const std::vector<float>& v = params[environment.param].value;
    const float brightest = v.empty() ? 0.f : *std::max_element(v.begin(), v.end());
    if (double(brightest) * double(environment.scale) > double(std::numeric_limits<float>::max())) {
      std::ostringstream s;
      s << source << ": environment: radiance up to " << brightest << " × scale " << environment.scale
        << " exceeds float's range (lower the scale or the map's values)";
      throw InputError(s.str());
    }
  }
  environment.prepare(params);
  for (auto& m : media) {
    m.prepare(params);
    // An infinite majorant steps by 0 for ever. In a grid, tracking crosses the thin parts of a
    // block at ~majorant × length null collisions: an optically solid block would never finish.
    // (A homogeneous medium's collisions are real with probability 1 / headroom, and its ratio
    // tracking reaches 0 in a few hundred steps: any finite majorant ends.)
    const float majorant = m.grid ? m.majorants.max() : m.homogeneous_majorant;
    if (!std::isfinite(majorant))
      throw InputError(source + ": medium '" + m.name +
                       "': its extinction (density × scale × majorant headroom) exceeds float's range");
    if (!m.grid) continue;
    const GridSize g = grid_size(params[m.density]);
    const Vec3f size = m.bbox_max - m.bbox_min;
    // In double: a box 1e30 wide made the block's diagonal, and the step count, inf.
    const int* block = m.majorants.size;
    const double bx = double(size.x) * std::min(block[0], g.x) / g.x,
                 by = double(size.y) * std::min(block[1], g.y) / g.y,
                 bz = double(size.z) * std::min(block[2], g.z) / g.z;
    const double depth = double(majorant) * std::sqrt(bx * bx + by * by + bz * bz);
    if (depth > limits::kOpticalDepth) {
      std::ostringstream s;
      s << source << ": medium '" << m.name << "': extinction up to " << majorant
        << " (density × scale × majorant headroom) makes ~" << depth
        << " tracking steps across one majorant block, beyond the limit of " << limits::kOpticalDepth
        << " (an optically solid medium: lower its density or scale, or the size of its box)";
      throw InputError(s.str());
    }
  }
}

std::vector<std::string> Scene::camera_medium_warnings() const {
  std::vector<std::string> out;
  if (media.empty()) return out;
  auto medium_name = [&](int m) { return m < 0 ? std::string("no medium") : "medium '" + media[size_t(m)].name + "'"; };
  for (const Camera& cam : cameras) {
    // Rays through the film's centre and corners: the first surface each meets, when it is a
    // medium boundary, tells from its normal which medium the camera looks out of.
    const float w = float(cam.width), h = float(cam.height);
    for (const auto& [px, py] : {std::pair{0.5f, 0.5f}, {0.f, 0.f}, {1.f, 0.f}, {0.f, 1.f}, {1.f, 1.f}}) {
      const Ray ray = cam.generate(px * w, py * h);
      const Hit hit = geometry->intersect(ray);
      if (hit.mesh < 0) continue;
      const Mesh& mesh = meshes[size_t(hit.mesh)];
      if (!mesh.medium_transition()) continue;
      const Vec3f ng = mesh.face_normals[size_t(hit.triangle)];
      const int before = dot(ray.direction, ng) < 0.f ? mesh.exterior : mesh.interior;
      if (before == cam.medium) continue;
      out.push_back("backlight: " + source + ": warning: camera '" + cam.name + "' is in " + medium_name(cam.medium) +
                    ", but its view meets shape '" + mesh.name + "' from the side of " + medium_name(before) +
                    " (set the camera's \"medium\", or check the shape's interior/exterior and its normals)");
      break;
    }
  }
  return out;
}

std::vector<std::string> Scene::open_medium_warnings() const {
  std::vector<std::string> out;
  for (size_t m = 0; m < media.size(); ++m) {
    // Vertices welded by bitwise position (a uv seam or a hard edge splits a vertex, not the
    // surface), then each undirected edge counted over every triangle of every such shape.
    uint32_t vertices = 0;
    std::unordered_map<uint64_t, uint32_t> edges;
    std::vector<std::string> shapes;
    auto key = [](const Vec3f& p) {
      uint32_t b[3];
      std::memcpy(b, &p, sizeof b);
      return uint64_t(b[0]) * 0x9E3779B97F4A7C15ull ^ uint64_t(b[1]) * 0xC2B2AE3D27D4EB4Full ^
             (uint64_t(b[2]) << 21 | uint64_t(b[2]) >> 43);
    };
    std::unordered_map<uint64_t, std::vector<std::pair<Vec3f, uint32_t>>> buckets;
    auto id_of = [&](const Vec3f& p) {
      auto& bucket = buckets[key(p)];
      for (const auto& [q, id] : bucket)
        if (std::memcmp(&q, &p, sizeof p) == 0) return id;
      bucket.push_back({p, vertices});
      return vertices++;
    };
    for (const Mesh& mesh : meshes) {
      if (mesh.interior != int(m)) continue;
      shapes.push_back("'" + mesh.name + "'");
      for (size_t t = 0; t < mesh.triangle_count(); ++t) {
        uint32_t v[3];
        for (int k = 0; k < 3; ++k) v[k] = id_of(mesh.positions[mesh.indices[3 * t + size_t(k)]]);
        for (int k = 0; k < 3; ++k) {
          const uint32_t a = std::min(v[k], v[(k + 1) % 3]), b = std::max(v[k], v[(k + 1) % 3]);
          if (a != b) ++edges[uint64_t(a) << 32 | b];
        }
      }
    }
    size_t open = 0;
    for (const auto& [edge, count] : edges) open += count == 1;
    if (open == 0) continue;
    std::string names;
    for (size_t i = 0; i < shapes.size(); ++i) names += (i ? ", " : "") + shapes[i];
    out.push_back("backlight: " + source + ": warning: the inside of medium '" + media[m].name + "' (shape" +
                  (shapes.size() > 1 ? "s " : " ") + names + ") is not closed: " + std::to_string(open) + " of " +
                  std::to_string(edges.size()) +
                  " edges belong to one triangle only, and a ray leaving through that gap stays in the medium");
  }
  return out;
}

bool Scene::occluded(const Vec3f& o, const Vec3f& d, float tmax) const {
  if (!has_null_surfaces) return geometry->occluded(o, d, tmax);
  return walk_shadow_segment(*this, o, d, tmax, -1, true, [](int, const Vec3f&, float) { return true; });
}

SurfacePoint Scene::surface_point(const Hit& hit, const Ray& ray) const {
  const Mesh& m = meshes[size_t(hit.mesh)];
  const uint32_t i0 = m.indices[3 * size_t(hit.triangle)], i1 = m.indices[3 * size_t(hit.triangle) + 1],
                 i2 = m.indices[3 * size_t(hit.triangle) + 2];
  const float b0 = 1.f - hit.b1 - hit.b2;
  SurfacePoint sp;
  sp.mesh = hit.mesh;
  sp.p = ray.origin + ray.direction * hit.t;
  sp.geometric_normal = m.face_normals[size_t(hit.triangle)];
  if (!m.normals.empty()) {
    Vec3f n = m.normals[i0] * b0 + m.normals[i1] * hit.b1 + m.normals[i2] * hit.b2;
    float len = length(n);
    sp.shading_normal = len > 0 ? n / len : sp.geometric_normal;
  } else {
    sp.shading_normal = sp.geometric_normal;
  }
  if (!m.uvs.empty()) {
    sp.uv = {m.uvs[i0].x * b0 + m.uvs[i1].x * hit.b1 + m.uvs[i2].x * hit.b2,
             m.uvs[i0].y * b0 + m.uvs[i1].y * hit.b1 + m.uvs[i2].y * hit.b2};
  } else {
    sp.uv = {hit.b1, hit.b2};
  }
  if (!m.colors.empty()) sp.color = m.colors[i0] * b0 + m.colors[i1] * hit.b1 + m.colors[i2] * hit.b2;
  return sp;
}

EmitterSample Scene::sample_area_emitter(int index, const Vec3f& ref, double u0, double u1) const {
  const AreaEmitter& e = area_emitters[size_t(index)];
  const Mesh& m = meshes[size_t(e.mesh)];
  // Pick a triangle by area with u0, then reuse the remainder of u0 inside it.
  float ux = 0.f;
  const size_t t = e.triangles.sample(u0, &ux);
  const float uy = std::min(float(u1), std::nextafter(1.f, 0.f));
  // Uniform point on the triangle (square-root parameterisation).
  float su = std::sqrt(ux), b1 = 1.f - su, b2 = uy * su, b0 = 1.f - b1 - b2;
  const uint32_t i0 = m.indices[3 * t], i1 = m.indices[3 * t + 1], i2 = m.indices[3 * t + 2];
  EmitterSample s;
  s.point = m.positions[i0] * b0 + m.positions[i1] * b1 + m.positions[i2] * b2;
  const Vec3f n = m.face_normals[t];
  // Only the side of the interpolated shading normal matters (below): no need to normalize it.
  Vec3f shading = n;
  if (!m.normals.empty()) shading = m.normals[i0] * b0 + m.normals[i1] * b1 + m.normals[i2] * b2;
  if (!m.uvs.empty())
    s.uv = {m.uvs[i0].x * b0 + m.uvs[i1].x * b1 + m.uvs[i2].x * b2,
            m.uvs[i0].y * b0 + m.uvs[i1].y * b1 + m.uvs[i2].y * b2};
  else
    s.uv = {b1, b2};
  Vec3f to = s.point - ref;
  float d2 = dot(to, to);
  s.distance = std::sqrt(d2);
  if (s.distance <= 0.f) return {};
  s.wi = to / s.distance;
  // Emission leaves on the shading normal's side; the pdf uses the geometric cosine.
  float cos_shading = -dot(shading, s.wi);
  float cos_geometric = std::abs(dot(n, s.wi));
  if (cos_shading <= 0.f || cos_geometric <= 0.f) return {};
  s.pdf = d2 / (cos_geometric * e.total_area);
  s.triangle = int(t);
  s.b1 = b1;
  s.b2 = b2;
  return s;
}

uint64_t Scene::content_hash() const {
  uint64_t h = 1469598103934665603ull;
  auto add = [&h](const void* data, size_t bytes) {
    // Eight bytes per step (a 64³ grid is 1 MB), then the tail byte by byte, and the length.
    const auto* b = static_cast<const unsigned char*>(data);
    size_t i = 0;
    for (; i + 8 <= bytes; i += 8) {
      uint64_t word;
      std::memcpy(&word, b + i, 8);
      h = (h ^ word) * 1099511628211ull;
    }
    for (; i < bytes; ++i) h = (h ^ b[i]) * 1099511628211ull;
    h = (h ^ uint64_t(bytes)) * 1099511628211ull;
  };
  for (const Param& p : params.all()) {
    add(p.name.data(), p.name.size());
    add(p.value.data(), p.value.size() * sizeof(float));
  }
  for (const Mesh& m : meshes) {
    add(m.positions.data(), m.positions.size() * sizeof(Vec3f));
    add(m.indices.data(), m.indices.size() * sizeof(uint32_t));
    add(m.normals.data(), m.normals.size() * sizeof(Vec3f));
    add(m.uvs.data(), m.uvs.size() * sizeof(Vec2f));
    add(m.colors.data(), m.colors.size() * sizeof(Vec3f));
  }
  return h;
}

void require_same_scene(const Scene& scene) {
  if (!dist::active()) return;  // one process: not even the hash (a 4096² texture is 200 MB)
  dist::require_same(scene.content_hash(),
                     "the ranks loaded different scenes from the same command: a file the scene refers to (a texture, "
                     "mesh or grid) differs between their machines (every rank must read the same files)");
}

}  // namespace bl

// ---- Built-in shapes, mesh finishing, parameter overrides -------------------------------------

#include <cstring>
#include <filesystem>
#include <sstream>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/image_io.h"
#include "engine/scene/mesh_io.h"
#include "engine/scene/scene_load.h"

namespace bl {

Mesh make_rectangle() {
  Mesh m;
  m.positions = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
  m.normals.assign(4, {0, 0, 1});
  // uv = ((x+1)/2, (1−y)/2): row 0 of an image lands at the top (+y).
  m.uvs = {{0, 1}, {1, 1}, {1, 0}, {0, 0}};
  m.indices = {0, 1, 2, 0, 2, 3};
  return m;
}

Mesh make_cube() {
  Mesh m;
  // Each face: outward normal n, in-plane axes a (u) and b (v up); corners n ± a ± b.
  const Vec3f faces[6][3] = {{{1, 0, 0}, {0, 0, -1}, {0, 1, 0}}, {{-1, 0, 0}, {0, 0, 1}, {0, 1, 0}},
                             {{0, 1, 0}, {1, 0, 0}, {0, 0, -1}}, {{0, -1, 0}, {1, 0, 0}, {0, 0, 1}},
                             {{0, 0, 1}, {1, 0, 0}, {0, 1, 0}},  {{0, 0, -1}, {-1, 0, 0}, {0, 1, 0}}};
  for (const auto& f : faces) {
    const Vec3f n = f[0], a = f[1], b = f[2];
    uint32_t base = uint32_t(m.positions.size());
    const float corners[4][2] = {{-1, -1}, {1, -1}, {1, 1}, {-1, 1}};
    for (const auto& c : corners) {
      m.positions.push_back(n + a * c[0] + b * c[1]);
      m.normals.push_back(n);
      m.uvs.push_back({(c[0] + 1) / 2, (1 - c[1]) / 2});
    }
    // Winding (p1−p0)×(p2−p0) = a×b must agree with n; every face above has a×b = n.
    for (uint32_t i : {0u, 1u, 2u, 0u, 2u, 3u}) m.indices.push_back(base + i);
  }
  return m;
}

void finalize_mesh(Mesh& m, const Transform& to_world, bool flip_normals, const std::string& where) {
  // Expects an unpadded mesh (as built by make_*, inline meshes and load_gltf_meshes).
  for (auto& p : m.positions) p = to_world.point(p);
  for (auto& n : m.normals) n = to_world.normal(n);
  const float det = to_world.m[0][0] * (to_world.m[1][1] * to_world.m[2][2] - to_world.m[1][2] * to_world.m[2][1]) -
                    to_world.m[0][1] * (to_world.m[1][0] * to_world.m[2][2] - to_world.m[1][2] * to_world.m[2][0]) +
                    to_world.m[0][2] * (to_world.m[1][0] * to_world.m[2][1] - to_world.m[1][1] * to_world.m[2][0]);
  if (det == 0.f) throw InputError(where + ": degenerate transform (zero scale)");
  // A mirroring transform reverses the winding; swap to keep it consistent with the normals.
  bool swap = (det < 0) != flip_normals;
  if (flip_normals)
    for (auto& n : m.normals) n = -n;
  if (swap)
    for (size_t t = 0; t + 2 < m.indices.size(); t += 3) std::swap(m.indices[t + 1], m.indices[t + 2]);
  for (const auto& p : m.positions)
    if (!is_finite(p)) throw InputError(where + ": vertex position is not finite");
  for (const auto& n : m.normals)
    if (!is_finite(n)) throw InputError(where + ": vertex normal is not finite or zero");
  if (m.indices.empty() || m.indices.size() % 3 != 0) throw InputError(where + ": mesh has no triangles");
  limits::require_at_most(where, "vertex count", m.positions.size(), limits::kMeshElements);
  limits::require_at_most(where, "triangle count", m.indices.size() / 3, limits::kMeshElements);
  for (const auto& p : m.positions)
    if (std::abs(p.x) > limits::kCoordinate || std::abs(p.y) > limits::kCoordinate ||
        std::abs(p.z) > limits::kCoordinate)
      throw InputError(where + ": vertex coordinate exceeds the limit of 1e18 in magnitude");
  for (uint32_t i : m.indices)
    if (i >= m.positions.size()) throw InputError(where + ": triangle index out of range");
  m.positions.push_back({0, 0, 0});  // Embree padding, see Mesh
}

void validate_param(const Param& p, const std::string& where) {
  for (size_t i = 0; i < p.value.size(); ++i) {
    float v = p.value[i];
    if (!std::isfinite(v))
      throw InputError(where + ": parameter '" + p.name + "' element " + std::to_string(i) + " is NaN or infinite");
    if (v < p.lower || v > p.upper) {
      std::ostringstream s;
      // All the digits a float needs: 1.0000001 printed as "1" read as inside [0, 1].
      s << where << ": parameter '" << p.name << "' element " << i << " = " << std::setprecision(9) << v
        << std::setprecision(6) << " is outside its valid range [" << p.lower << ", " << p.upper << "]"
        << (v < 0 && p.lower >= 0 ? " (negative)" : "");
      throw InputError(s.str());
    }
  }
}

namespace {
// The grid of a .vdb file for parameter `name`: one named like it ("fog.density") or like its
// key ("density"), else the file's only grid.
VolumeGrid read_vdb_for(const std::string& path, const std::string& name) {
  try {
    return read_vdb(path, name);
  } catch (const InputError&) {
  }
  const std::string key = name.substr(name.find('.') + 1);
  try {
    return read_vdb(path, key);
  } catch (const InputError&) {
  }
  return read_vdb(path, "");
}
}  // namespace

void apply_override(Scene& scene, const std::string& assignment) {
  auto eq = assignment.find('=');
  if (eq == std::string::npos || eq == 0)
    throw InputError("--set '" + assignment + "': expected NAME=FILE or NAME=v1,v2,...");
  std::string name = assignment.substr(0, eq), rhs = assignment.substr(eq + 1);
  if (rhs.empty()) throw InputError("--set " + name + ": no value after '=' (a file name or numbers)");
  int h = scene.params.find(name);
  if (h < 0) throw InputError("--set: unknown parameter '" + name + "' (see `backlight params`)");
  Param& p = scene.params[h];
  std::vector<float> values;
  // Numbers (including nan/inf, which validation then rejects by name) unless it names a file.
  std::error_code ec;
  bool numeric = !rhs.empty() && !std::filesystem::exists(rhs, ec);
  // A list of more than ~25 numbers is too long for a file name (255 bytes), which is no reason to
  // read it as one: a box's 72 vertex coordinates were refused as an unusable file name.
  if (ec && rhs.find(',') != std::string::npos && rhs.find_first_not_of("0123456789.,+-eE ") == std::string::npos) {
    ec.clear();
    numeric = true;
  }
  if (ec && rhs.find_first_of("/.") != std::string::npos && ec != std::errc::no_such_file_or_directory)
    throw InputError("--set " + name + ": '" + rhs.substr(0, 120) + (rhs.size() > 120 ? "...'" : "'") +
                     " is not a usable file name (" + ec.message() + ")");
  if (numeric) {
    // Every item between commas, the one after a last comma too: getline dropped it, so that
    // "0.5,0.5,0.5," (an item missing, or a comma too many) was taken as three numbers.
    for (size_t begin = 0; numeric && begin <= rhs.size();) {
      size_t comma = rhs.find(',', begin);
      if (comma == std::string::npos) comma = rhs.size();
      const std::string item = rhs.substr(begin, comma - begin);
      begin = comma + 1;
      char* end = nullptr;
      float v = std::strtof(item.c_str(), &end);
      while (end && *end == ' ') ++end;
      if (item.empty() || end == item.c_str() || *end != '\0') numeric = false;
      values.push_back(v);
    }
    // Not numbers and no such file: a list with an empty or malformed item ("0.5,,0.5") is
    // named as such, not as a missing file.
    if (!numeric &&
        (rhs.find_first_of("/.") == std::string::npos ||
         (rhs.find(',') != std::string::npos && rhs.find_first_not_of("0123456789.,+-eE ") == std::string::npos)))
      throw InputError("--set " + name + ": '" + rhs + "' is neither numbers nor an existing image file");
  }
  if (numeric) {
    set_param_values(scene, name, std::move(values), "--set");
    return;
  } else if (p.shape.size() == 4 || std::filesystem::path(rhs).extension() == ".vol" ||
             std::filesystem::path(rhs).extension() == ".vdb") {
    // A volume grid: a .vol or .vdb file of exactly the parameter's [Z, Y, X, C] (the .vdb grid
    // named after the parameter, or its only one).
    VolumeGrid grid = std::filesystem::path(rhs).extension() == ".vdb" ? read_vdb_for(rhs, name) : read_vol(rhs);
    if (grid.shape() != p.shape) {
      const auto shape = grid.shape();
      throw InputError(rhs + ": grid is [" + std::to_string(shape[0]) + "," + std::to_string(shape[1]) + "," +
                       std::to_string(shape[2]) + "," + std::to_string(shape[3]) + "] but parameter '" + name +
                       "' has shape " + scene.params.shape_string(h));
    }
    values = std::move(grid.data);
  } else if (p.geometry && p.shape.size() == 2 && p.shape[1] == 3 && std::filesystem::path(rhs).extension() == ".ply") {
    // A mesh's positions from a PLY file with the same vertices in the same order (a deformed copy
    // of the mesh): its vertices are taken as world positions, no shape transform applied.
    const Mesh m = read_ply(rhs);
    if (m.positions.size() != size_t(p.shape[0]))
      throw InputError(rhs + ": the PLY file has " + std::to_string(m.positions.size()) + " vertices but parameter '" +
                       name + "' has shape " + scene.params.shape_string(h));
    for (const Vec3f& v : m.positions) values.insert(values.end(), {v.x, v.y, v.z});
  } else {
    values.clear();
    // 8-bit files in the parameter's own colour space (a linear roughness map was sRGB-decoded).
    Image img = read_image(rhs, p.is_image() && p.srgb);
    if (!p.is_image() || img.width != p.width() || img.height != p.height())
      throw InputError(rhs + ": image is " + std::to_string(img.width) + "x" + std::to_string(img.height) +
                       " but parameter '" + name + "' has shape " + scene.params.shape_string(h));
    int c = p.channels();
    values.resize(p.size());
    for (size_t i = 0; i < img.pixel_count(); ++i)
      for (int k = 0; k < c; ++k)
        values[i * size_t(c) + size_t(k)] = img.data[i * size_t(img.channels) + size_t(std::min(k, img.channels - 1))];
  }
  Param candidate = p;
  candidate.value = values;
  validate_param(candidate, "--set " + name);
  p.value = std::move(values);
  scene.prepare_sampling();
}

void set_param_values(Scene& scene, const std::string& name, std::vector<float> values, const std::string& where) {
  const int h = scene.params.find(name);
  if (h < 0) throw InputError(where + ": unknown parameter '" + name + "' (see `backlight params`)");
  Param& p = scene.params[h];
  if (values.size() == 1 && p.size() > 1) values.assign(p.size(), values[0]);  // broadcast a scalar
  if (values.size() == 3 && p.is_image() && p.channels() == 3) {
    std::vector<float> full(p.size());
    for (size_t i = 0; i < full.size(); ++i) full[i] = values[i % 3];
    values = full;
  }
  if (values.size() != p.size())
    throw InputError(where + " " + name + ": got " + std::to_string(values.size()) + " values, parameter has shape " +
                     scene.params.shape_string(h));
  Param candidate = p;
  candidate.value = values;
  validate_param(candidate, where + " " + name);
  p.value = std::move(values);
  scene.prepare_sampling();
}

}  // namespace bl
