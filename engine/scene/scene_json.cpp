// JSON scene loader. Strict: every key is known, every value checked, errors carry the file and
// the JSON pointer (or line:column for syntax errors) — the format is documented in scenes/README.md.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/image_io.h"
#include "engine/io/json_node.h"
#include "engine/scene/mesh_io.h"
#include "engine/scene/openvdb_io.h"
#include "engine/scene/scene_load.h"
#include "engine/scene/volume_io.h"

namespace bl {

namespace fs = std::filesystem;
Camera parse_camera(Node& n, const std::string& default_name) {
  Camera c;
  c.name = n.string("name", default_name);
  if (const std::string problem = object_name_problem(c.name); !problem.empty())
    n.fail_at("name", "camera name '" + printable_name(c.name) + "' " + problem);
  c.origin = n.vec3("origin");
  c.target = n.vec3("target");
  c.up = n.vec3("up", {0, 1, 0});
  c.fov_degrees = float(n.number_required("fov", 1e-3, 179.9));
  const std::string axis = n.string("fov_axis", "x");
  if (axis == "x")
    c.fov_axis = Camera::FovAxis::X;
  else if (axis == "y")
    c.fov_axis = Camera::FovAxis::Y;
  else if (axis == "diagonal")
    c.fov_axis = Camera::FovAxis::Diagonal;
  else if (axis == "smaller")
    c.fov_axis = Camera::FovAxis::Smaller;
  else if (axis == "larger")
    c.fov_axis = Camera::FovAxis::Larger;
  else
    n.fail_at("fov_axis", "expected \"x\", \"y\", \"diagonal\", \"smaller\" or \"larger\"");
  if (const json* r = n.find("resolution")) {
    if (!r->is_array() || r->size() != 2 || !(*r)[0].is_number_integer() || !(*r)[1].is_number_integer() ||
        (*r)[0].get<int64_t>() < 1 || (*r)[1].get<int64_t>() < 1 || (*r)[0].get<int64_t>() > 16384 ||
        (*r)[1].get<int64_t>() > 16384)
      n.fail_at("resolution", "expected [width, height] with positive integers ≤ 16384");
    c.width = (*r)[0].get<int>();
    c.height = (*r)[1].get<int>();
  }
  c.near_clip = float(n.number("near_clip", 1e-3, 0, 1e6));
  n.finish();
  if (length(c.target - c.origin) <= 0) n.fail("origin and target coincide");
  if (length(cross(normalize(c.target - c.origin), c.up)) < 1e-6f) n.fail("up is parallel to the view direction");
  c.update();
  return c;
}

namespace {

struct Loader {
  std::string file;
  fs::path dir;
  Scene& scene;
  // Running totals over all shapes (a glTF shape listed many times costs its size every time).
  uint64_t total_vertices = 0, total_triangles = 0, total_shapes = 0;
  // Warnings of the files read (a glTF's skipped points and lines), printed once the scene loaded.
  std::vector<std::string> warnings;

  std::string resolve(const std::string& f) const { return (dir / f).lexically_normal().string(); }
  // The file a node's "file" names, relative to the scene's folder; an empty name is refused here
  // (it said "backlight: : file not found", naming neither the scene nor the key).
  template <class N>
  std::string input_file(N& n) const {
    const std::string f = n.string("file");
    if (f.empty()) n.fail_at("file", "the file name is empty");
    return resolve(f);
  }

  // A texturable value → a parameter "<owner>.<key>" and a slot reading it.
  TextureSlot texturable(const json& v, const std::string& where, const std::string& owner, const std::string& key,
                         bool scalar, float lower, float upper) {
    Param p;
    p.name = owner + "." + key;
    p.lower = lower;
    p.upper = upper;
    TextureSlot slot;
    if (v.is_number()) {
      float x = v.get<float>();
      p.shape = {scalar ? 1 : 3};
      p.value.assign(size_t(p.shape[0]), x);
    } else if (v.is_array()) {
      if (scalar && v.size() == 1) {
        p.shape = {1};
      } else if (v.size() == 3 && !scalar) {
        p.shape = {3};
      } else {
        throw file_error(file, where + (scalar ? ": expected a number" : ": expected a number or [r, g, b]"));
      }
      for (const auto& e : v) {
        if (!e.is_number()) throw file_error(file, where + ": expected numbers");
        p.value.push_back(e.get<float>());
      }
    } else if (v.is_object()) {
      Node n(v, where, file);
      std::string type = n.string("type");
      if (type != "bitmap") n.fail_at("type", "unknown texture type '" + type + "' (expected \"bitmap\")");
      std::string path = input_file(n);
      std::string wrap = n.string("wrap", "repeat");
      if (wrap != "repeat" && wrap != "clamp" && wrap != "mirror")
        n.fail_at("wrap", "expected \"repeat\", \"clamp\" or \"mirror\"");
      std::string cs = n.string("color_space", "auto");
      if (cs != "auto" && cs != "srgb" && cs != "linear") n.fail_at("color_space", "expected \"srgb\" or \"linear\"");
      n.finish();
      Image img = read_image(path, cs != "linear");
      if (cs == "srgb" && img.from_float_file) img = read_image(path, false);  // float data is linear already
      int c = scalar ? 1 : 3;
      p.shape = {img.height, img.width, c};
      p.srgb = cs != "linear";
      p.value.resize(size_t(img.width) * size_t(img.height) * size_t(c));
      for (size_t i = 0; i < img.pixel_count(); ++i)
        for (int k = 0; k < c; ++k)
          p.value[i * size_t(c) + size_t(k)] =
              img.data[i * size_t(img.channels) + size_t(std::min(k, img.channels - 1))];
      slot.bitmap = true;
      slot.wrap = wrap == "clamp" ? Wrap::Clamp : wrap == "mirror" ? Wrap::Mirror : Wrap::Repeat;
    } else {
      throw file_error(file, where + ": expected a number, [r, g, b] or a bitmap texture object");
    }
    validate_param(p, file + ": " + where);
    slot.param = scene.params.add(std::move(p), file + ": " + where);
    return slot;
  }

  void integrator(Node n) {
    auto& s = scene.settings;
    s.spp = int(n.integer("spp", s.spp, 1, long(limits::kSpp)));
    s.max_depth = int(n.integer("max_depth", s.max_depth, -1, 1024));
    if (s.max_depth == 0) n.fail_at("max_depth", "must be ≥ 1, or −1 for unlimited");
    s.rr_depth = int(n.integer("rr_depth", s.rr_depth, 0, 1024));
    s.seed = uint64_t(n.integer("seed", 0, 0, 4294967295L));
    s.hide_emitters = n.boolean("hide_emitters", false);
    n.finish();
  }

  void camera(Node n) {
    const int medium = n.has("medium") ? medium_index(n, "medium") : -1;
    Camera c = parse_camera(n, "camera" + std::to_string(scene.cameras.size()));
    c.medium = medium;
    scene.cameras.push_back(std::move(c));
  }

  int medium_index(Node& n, const char* key) {
    const std::string name = n.string(key);
    for (size_t i = 0; i < scene.media.size(); ++i)
      if (scene.media[i].name == name) return int(i);
    n.fail_at(key, "unknown medium '" + name + "'");
  }

  // A parameter "<medium>.<key>" from a number, [r, g, b] (rgb) or a grid object
  // {"type": "vol", "file": ...} ([Z, Y, X, C]); every value within [lower, upper].
  int medium_param(Node& n, const std::string& medium, const char* key, bool rgb, float lower, float upper,
                   VolumeGrid* grid_out = nullptr) {
    const json& v = n.at(key);
    const std::string where = n.pointer(key);
    Param p;
    p.name = medium + "." + key;
    p.lower = lower;
    p.upper = upper;
    if (v.is_number()) {
      p.shape = {rgb ? 3 : 1};
      p.value.assign(size_t(p.shape[0]), v.get<float>());
    } else if (v.is_array() && rgb && v.size() == 3) {
      p.shape = {3};
      for (const auto& e : v) {
        if (!e.is_number()) throw file_error(file, where + ": expected numbers");
        p.value.push_back(e.get<float>());
      }
    } else if (v.is_object()) {
      Node g(v, where, file);
      const std::string type = g.string("type");
      if (type != "vol" && type != "vdb") g.fail_at("type", "unknown grid type '" + type + "' (expected vol or vdb)");
      VolumeGrid grid = type == "vol" ? read_vol(input_file(g)) : read_vdb(input_file(g), g.string("grid", ""));
      g.finish();
      if (grid.channels != 1 && !(rgb && grid.channels == 3))
        throw file_error(file, where + ": the grid has " + std::to_string(grid.channels) + " channels; expected " +
                                   (rgb ? "1 or 3" : "1"));
      p.shape = grid.shape();
      p.value = std::move(grid.data);
      grid.data.clear();
      if (grid_out) *grid_out = grid;
    } else {
      throw file_error(file, where + (rgb ? ": expected a number, [r, g, b] or a grid object"
                                          : ": expected a number or a grid object"));
    }
    validate_param(p, file + ": " + where);
    return scene.params.add(std::move(p), file + ": " + where);
  }

  void medium(const std::string& name, Node n) {
    if (const std::string problem = object_name_problem(name); !problem.empty())
      n.fail("medium name '" + printable_name(name) + "' " + problem);
    Medium m;
    m.name = name;
    const std::string type = n.string("type");
    if (type != "homogeneous" && type != "grid")
      n.fail_at("type", "unknown medium type '" + type + "' (expected homogeneous or grid)");
    m.grid = type == "grid";
    VolumeGrid grid;
    m.density = medium_param(n, name, "density", false, 0.f, 1e30f, &grid);
    const bool density_is_grid = scene.params[m.density].shape.size() == 4;
    if (m.grid != density_is_grid)
      n.fail_at("density", m.grid ? "a grid medium needs a grid density ({\"type\": \"vol\", \"file\": ...})"
                                  : "a homogeneous medium takes a number");
    m.albedo = n.has("albedo") ? medium_param(n, name, "albedo", true, 0.f, 1.f) : [&] {
      Param p;
      p.name = name + ".albedo";
      p.shape = {3};
      p.value = {1.f, 1.f, 1.f};
      p.upper = 1.f;
      return scene.params.add(std::move(p), file);
    }();
    if (scene.params[m.albedo].shape.size() == 4 && !m.grid) n.fail_at("albedo", "an albedo grid needs a grid medium");
    {
      Param p;
      p.name = name + ".scale";
      p.shape = {1};
      p.value = {float(n.number("scale", 1.0, 0.0, 1e30))};
      m.scale = scene.params.add(std::move(p), file);
    }
    if (n.has("phase")) {
      Node ph = n.child("phase");
      const std::string pt = ph.string("type");
      if (pt == "hg") {
        Param p;
        p.name = name + ".g";
        p.shape = {1};
        p.value = {float(ph.number_required("g", -kHgMaxAbsG, kHgMaxAbsG))};
        p.lower = -kHgMaxAbsG;
        p.upper = kHgMaxAbsG;
        m.g = scene.params.add(std::move(p), file);
      } else if (pt != "isotropic") {
        ph.fail_at("type", "unknown phase function '" + pt + "' (expected isotropic or hg)");
      }
      ph.finish();
    }
    // Above 1 everywhere: where σ̄ = σ_t (a plateau of maxima) null collisions never happen and
    // the null-collision terms of the gradient would be lost there (Mitsuba 3's prbvolpath moves
    // by 10% between majorant = max and a larger one in that case).
    m.headroom = float(n.number("majorant_headroom", 1.25, 1.05, 100.0));
    m.light_derivatives = float(n.number("light_derivatives", 0.0, 0.0, 1.0));
    if (m.grid) {
      if (n.has("bbox")) {
        Node b = n.child("bbox");
        m.bbox_min = b.vec3("min");
        m.bbox_max = b.vec3("max");
        b.finish();
      } else {
        // The unit cube maps to the box stored in the .vol file.
        m.bbox_min = grid.bbox_min;
        m.bbox_max = grid.bbox_max;
      }
      const Vec3f extent = m.bbox_max - m.bbox_min;
      // Lookups divide by the extent: a denormal one (1e-40) has an infinite reciprocal (NaN pixels).
      if (!(extent.x > 0.f && extent.y > 0.f && extent.z > 0.f) || !std::isfinite(extent.x + extent.y + extent.z) ||
          !std::isfinite(1.f / extent.x) || !std::isfinite(1.f / extent.y) || !std::isfinite(1.f / extent.z))
        n.fail_at(n.has("bbox") ? "bbox" : "density",
                  "the grid's box must have positive, finite extent (with a finite reciprocal)");
    } else if (n.has("bbox")) {
      n.fail_at("bbox", "only grid media have a box");
    }
    n.finish();
    scene.media.push_back(std::move(m));
  }

  void material(const std::string& name, Node n) {
    if (const std::string problem = object_name_problem(name); !problem.empty())
      n.fail("material name '" + printable_name(name) + "' " + problem);
    Material m;
    m.name = name;
    std::string type = n.string("type");
    m.two_sided = n.boolean("two_sided", true);
    auto tex = [&](const char* key, bool scalar, float lo, float hi) {
      return texturable(n.at(key), n.pointer(key), name, key, scalar, lo, hi);
    };
    if (type == "null") {
      m.is_null = true;
    } else if (type == "diffuse") {
      m.type = BsdfType::Diffuse;
      m.albedo = tex("albedo", false, 0.f, 1.f);
    } else if (type == "roughconductor") {
      m.type = BsdfType::RoughConductor;
      m.specular = tex("specular", false, 0.f, 1.f);
      m.roughness = tex("roughness", true, 0.f, 4.f);
    } else if (type == "roughplastic") {
      m.type = BsdfType::RoughPlastic;
      m.albedo = tex("albedo", false, 0.f, 1.f);
      m.roughness = tex("roughness", true, 0.f, 4.f);
      m.ior = float(n.number("ior", 1.5, 1.0001, 4.0));
    } else if (type == "metallic_roughness") {
      m.type = BsdfType::MetallicRoughness;
      m.albedo = tex("base_color", false, 0.f, 1.f);
      m.roughness = tex("roughness", true, 0.f, 4.f);
      m.metallic = tex("metallic", true, 0.f, 1.f);
    } else {
      n.fail_at("type", "unknown material type '" + type +
                            "' (expected diffuse, roughconductor, roughplastic, metallic_roughness or null)");
    }
    n.finish();
    scene.materials.push_back(std::move(m));
  }

  Transform transform(Node n) {
    if (const json* m = n.find("matrix")) {
      if (!m->is_array() || m->size() != 4) n.fail_at("matrix", "expected a 4×4 row-major array");
      Transform t;
      for (int i = 0; i < 4; ++i) {
        const json& row = (*m)[size_t(i)];
        if (!row.is_array() || row.size() != 4) n.fail_at("matrix", "expected a 4×4 row-major array");
        for (int k = 0; k < 4; ++k) {
          if (!row[size_t(k)].is_number()) n.fail_at("matrix", "expected numbers");
          t.m[i][k] = row[size_t(k)].get<float>();
        }
      }
      // Points are transformed as affine (w stays 1): a projective last row would be dropped.
      if (t.m[3][0] != 0.f || t.m[3][1] != 0.f || t.m[3][2] != 0.f || t.m[3][3] != 1.f)
        n.fail_at("matrix", "the last row must be [0, 0, 0, 1] (transforms are affine)");
      n.finish();
      return t;
    }
    Transform t;
    if (const json* s = n.find("scale")) {
      Vec3f v = s->is_number() ? Vec3f(s->get<float>()) : n.vec3_of(*s, n.pointer("scale"));
      t = Transform::scale(v) * t;
    }
    if (n.has("rotate")) {
      Node r = n.child("rotate");
      Vec3f axis = r.vec3("axis");
      if (length(axis) <= 0) r.fail_at("axis", "zero rotation axis");
      t = Transform::rotate(axis, float(r.number_required("angle"))) * t;
      r.finish();
    }
    if (n.has("translate")) t = Transform::translate(n.vec3("translate")) * t;
    n.finish();
    return t;
  }

  std::vector<Vec3f> vec3_list(const json& v, const std::string& where) {
    if (!v.is_array()) throw file_error(file, where + ": expected an array of [x, y, z]");
    std::vector<Vec3f> out;
    Node dummy = Node::at_pointer(where, file);
    for (size_t i = 0; i < v.size(); ++i) out.push_back(dummy.vec3_of(v[i], where + "/" + std::to_string(i)));
    return out;
  }

  Mesh inline_mesh(Node& n) {
    Mesh m;
    m.positions = vec3_list(n.at("positions"), n.pointer("positions"));
    const json& idx = n.at("indices");
    if (!idx.is_array()) n.fail_at("indices", "expected an array of [i, j, k]");
    for (size_t t = 0; t < idx.size(); ++t) {
      const json& tri = idx[t];
      if (!tri.is_array() || tri.size() != 3) n.fail_at("indices/" + std::to_string(t), "expected [i, j, k]");
      for (const auto& e : tri) {
        if (!e.is_number_integer() || e.get<long>() < 0 || e.get<size_t>() >= m.positions.size())
          n.fail_at("indices/" + std::to_string(t), "index out of range");
        m.indices.push_back(e.get<uint32_t>());
      }
    }
    if (const json* nr = n.find("normals")) {
      m.normals = vec3_list(*nr, n.pointer("normals"));
      if (m.normals.size() != m.positions.size()) n.fail_at("normals", "needs one normal per position");
    }
    if (const json* uv = n.find("uvs")) {
      if (!uv->is_array() || uv->size() != m.positions.size()) n.fail_at("uvs", "needs one [u, v] per position");
      for (const auto& e : *uv) {
        if (!e.is_array() || e.size() != 2 || !e[0].is_number() || !e[1].is_number())
          n.fail_at("uvs", "expected [u, v]");
        Vec2f uv{e[0].get<float>(), e[1].get<float>()};
        if (!std::isfinite(uv.x) || !std::isfinite(uv.y)) n.fail_at("uvs", "not a finite number");
        m.uvs.push_back(uv);
      }
    }
    return m;
  }

  void shape(Node n, std::set<std::string>& names) {
    std::string name = n.string("name");
    if (const std::string problem = object_name_problem(name); !problem.empty())
      n.fail_at("name", "shape name '" + printable_name(name) + "' " + problem);
    if (!names.insert(name).second) n.fail_at("name", "duplicate shape name '" + name + "'");
    std::string type = n.string("type");
    Transform to_world;
    if (n.has("transform")) to_world = transform(n.child("transform"));
    bool flip = n.boolean("flip_normals", false);
    std::string mat_name = n.string("material");
    int mat = -1;
    for (size_t i = 0; i < scene.materials.size(); ++i)
      if (scene.materials[i].name == mat_name) mat = int(i);
    if (mat < 0) n.fail_at("material", "unknown material '" + mat_name + "'");

    std::vector<Mesh> parts;
    if (type == "rectangle") {
      parts.push_back(make_rectangle());
    } else if (type == "cube") {
      parts.push_back(make_cube());
    } else if (type == "mesh") {
      parts.push_back(inline_mesh(n));
    } else if (type == "gltf") {
      parts = load_gltf_meshes(input_file(n), Transform(), warnings);
      if (parts.empty()) n.fail_at("file", "the glTF file has no triangle meshes");
    } else if (type == "obj") {
      parts.push_back(read_obj(input_file(n), n.boolean("flip_tex_coords", true)));
    } else if (type == "ply") {
      parts.push_back(read_ply(input_file(n)));
    } else if (type == "sphere") {
      parts.push_back(make_sphere(int(n.integer("segments", 64, 4, 4096))));
    } else {
      n.fail_at("type", "unknown shape type '" + type + "' (expected rectangle, cube, sphere, mesh, obj, ply or gltf)");
    }
    if (n.boolean("face_normals", false))
      for (auto& part : parts) part.normals.clear();
    // One emitter per shape even when a glTF file holds several primitives: merge them.
    Mesh merged;
    merged.name = name;
    for (auto& part : parts) {
      uint32_t base = uint32_t(merged.positions.size());
      bool normals = !part.normals.empty(), uvs = !part.uvs.empty();
      if (!merged.positions.empty() && (normals != !merged.normals.empty() || uvs != !merged.uvs.empty()))
        n.fail_at("file", "primitives disagree on having normals/uvs");
      merged.positions.insert(merged.positions.end(), part.positions.begin(), part.positions.end());
      merged.normals.insert(merged.normals.end(), part.normals.begin(), part.normals.end());
      merged.uvs.insert(merged.uvs.end(), part.uvs.begin(), part.uvs.end());
      for (uint32_t i : part.indices) merged.indices.push_back(base + i);
    }
    merged.material = mat;
    if (n.has("interior")) merged.interior = medium_index(n, "interior");
    if (n.has("exterior")) merged.exterior = medium_index(n, "exterior");
    // The shape, not its "type": finalize_mesh's errors are about its transform or vertices.
    const std::string where = file + ": " + n.pointer() + " ('" + name + "')";
    finalize_mesh(merged, to_world, flip, where);
    limits::add_to_total(where, "shape count", total_shapes, 1, limits::kShapes);
    limits::add_to_total(where, "total vertex count (all shapes)", total_vertices, merged.vertex_count(),
                         limits::kSceneElements);
    limits::add_to_total(where, "total triangle count (all shapes)", total_triangles, merged.triangle_count(),
                         limits::kSceneElements);
    if (n.has("emitter")) {
      // A null surface is crossed without a vertex (path.h): its emission was left out of what
      // rays hitting it see and kept in light sampling's MIS weight (a lamp 24% too dark; all
      // black from Mitsuba XML's null bsdf). Refused rather than rendered wrong.
      if (scene.materials[size_t(mat)].is_null)
        n.fail_at("emitter",
                  "an emitter on a shape whose material is null (crossed without a vertex) is not supported: give "
                  "the shape a material (a black diffuse one emits only)");
      Node e = n.child("emitter");
      AreaEmitter em;
      em.mesh = int(scene.meshes.size());
      em.radiance = texturable(e.at("radiance"), e.pointer("radiance"), name, "radiance", false, 0.f, 1e30f);
      e.finish();
      merged.emitter = int(scene.area_emitters.size());
      scene.area_emitters.push_back(std::move(em));
    }
    n.finish();
    scene.meshes.push_back(std::move(merged));
  }

  void environment(Node n) {
    std::string type = n.string("type");
    Environment& env = scene.environment;
    env.present = true;
    if (type == "constant") {
      env.is_map = false;
      env.param =
          texturable(n.at("radiance"), n.pointer("radiance"), "environment", "radiance", false, 0.f, 1e30f).param;
    } else if (type == "envmap") {
      env.is_map = true;
      env.scale = float(n.number("scale", 1.0, 0.0, 1e30));
      // "backlight" (nearest texel, u = 0 at +z) or "mitsuba" (Mitsuba 3's envmap: bilinear,
      // u = 0 at −z; kernels/emitter/envmap.h).
      const std::string convention = n.string("convention", "backlight");
      if (convention != "backlight" && convention != "mitsuba")
        n.fail_at("convention", "expected \"backlight\" or \"mitsuba\"");
      env.bilinear = convention == "mitsuba";
      const std::string cs = n.string("color_space", "linear");
      if (cs != "auto" && cs != "srgb" && cs != "linear") n.fail_at("color_space", "expected \"srgb\" or \"linear\"");
      if (n.string("file").empty()) n.fail_at("file", "the file name is empty");
      json tex = {{"type", "bitmap"}, {"file", n.string("file")}, {"color_space", cs}};
      TextureSlot slot = texturable(tex, n.pointer("file"), "environment", "radiance", false, 0.f, 1e30f);
      env.param = slot.param;
      if (env.bilinear && scene.params[env.param].height() < 2)
        n.fail_at("file", "the mitsuba convention needs an image at least 2 pixels high");
      // The map's orientation (Mitsuba's to_world): a rotation; directions have no position.
      if (n.has("transform")) {
        const Transform t = transform(n.child("transform"));
        if (t.m[0][3] != 0.f || t.m[1][3] != 0.f || t.m[2][3] != 0.f)
          n.fail_at("transform", "an environment is infinitely far away: a translation would do nothing (remove it)");
        double worst = 0.0;
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            double dot_ij = 0.0;
            for (int k = 0; k < 3; ++k) dot_ij += double(t.m[k][i]) * double(t.m[k][j]);
            worst = std::max(worst, std::abs(dot_ij - (i == j ? 1.0 : 0.0)));
          }
        const double det = double(t.m[0][0]) * (double(t.m[1][1]) * t.m[2][2] - double(t.m[1][2]) * t.m[2][1]) -
                           double(t.m[0][1]) * (double(t.m[1][0]) * t.m[2][2] - double(t.m[1][2]) * t.m[2][0]) +
                           double(t.m[0][2]) * (double(t.m[1][0]) * t.m[2][1] - double(t.m[1][1]) * t.m[2][0]);
        if (!(worst <= 1e-4) || !(det > 0.0))
          n.fail_at("transform", "must be a rotation (a scale, shear or mirror image would distort the sky)");
        env.rotated = false;
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            env.rotation[i][j] = t.m[i][j];
            env.rotated = env.rotated || t.m[i][j] != (i == j ? 1.f : 0.f);
          }
      }
    } else {
      n.fail_at("type", "unknown environment type '" + type + "' (expected constant or envmap)");
    }
    n.finish();
  }

  void load(const json& root) {
    Node n(root, "", file);
    if (n.has("integrator")) integrator(n.child("integrator"));
    if (n.has("media")) {
      const json& media = n.at("media");
      if (!media.is_object()) n.fail_at("media", "expected an object name → medium");
      for (auto it = media.begin(); it != media.end(); ++it)
        medium(it.key(), Node(it.value(), "/media/" + it.key(), file));
    }
    const json& cams = n.at("cameras");
    if (!cams.is_array() || cams.empty()) n.fail_at("cameras", "expected a non-empty list of cameras");
    for (size_t i = 0; i < cams.size(); ++i) camera(Node(cams[i], "/cameras/" + std::to_string(i), file));
    const json& mats = n.at("materials");
    if (!mats.is_object()) n.fail_at("materials", "expected an object name → material");
    for (auto it = mats.begin(); it != mats.end(); ++it)
      material(it.key(), Node(it.value(), "/materials/" + it.key(), file));
    const json& shapes = n.at("shapes");
    if (!shapes.is_array() || shapes.empty()) n.fail_at("shapes", "expected a non-empty list of shapes");
    std::set<std::string> names;
    for (size_t i = 0; i < shapes.size(); ++i) shape(Node(shapes[i], "/shapes/" + std::to_string(i), file), names);
    if (n.has("environment")) environment(n.child("environment"));
    n.finish();
  }
};

}  // namespace

std::unique_ptr<Scene> load_json_scene(const std::string& path) {
  const std::string text = read_json_file(path);
  return build_json_scene(parse_json_text(text, path), path);
}

std::unique_ptr<Scene> build_json_scene(const json& root, const std::string& path) {
  auto scene = std::make_unique<Scene>();
  scene->source = path;
  Loader loader{path, fs::path(path).parent_path(), *scene};
  loader.load(root);
  scene->add_geometry_params();
  scene->prepare();
  for (std::string& w : scene->camera_medium_warnings()) loader.warnings.push_back(std::move(w));
  for (std::string& w : scene->open_medium_warnings()) loader.warnings.push_back(std::move(w));
  // A scene that fails to load gets its one error line only; one that loads, its warnings.
  for (const std::string& w : loader.warnings) std::fprintf(stderr, "%s\n", w.c_str());
  return scene;
}

std::unique_ptr<Scene> load_scene(const std::string& path) {
  return with_path_errors([&] {
    std::string ext = fs::path(path).extension().string();
    for (auto& ch : ext) ch = char(std::tolower(ch));
    if (ext == ".gltf" || ext == ".glb") return load_gltf_scene(path);
    if (ext == ".xml") return load_xml_scene(path);
    return load_json_scene(path);
  });
}

}  // namespace bl
