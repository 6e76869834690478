// JSON scene loader. Strict: every key is known, every value checked, errors carry the file and
// the JSON pointer (or line:column for syntax errors) — the format is documented in scenes/README.md.
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "engine/errors.h"
#include "engine/image_io.h"
#include "engine/json_node.h"
#include "engine/scene_load.h"

namespace bl {

namespace fs = std::filesystem;
Camera parse_camera(Node& n, const std::string& default_name) {
  Camera c;
  c.name = n.string("name", default_name);
  c.origin = n.vec3("origin");
  c.target = n.vec3("target");
  c.up = n.vec3("up", {0, 1, 0});
  c.fov_degrees = float(n.number_required("fov", 1e-3, 179.9));
  std::string axis = n.string("fov_axis", "x");
  if (axis != "x" && axis != "y") n.fail_at("fov_axis", "expected \"x\" or \"y\"");
  c.fov_axis_x = axis == "x";
  if (const json* r = n.find("resolution")) {
    if (!r->is_array() || r->size() != 2 || !(*r)[0].is_number_integer() || !(*r)[1].is_number_integer() ||
        (*r)[0].get<int>() < 1 || (*r)[1].get<int>() < 1 || (*r)[0].get<int>() > 16384 || (*r)[1].get<int>() > 16384)
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

  std::string resolve(const std::string& f) const { return (dir / f).lexically_normal().string(); }

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
      std::string path = resolve(n.string("file"));
      std::string wrap = n.string("wrap", "repeat");
      if (wrap != "repeat" && wrap != "clamp") n.fail_at("wrap", "expected \"repeat\" or \"clamp\"");
      std::string cs = n.string("color_space", "auto");
      if (cs != "auto" && cs != "srgb" && cs != "linear") n.fail_at("color_space", "expected \"srgb\" or \"linear\"");
      n.finish();
      Image img = read_image(path, cs != "linear");
      if (cs == "srgb" && img.from_float_file) img = read_image(path, false);  // float data is linear already
      int c = scalar ? 1 : 3;
      p.shape = {img.height, img.width, c};
      p.value.resize(size_t(img.width) * size_t(img.height) * size_t(c));
      for (size_t i = 0; i < img.pixel_count(); ++i)
        for (int k = 0; k < c; ++k)
          p.value[i * size_t(c) + size_t(k)] =
              img.data[i * size_t(img.channels) + size_t(std::min(k, img.channels - 1))];
      slot.bitmap = true;
      slot.wrap = wrap == "clamp" ? Wrap::Clamp : Wrap::Repeat;
    } else {
      throw file_error(file, where + ": expected a number, [r, g, b] or a bitmap texture object");
    }
    validate_param(p, file + ": " + where);
    slot.param = scene.params.add(std::move(p));
    return slot;
  }

  void integrator(Node n) {
    auto& s = scene.settings;
    s.spp = int(n.integer("spp", s.spp, 1, 1 << 24));
    s.max_depth = int(n.integer("max_depth", s.max_depth, -1, 1024));
    if (s.max_depth == 0) n.fail_at("max_depth", "must be ≥ 1, or −1 for unlimited");
    s.rr_depth = int(n.integer("rr_depth", s.rr_depth, 0, 1024));
    s.seed = uint64_t(n.integer("seed", 0, 0, 4294967295L));
    s.hide_emitters = n.boolean("hide_emitters", false);
    n.finish();
  }

  void camera(Node n) { scene.cameras.push_back(parse_camera(n, "camera" + std::to_string(scene.cameras.size()))); }

  void material(const std::string& name, Node n) {
    if (name.find('.') != std::string::npos) n.fail("material names must not contain '.'");
    Material m;
    m.name = name;
    std::string type = n.string("type");
    m.two_sided = n.boolean("two_sided", true);
    auto tex = [&](const char* key, bool scalar, float lo, float hi) {
      return texturable(n.at(key), n.pointer(key), name, key, scalar, lo, hi);
    };
    if (type == "diffuse") {
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
    } else {
      n.fail_at("type", "unknown material type '" + type + "' (expected diffuse, roughconductor or roughplastic)");
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
    if (name.empty() || name.find('.') != std::string::npos)
      n.fail_at("name", "shape names must be non-empty and contain no '.'");
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
      parts = load_gltf_meshes(resolve(n.string("file")), Transform());
      if (parts.empty()) n.fail_at("file", "the glTF file has no triangle meshes");
    } else {
      n.fail_at("type", "unknown shape type '" + type + "' (expected rectangle, cube, mesh or gltf)");
    }
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
    finalize_mesh(merged, to_world, flip, file + ": " + n.pointer("type"));
    if (n.has("emitter")) {
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
      json tex = {{"type", "bitmap"}, {"file", n.string("file")}, {"color_space", "linear"}};
      TextureSlot slot = texturable(tex, n.pointer("file"), "environment", "radiance", false, 0.f, 1e30f);
      env.param = slot.param;
    } else {
      n.fail_at("type", "unknown environment type '" + type + "' (expected constant or envmap)");
    }
    n.finish();
  }

  void load(const json& root) {
    Node n(root, "", file);
    if (n.has("integrator")) integrator(n.child("integrator"));
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
  if (!fs::exists(path)) throw file_error(path, "file not found");
  if (!fs::is_regular_file(path)) throw file_error(path, "not a regular file");
  std::ifstream f(path, std::ios::binary);
  if (!f) throw file_error(path, "cannot open");
  std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  json root = parse_json_text(text, path);
  auto scene = std::make_unique<Scene>();
  scene->source = path;
  Loader loader{path, fs::path(path).parent_path(), *scene};
  loader.load(root);
  scene->prepare();
  return scene;
}

std::unique_ptr<Scene> load_scene(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  for (auto& ch : ext) ch = char(std::tolower(ch));
  if (ext == ".gltf" || ext == ".glb") return load_gltf_scene(path);
  return load_json_scene(path);
}

}  // namespace bl
