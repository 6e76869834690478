// Mitsuba 3 XML scenes (pugixml), translated into backlight's JSON scene and built by its loader.
//
// Supported: <default>/$name substitution, id/<ref>, shapes obj, ply, rectangle, cube, sphere
// (tessellated), to_world (matrix, lookat, translate, rotate, scale in document order), bsdfs
// diffuse, roughconductor (eta/k → Schlick), conductor, roughplastic, plastic, twosided, null,
// textures bitmap, emitters area, constant and envmap (identity to_world), sensor perspective with film hdrfilm and a
// sampler, integrators path/prb/volpath/prbvolpath, media homogeneous and heterogeneous (grey σ_t, a
// gridvolume .vol with a scale-and-translate to_world, constvolume values, phase isotropic or hg)
// as shape interiors/exteriors and sensor media. Anything else is an error naming the plugin and its line;
// attributes that do not change the image (file formats, far_clip, …) give one warning.
#include <pugixml.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/json_node.h"
#include "engine/scene/scene_load.h"

namespace bl {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

constexpr int kXmlDepth = 64;  // nesting of XML elements

class XmlScene {
 public:
  XmlScene(std::string path, std::string text) : path_(std::move(path)), text_(std::move(text)) {}
  const std::vector<std::string>& warnings() const { return warnings_; }

  // An error of the translated scene names a place in it by JSON pointer ("/shapes/3 ('shape_3'):
  // degenerate transform"), which an XML file's author cannot look up: the pointer becomes the
  // XML element it was translated from ("line 12: <shape type="rectangle"> ('shape_3'): ..."),
  // keeping any key below it.
  std::string relocate(const std::string& message) const {
    const std::string head = path_ + ": /";
    if (message.compare(0, head.size(), head) != 0) return message;
    const size_t start = head.size() - 1, end = message.find_first_of(" :", start);
    const std::string pointer = message.substr(start, end == std::string::npos ? std::string::npos : end - start);
    const std::pair<std::string, std::string>* best = nullptr;
    for (const auto& o : origins_)
      if ((pointer == o.first || pointer.compare(0, o.first.size() + 1, o.first + "/") == 0) &&
          (!best || o.first.size() > best->first.size()))
        best = &o;
    if (!best) return message;
    const std::string below = pointer.substr(best->first.size());
    return path_ + ": " + best->second + (below.empty() ? "" : " (scene key '" + below.substr(1) + "')") +
           (end == std::string::npos ? "" : message.substr(end));
  }

  json translate() {
    pugi::xml_document doc;
    // pugixml parses iteratively, but the walk below recurses: bound the depth first.
    check_depth();
    const pugi::xml_parse_result r =
        doc.load_buffer(text_.data(), text_.size(), pugi::parse_default, pugi::encoding_utf8);
    if (!r)
      throw file_error(
          path_, "line " + std::to_string(line_at(size_t(r.offset))) + ": malformed XML (" + r.description() + ")");
    pugi::xml_node scene = doc.child("scene");
    if (!scene) throw file_error(path_, "no <scene> element");
    for (pugi::xml_node other = doc.first_child(); other; other = other.next_sibling())
      if (other.type() == pugi::node_element && other != scene)
        fail(other, "unexpected top-level <" + tag(other) + ">");
    const std::string version = scene.attribute("version").value();
    if (version.empty()) fail(scene, "<scene> needs a version attribute");
    if (version[0] != '2' && version[0] != '3') fail(scene, "scene version " + version + " is not 2.x or 3.x");
    // Defaults first (Mitsuba allows them anywhere at the top level), then ids.
    for (pugi::xml_node n : scene.children()) {
      if (n.type() != pugi::node_element) continue;
      if (tag(n) == "default") {
        const std::string name = n.attribute("name").value();
        if (name.empty() || !n.attribute("value")) fail(n, "<default> needs name and value");
        defaults_.emplace(name, n.attribute("value").value());
      }
      if (pugi::xml_attribute id = n.attribute("id")) {
        if (!ids_.emplace(id.value(), n).second) fail(n, "duplicate id '" + std::string(id.value()) + "'");
      }
    }
    root_ = {{"materials", json::object()},
             {"shapes", json::array()},
             {"cameras", json::array()},
             {"integrator", json::object()}};
    for (pugi::xml_node n : scene.children()) {
      if (n.type() != pugi::node_element) continue;
      const std::string t = tag(n);
      if (t == "default") continue;
      if (t == "integrator")
        integrator(n);
      else if (t == "sensor")
        sensor(n);
      else if (t == "shape")
        shape(n);
      else if (t == "bsdf")
        material_name(n);  // declared with an id: added when used, or now
      else if (t == "texture")
        continue;  // used through <ref>
      else if (t == "medium" || t == "volume" || t == "phase") {
        if (!n.attribute("id")) fail(n, "a top-level <" + t + "> needs an id (it is used through <ref>)");
        continue;  // used through <ref>
      } else if (t == "emitter")
        environment(n);
      else
        fail(n, "unsupported <" + t + "> at the top level");
    }
    if (root_["cameras"].empty()) throw file_error(path_, "the scene has no <sensor>");
    if (root_["shapes"].empty()) throw file_error(path_, "the scene has no <shape>");
    if (root_["integrator"].empty()) root_.erase("integrator");
    return root_;
  }

 private:
  std::string path_, text_;
  std::map<std::string, std::string> defaults_;
  std::map<std::string, pugi::xml_node> ids_;
  std::map<std::string, std::string> material_of_id_;
  std::map<std::string, std::string> medium_of_id_;
  std::set<std::string> warned_;
  std::vector<std::string> warnings_;                         // printed once the scene has loaded (see load_xml_scene)
  std::vector<std::pair<std::string, std::string>> origins_;  // JSON pointer → its XML element (relocate)
  json root_;
  int anonymous_ = 0;

  // ---- diagnostics -------------------------------------------------------------------------
  int line_at(size_t offset) const {
    int line = 1;
    for (size_t i = 0; i < offset && i < text_.size(); ++i) line += text_[i] == '\n';
    return line;
  }
  static std::string tag(const pugi::xml_node& n) { return n.name(); }
  std::string where(const pugi::xml_node& n) const {
    std::string s = "line " + std::to_string(line_at(size_t(n.offset_debug()))) + ": <" + tag(n);
    if (n.attribute("type")) s += " type=\"" + std::string(n.attribute("type").value()) + "\"";
    if (n.attribute("name")) s += " name=\"" + std::string(n.attribute("name").value()) + "\"";
    return s + ">";
  }
  [[noreturn]] void fail(const pugi::xml_node& n, const std::string& msg) const {
    throw file_error(path_, where(n) + ": " + msg);
  }
  void warn(const pugi::xml_node& n, const std::string& key, const std::string& msg) {
    if (!warned_.insert(key).second) return;
    warnings_.push_back("backlight: " + path_ + ": warning: " + where(n) + ": " + msg);
  }

  void check_depth() const {
    int depth = 0;
    bool in_tag = false;
    for (size_t i = 0; i < text_.size(); ++i) {
      const char c = text_[i];
      if (c == '<' && i + 1 < text_.size() && text_[i + 1] != '/' && text_[i + 1] != '!' && text_[i + 1] != '?') {
        in_tag = true;
        ++depth;
        if (depth > kXmlDepth)
          throw file_error(path_, "line " + std::to_string(line_at(i)) + ": elements nested deeper than " +
                                      std::to_string(kXmlDepth));
      } else if (c == '<' && i + 1 < text_.size() && text_[i + 1] == '/') {
        --depth;
      } else if (c == '/' && in_tag && i + 1 < text_.size() && text_[i + 1] == '>') {
        --depth;
      } else if (c == '>') {
        in_tag = false;
      }
    }
  }

  // ---- values --------------------------------------------------------------------------------
  // An attribute with $name substituted from <default> values.
  std::string attr(const pugi::xml_node& n, const char* name) const {
    std::string v = n.attribute(name).value();
    for (size_t at = v.find('$'); at != std::string::npos; at = v.find('$', at)) {
      size_t end = at + 1;
      while (end < v.size() && (std::isalnum(static_cast<unsigned char>(v[end])) || v[end] == '_')) ++end;
      const std::string key = v.substr(at + 1, end - at - 1);
      auto it = defaults_.find(key);
      if (key.empty() || it == defaults_.end())
        fail(n, "unknown parameter $" + key + " (no <default name=\"" + key + "\">)");
      v.replace(at, end - at, it->second);
      at += it->second.size();
    }
    return v;
  }
  double number(const pugi::xml_node& n, const std::string& text) const {
    char* end = nullptr;
    const double v = std::strtod(text.c_str(), &end);
    if (text.empty() || end == text.c_str() || *end != '\0' || !std::isfinite(v))
      fail(n, "'" + text + "' is not a finite number");
    return v;
  }
  std::vector<double> numbers(const pugi::xml_node& n, const std::string& text) const {
    std::string t = text;
    for (char& c : t)
      if (c == ',') c = ' ';
    std::istringstream s(t);
    std::vector<double> out;
    std::string word;
    while (s >> word) out.push_back(number(n, word));
    return out;
  }
  double value(const pugi::xml_node& n) const { return number(n, attr(n, "value")); }
  // <rgb value="r, g, b"> (or one number), <spectrum value="v"> (grey), <float value="v">.
  json color(const pugi::xml_node& n) {
    const std::string t = tag(n);
    if (t == "float") return value(n);
    if (t == "rgb" || t == "spectrum") {
      const std::string text = attr(n, "value");
      if (t == "spectrum" && text.find(':') != std::string::npos)
        fail(n, "wavelength-sampled spectra are not supported (RGB only)");
      const std::vector<double> v = numbers(n, text);
      if (v.size() == 1) return json::array({v[0], v[0], v[0]});
      if (v.size() == 3) return json::array({v[0], v[1], v[2]});
      fail(n, "expected one or three values");
    }
    fail(n, "expected <rgb>, <spectrum> or <float>");
  }
  Vec3f vec3(const pugi::xml_node& n, const char* name) const {
    const std::vector<double> v = numbers(n, attr(n, name));
    if (v.size() != 3) fail(n, std::string("'") + name + "' needs three values");
    return {float(v[0]), float(v[1]), float(v[2])};
  }
  // x/y/z attributes (default `fallback`) or value="x, y, z".
  Vec3f xyz(const pugi::xml_node& n, float fallback) const {
    if (n.attribute("value")) {
      const std::vector<double> v = numbers(n, attr(n, "value"));
      if (v.size() == 1) return Vec3f(float(v[0]));
      if (v.size() != 3) fail(n, "value needs one or three numbers");
      return {float(v[0]), float(v[1]), float(v[2])};
    }
    auto get = [&](const char* a) { return n.attribute(a) ? float(number(n, attr(n, a))) : fallback; };
    return {get("x"), get("y"), get("z")};
  }

  // <transform>: children applied in document order (each left-multiplies what came before).
  Transform transform(const pugi::xml_node& n) const {
    Transform t;
    for (pugi::xml_node c : n.children()) {
      if (c.type() != pugi::node_element) continue;
      const std::string k = tag(c);
      Transform step;
      if (k == "translate") {
        step = Transform::translate(xyz(c, 0.f));
      } else if (k == "scale") {
        step = Transform::scale(xyz(c, 1.f));
      } else if (k == "rotate") {
        const Vec3f axis = xyz(c, 0.f);
        if (!(length(axis) > 0.f)) fail(c, "zero rotation axis");
        step = Transform::rotate(axis, float(number(c, attr(c, "angle"))));
      } else if (k == "matrix") {
        const std::vector<double> v = numbers(c, attr(c, "value"));
        if (v.size() != 16 && v.size() != 9) fail(c, "a matrix needs 16 (or 9) values");
        const int d = v.size() == 16 ? 4 : 3;
        for (int i = 0; i < d; ++i)
          for (int j = 0; j < d; ++j) step.m[i][j] = float(v[size_t(i * d + j)]);
      } else if (k == "lookat") {
        const Vec3f o = vec3(c, "origin"), target = vec3(c, "target");
        Vec3f up = c.attribute("up") ? vec3(c, "up") : Vec3f{0, 1, 0};
        const Vec3f dir = normalize(target - o);
        Vec3f left = cross(up, dir);
        if (!(length(dir) > 0.f) || !(length(left) > 0.f))
          fail(c, "degenerate lookat (origin = target or up ∥ direction)");
        left = normalize(left);
        const Vec3f new_up = cross(dir, left);
        const Vec3f cols[4] = {left, new_up, dir, o};
        for (int j = 0; j < 4; ++j) step.m[0][j] = cols[j].x, step.m[1][j] = cols[j].y, step.m[2][j] = cols[j].z;
      } else {
        fail(c, "unsupported transform element");
      }
      t = step * t;
    }
    return t;
  }
  static json matrix_json(const Transform& t) {
    json rows = json::array();
    for (int i = 0; i < 4; ++i) rows.push_back({t.m[i][0], t.m[i][1], t.m[i][2], t.m[i][3]});
    return rows;
  }

  // ---- plugins -------------------------------------------------------------------------------
  // The property elements of a plugin by name; objects (bsdf, texture, emitter, ref, …) apart.
  struct Props {
    std::map<std::string, pugi::xml_node> values;
    std::vector<pugi::xml_node> objects;
    std::set<std::string> used;
  };
  Props props(const pugi::xml_node& n) const {
    static const std::set<std::string> kValueTags = {"float",    "integer", "boolean", "string",   "rgb",
                                                     "spectrum", "point",   "vector",  "transform"};
    Props p;
    for (pugi::xml_node c : n.children()) {
      if (c.type() != pugi::node_element) continue;
      if (kValueTags.count(tag(c))) {
        const std::string name = c.attribute("name").value();
        if (name.empty()) fail(c, "property without a name");
        if (!p.values.emplace(name, c).second) fail(c, "property '" + name + "' given twice");
      } else {
        p.objects.push_back(c);
      }
    }
    return p;
  }
  bool has(Props& p, const std::string& name) const { return p.values.count(name) > 0; }
  pugi::xml_node get(Props& p, const std::string& name) {
    p.used.insert(name);
    return p.values.at(name);
  }
  double get_number(Props& p, const std::string& name, double fallback) {
    return has(p, name) ? value(get(p, name)) : fallback;
  }
  // An integer property within [lo, hi], checked before any conversion (huge values are errors).
  long get_integer(Props& p, const std::string& name, long fallback, long lo, long hi) {
    if (!has(p, name)) return fallback;
    const pugi::xml_node n = get(p, name);
    const double v = value(n);
    if (v != std::floor(v) || v < double(lo) || v > double(hi))
      fail(n, "expected an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return long(v);
  }
  std::string get_string(Props& p, const std::string& name, const std::string& fallback) {
    return has(p, name) ? attr(get(p, name), "value") : fallback;
  }
  bool get_bool(Props& p, const std::string& name, bool fallback) {
    if (!has(p, name)) return fallback;
    const pugi::xml_node n = get(p, name);
    const std::string v = attr(n, "value");
    if (v == "true") return true;
    if (v == "false") return false;
    fail(n, "expected true or false");
  }
  // What is left over: harmless names warn once, everything else is an error.
  void finish(const pugi::xml_node& n, Props& p, const std::set<std::string>& harmless = {}) {
    for (const auto& [name, node] : p.values) {
      if (p.used.count(name)) continue;
      if (harmless.count(name)) {
        warn(node, tag(n) + "." + name, "ignored (does not change the rendered image here)");
        continue;
      }
      fail(node, "unsupported property of " + where(n));
    }
  }
  std::string plugin_type(const pugi::xml_node& n) const {
    const std::string t = attr(n, "type");
    if (t.empty()) fail(n, "missing type attribute");
    return t;
  }
  pugi::xml_node resolve(const pugi::xml_node& n) const {
    if (tag(n) != "ref") return n;
    const std::string id = attr(n, "id");
    auto it = ids_.find(id);
    if (it == ids_.end()) fail(n, "no element with id '" + id + "'");
    return it->second;
  }

  // A texturable value: <rgb>/<spectrum>/<float> property `name`, or a <texture name=…> / <ref name=…>.
  json texturable(const pugi::xml_node& plugin, Props& p, const std::string& name, json fallback) {
    if (has(p, name)) return color(get(p, name));
    for (const pugi::xml_node& o : p.objects) {
      if (std::string(o.attribute("name").value()) != name) continue;
      const pugi::xml_node t = resolve(o);
      if (tag(t) != "texture") fail(o, "expected a texture");
      return texture(t);
    }
    (void)plugin;
    return fallback;
  }
  json texture(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    if (type != "bitmap") fail(n, "unsupported texture type (bitmap only)");
    Props p = props(n);
    if (!has(p, "filename")) fail(n, "bitmap needs a filename");
    json t = {{"type", "bitmap"}, {"file", get_string(p, "filename", "")}};
    const std::string wrap = get_string(p, "wrap_mode", "repeat");
    if (wrap != "repeat" && wrap != "clamp" && wrap != "mirror")
      fail(n, "wrap_mode '" + wrap + "' is not supported (repeat, mirror or clamp)");
    t["wrap"] = wrap;
    if (get_bool(p, "raw", false)) t["color_space"] = "linear";
    const std::string filter = get_string(p, "filter_type", "bilinear");
    if (filter != "bilinear") warn(n, "filter_type", "filter_type '" + filter + "' is read as bilinear");
    if (has(p, "to_uv")) fail(get(p, "to_uv"), "texture to_uv transforms are not supported");
    finish(n, p, {"format"});
    return t;
  }

  std::string fresh(const std::string& base) { return base + "_" + std::to_string(anonymous_++); }
  static std::string clean(std::string id) {
    for (char& c : id)
      if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-')) c = '_';
    return id.empty() ? "unnamed" : id;
  }

  // A <bsdf> (with an id: translated once) → the name of its JSON material.
  std::string material_name(const pugi::xml_node& n) {
    const std::string id = n.attribute("id").value();
    if (!id.empty())
      if (auto it = material_of_id_.find(id); it != material_of_id_.end()) return it->second;
    std::string name = id.empty() ? fresh("bsdf") : clean(id);
    while (root_["materials"].contains(name)) name = fresh(name);
    json m = bsdf(n, false);
    origins_.push_back({"/materials/" + name, where(n)});
    root_["materials"][name] = m;
    if (!id.empty()) material_of_id_[id] = name;
    return name;
  }

  json bsdf(const pugi::xml_node& n, bool two_sided) {
    const std::string type = plugin_type(n);
    Props p = props(n);
    json m;
    if (type == "twosided") {
      // (Also what ends a cycle of references: twosided → … → itself.)
      if (two_sided) fail(n, "a twosided bsdf inside a twosided bsdf");
      pugi::xml_node inner;
      for (const pugi::xml_node& o : p.objects)
        if (tag(resolve(o)) == "bsdf") {
          if (inner) fail(o, "twosided with two different bsdfs is not supported");
          inner = resolve(o);
        }
      if (!inner) fail(n, "twosided needs a nested bsdf");
      finish(n, p);
      return bsdf(inner, true);
    }
    auto check_objects = [&](const std::set<std::string>& texture_names) {
      for (const pugi::xml_node& o : p.objects)
        if (!texture_names.count(o.attribute("name").value())) fail(o, "unexpected nested element in " + where(n));
    };
    if (type == "diffuse") {
      m = {{"type", "diffuse"}, {"albedo", texturable(n, p, "reflectance", 0.5)}};
      check_objects({"reflectance"});
    } else if (type == "roughconductor" || type == "conductor") {
      double alpha = 0.001;
      if (type == "roughconductor") {
        alpha = get_number(p, "alpha", 0.1);
        if (has(p, "alpha_u") || has(p, "alpha_v")) {
          const double u = get_number(p, "alpha_u", alpha), v = get_number(p, "alpha_v", alpha);
          if (u != v) fail(n, "anisotropic roughness (alpha_u ≠ alpha_v) is not supported");
          alpha = u;
        }
        const std::string dist = get_string(p, "distribution", "beckmann");
        if (dist != "ggx") warn(n, "distribution", "microfacet distribution '" + dist + "' is rendered as GGX");
      } else {
        warn(n, "conductor", "a smooth conductor is rendered as GGX with alpha 0.001");
      }
      // Fresnel: the exact conductor term becomes Schlick's with the same normal-incidence
      // reflectance F0 = ((η − 1)² + k²) / ((η + 1)² + k²) per channel.
      json f0 = json::array({1.0, 1.0, 1.0});
      const std::string material = get_string(p, "material", "none");
      if (has(p, "eta") || has(p, "k")) {
        if (!has(p, "eta") || !has(p, "k")) fail(n, "give both eta and k");
        const json eta = color(get(p, "eta")), k = color(get(p, "k"));
        for (int c = 0; c < 3; ++c) {
          const double e = eta[size_t(c)].get<double>(), kk = k[size_t(c)].get<double>();
          f0[size_t(c)] = ((e - 1) * (e - 1) + kk * kk) / ((e + 1) * (e + 1) + kk * kk);
        }
        warn(n, "schlick", "conductor Fresnel approximated by Schlick's with F0 from eta and k");
      } else if (material != "none") {
        fail(n, "named conductor material '" + material + "' is not supported: give eta and k");
      }
      json spec = texturable(n, p, "specular_reflectance", 1.0);
      if (spec.is_object()) fail(n, "a textured specular_reflectance is not supported");
      if (spec.is_number()) spec = json::array({spec, spec, spec});
      for (int c = 0; c < 3; ++c) f0[size_t(c)] = f0[size_t(c)].get<double>() * spec[size_t(c)].get<double>();
      m = {{"type", "roughconductor"}, {"specular", f0}, {"roughness", alpha}};
      check_objects({"specular_reflectance"});
    } else if (type == "roughplastic" || type == "plastic") {
      double alpha = 0.001;
      if (type == "roughplastic") {
        alpha = get_number(p, "alpha", 0.1);
        const std::string dist = get_string(p, "distribution", "beckmann");
        if (dist != "ggx") warn(n, "distribution", "microfacet distribution '" + dist + "' is rendered as GGX");
      } else {
        warn(n, "plastic", "a smooth plastic is rendered as GGX with alpha 0.001");
      }
      const double int_ior = get_number(p, "int_ior", 1.49), ext_ior = get_number(p, "ext_ior", 1.000277);
      if (!(int_ior > 0 && ext_ior > 0)) fail(n, "int_ior and ext_ior must be positive");
      if (has(p, "specular_reflectance") && color(get(p, "specular_reflectance")) != json::array({1.0, 1.0, 1.0}))
        fail(n, "specular_reflectance other than 1 is not supported");
      if (has(p, "nonlinear")) warn(get(p, "nonlinear"), "nonlinear", "nonlinear is ignored");
      m = {{"type", "roughplastic"},
           {"albedo", texturable(n, p, "diffuse_reflectance", 0.5)},
           {"roughness", alpha},
           {"ior", int_ior / ext_ior}};
      check_objects({"diffuse_reflectance"});
    } else if (type == "null") {
      m = {{"type", "null"}};
      check_objects({});
    } else {
      fail(n, "unsupported bsdf type");
    }
    if (m["type"] != "null") m["two_sided"] = two_sided;
    finish(n, p);
    return m;
  }

  void integrator(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    if (type != "path" && type != "prb" && type != "volpath" && type != "prbvolpath")
      fail(n, "unsupported integrator (path, prb, volpath or prbvolpath)");
    Props p = props(n);
    json& it = root_["integrator"];
    origins_.push_back({"/integrator", where(n)});
    if (has(p, "max_depth")) it["max_depth"] = get_integer(p, "max_depth", 6, -1, 1 << 20);
    if (has(p, "rr_depth")) it["rr_depth"] = get_integer(p, "rr_depth", 5, 0, 1 << 20);
    if (has(p, "hide_emitters")) it["hide_emitters"] = get_bool(p, "hide_emitters", false);
    for (const pugi::xml_node& o : p.objects) fail(o, "nested elements in an integrator are not supported");
    finish(n, p);
  }

  void sensor(const pugi::xml_node& n) {
    if (plugin_type(n) != "perspective") fail(n, "unsupported sensor (perspective only)");
    Props p = props(n);
    json cam;
    cam["name"] =
        n.attribute("id") ? clean(n.attribute("id").value()) : "sensor" + std::to_string(root_["cameras"].size());
    if (has(p, "focal_length")) fail(get(p, "focal_length"), "focal_length is not supported: give fov");
    cam["fov"] = get_number(p, "fov", 0.0);
    if (!has(p, "fov")) fail(n, "a perspective sensor needs fov");
    cam["fov_axis"] = get_string(p, "fov_axis", "x");
    cam["near_clip"] = get_number(p, "near_clip", 0.01);
    const Transform t = has(p, "to_world") ? transform(get(p, "to_world")) : Transform();
    // Mitsuba's camera looks along +z of its frame with +y up (+x to the left of the image).
    const Vec3f o = t.point({0, 0, 0}), forward = t.vector({0, 0, 1}), up = t.vector({0, 1, 0});
    if (!(length(forward) > 0.f) || !(length(up) > 0.f)) fail(n, "degenerate to_world");
    const Vec3f target = o + normalize(forward);
    cam["origin"] = {o.x, o.y, o.z};
    cam["target"] = {target.x, target.y, target.z};
    cam["up"] = {up.x, up.y, up.z};
    int width = 768, height = 576;
    for (const pugi::xml_node& o2 : p.objects) {
      const pugi::xml_node c = resolve(o2);
      if (tag(c) == "film") {
        if (plugin_type(c) != "hdrfilm") fail(c, "unsupported film (hdrfilm only)");
        Props f = props(c);
        width = int(get_integer(f, "width", 768, 1, long(limits::kImageSide)));
        height = int(get_integer(f, "height", 576, 1, long(limits::kImageSide)));
        if (width < 1 || height < 1) fail(c, "film size must be positive");
        limits::check_image_size(path_ + ": " + where(c), uint64_t(width), uint64_t(height));
        for (const pugi::xml_node& r : f.objects) {
          if (tag(r) != "rfilter") fail(r, "unexpected element in a film");
          if (plugin_type(r) != "box")
            warn(r, "rfilter", "reconstruction filter '" + plugin_type(r) + "' is rendered as a box filter");
        }
        if (has(f, "crop_width") || has(f, "crop_height") || has(f, "crop_offset_x") || has(f, "crop_offset_y"))
          fail(c, "crop windows are not supported");
        finish(c, f, {"pixel_format", "component_format", "file_format", "banner", "sample_border", "rgb_gamma"});
        if (f.objects.empty())
          warn(c, "rfilter", "no rfilter: Mitsuba's default (gaussian) is rendered as a box filter");
      } else if (tag(c) == "medium") {
        if (std::string(o2.attribute("name").value()) != "medium") fail(o2, "a sensor's medium is named medium");
        if (cam.contains("medium")) fail(o2, "a second sensor medium");
        cam["medium"] = medium_name(c);
      } else if (tag(c) == "sampler") {
        Props s = props(c);
        const std::string st = plugin_type(c);
        if (st != "independent" && st != "stratified" && st != "multijitter" && st != "orthogonal" && st != "ldsampler")
          fail(c, "unknown sampler type");
        if (st != "independent") warn(c, "sampler", "sampler '" + st + "' is rendered with independent samples");
        if (has(s, "sample_count"))
          root_["integrator"]["spp"] = get_integer(s, "sample_count", 4, 1, long(limits::kSpp));
        if (has(s, "seed")) root_["integrator"]["seed"] = get_integer(s, "seed", 0, 0, 4294967295L);
        finish(c, s, {"jitter", "scramble_type"});
      } else {
        fail(c, "unexpected element in a sensor");
      }
    }
    cam["resolution"] = {width, height};
    finish(n, p, {"far_clip", "shutter_open", "shutter_close", "srf"});
    origins_.push_back({"/cameras/" + std::to_string(root_["cameras"].size()), where(n)});
    root_["cameras"].push_back(cam);
  }

  void shape(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    Props p = props(n);
    json s;
    s["name"] = n.attribute("id") ? clean(n.attribute("id").value()) : fresh("shape");
    for (const auto& other : root_["shapes"])
      if (other["name"] == s["name"]) s["name"] = fresh(s["name"].get<std::string>());
    Transform to_world = has(p, "to_world") ? transform(get(p, "to_world")) : Transform();
    if (type == "obj" || type == "ply") {
      if (!has(p, "filename")) fail(n, type + " needs a filename");
      s["type"] = type;
      s["file"] = get_string(p, "filename", "");
      if (type == "obj") s["flip_tex_coords"] = get_bool(p, "flip_tex_coords", true);
      if (get_bool(p, "face_normals", false)) s["face_normals"] = true;
    } else if (type == "rectangle") {
      // Mitsuba's rectangle: [−1, 1]² at z = 0, normal +z, uv (0, 0) at (−1, −1).
      s["type"] = "mesh";
      s["positions"] = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
      s["normals"] = {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}, {0, 0, 1}};
      s["uvs"] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      s["indices"] = {{0, 1, 2}, {0, 2, 3}};
    } else if (type == "cube") {
      s["type"] = "cube";
    } else if (type == "sphere") {
      s["type"] = "sphere";
      const double radius = get_number(p, "radius", 1.0);
      if (!(radius > 0)) fail(n, "radius must be positive");
      Vec3f center{0, 0, 0};
      if (has(p, "center")) center = xyz(get(p, "center"), 0.f);
      to_world = to_world * Transform::translate(center) * Transform::scale(Vec3f(float(radius)));
      warn(n, "sphere", "spheres are tessellated (64 × 32 segments)");
    } else {
      fail(n, "unsupported shape type");
    }
    s["transform"] = {{"matrix", matrix_json(to_world)}};
    if (get_bool(p, "flip_normals", false)) s["flip_normals"] = true;
    std::string material;
    for (const pugi::xml_node& o : p.objects) {
      const pugi::xml_node c = resolve(o);
      const std::string t = tag(c);
      if (t == "bsdf") {
        if (!material.empty()) fail(o, "a shape with two bsdfs");
        material = material_name(c);
      } else if (t == "emitter") {
        if (plugin_type(c) != "area") fail(c, "only area emitters can be attached to shapes");
        Props e = props(c);
        json radiance = texturable(c, e, "radiance", 1.0);
        if (radiance.is_number()) radiance = json::array({radiance, radiance, radiance});
        for (const pugi::xml_node& x : e.objects)
          if (std::string(x.attribute("name").value()) != "radiance") fail(x, "unexpected element in an emitter");
        finish(c, e);
        s["emitter"] = {{"radiance", radiance}};
      } else if (t == "medium") {
        const std::string side = o.attribute("name").value();
        if (side != "interior" && side != "exterior") fail(o, "a shape's medium is named interior or exterior");
        if (s.contains(side)) fail(o, "a second " + side + " medium");
        s[side] = medium_name(c);
      } else {
        fail(c, "unexpected element in a shape");
      }
    }
    if (material.empty()) {
      // Mitsuba's default: a diffuse BSDF of reflectance 0.5.
      if (!root_["materials"].contains("default_bsdf"))
        root_["materials"]["default_bsdf"] = {{"type", "diffuse"}, {"albedo", 0.5}, {"two_sided", false}};
      material = "default_bsdf";
    }
    s["material"] = material;
    finish(n, p);
    origins_.push_back({"/shapes/" + std::to_string(root_["shapes"].size()), where(n)});
    root_["shapes"].push_back(s);
  }

  // A <medium> (with an id: translated once) → the name of its JSON medium.
  std::string medium_name(const pugi::xml_node& n) {
    const std::string id = n.attribute("id").value();
    if (!id.empty())
      if (auto it = medium_of_id_.find(id); it != medium_of_id_.end()) return it->second;
    if (!root_.contains("media")) root_["media"] = json::object();
    // JSON medium names may not contain '.' (parameter names are <medium>.density, …).
    std::string name = id.empty() ? fresh("medium") : clean(id);
    for (char& c : name)
      if (c == '.') c = '_';
    while (root_["media"].contains(name)) name = fresh(name);
    root_["media"][name] = medium(n);
    origins_.push_back({"/media/" + name, where(n)});
    if (!id.empty()) medium_of_id_[id] = name;
    return name;
  }

  // A constant medium coefficient: <float>, <rgb>/<spectrum> or a constvolume's value, as a number
  // (grey) or [r, g, b].
  json constant(const pugi::xml_node& n) {
    const json c = color(n);
    if (c.is_array() && c[0] == c[1] && c[1] == c[2]) return c[0];
    return c;
  }

  // A <volume>: its constant value, or (gridvolume) {"type": "vol", "file": F} with the world box
  // its to_world gives the unit cube (`box`: {min, max}, or null for the box stored in the file).
  struct VolumeValue {
    json value;  // a number, [r, g, b] or a grid object
    bool grid = false;
    json box;
  };
  VolumeValue volume(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    Props p = props(n);
    for (const pugi::xml_node& o : p.objects) fail(o, "unexpected element in a volume");
    VolumeValue v;
    if (type == "constvolume") {
      v.value = has(p, "value") ? constant(get(p, "value")) : json(1.0);
      finish(n, p);
      return v;
    }
    if (type != "gridvolume") fail(n, "unsupported volume type (gridvolume or constvolume)");
    if (!has(p, "filename")) fail(n, "gridvolume needs a filename");
    v.grid = true;
    v.value = {{"type", "vol"}, {"file", get_string(p, "filename", "")}};
    const std::string filter = get_string(p, "filter_type", "trilinear");
    if (filter != "trilinear") fail(n, "filter_type '" + filter + "' is not supported (trilinear only)");
    const std::string wrap = get_string(p, "wrap_mode", "clamp");
    if (wrap != "clamp") fail(n, "wrap_mode '" + wrap + "' is not supported (clamp only)");
    const bool grid_box = get_bool(p, "use_grid_bbox", false);
    Transform t;
    if (has(p, "to_world")) {
      const pugi::xml_node tn = get(p, "to_world");
      t = transform(tn);
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j)
          if (i != j && j != 3 && t.m[i][j] != 0.f)
            fail(tn, "a gridvolume's to_world must be a scale and a translation (no rotation or shear)");
      if (t.m[3][3] != 1.f || !(t.m[0][0] > 0.f && t.m[1][1] > 0.f && t.m[2][2] > 0.f))
        fail(tn, "a gridvolume's to_world must scale by positive factors");
      if (grid_box) fail(tn, "use_grid_bbox together with a to_world is not supported");
    }
    if (grid_box) {
      v.box = nullptr;  // the box stored in the .vol file
    } else {
      // Mitsuba ignores the box stored in the file: the unit cube, through to_world.
      const Vec3f lo = t.point({0, 0, 0}), hi = t.point({1, 1, 1});
      v.box = {{"min", {lo.x, lo.y, lo.z}}, {"max", {hi.x, hi.y, hi.z}}};
    }
    // `raw` only changes spectral variants' RGB upsampling; `accel` and `max_value` only the
    // majorant (a sampling choice here: block maxima).
    finish(n, p, {"raw", "accel", "max_value"});
    return v;
  }

  json phase(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    Props p = props(n);
    for (const pugi::xml_node& o : p.objects) fail(o, "unexpected element in a phase function");
    json ph;
    if (type == "isotropic") {
      ph = {{"type", "isotropic"}};
    } else if (type == "hg") {
      ph = {{"type", "hg"}, {"g", get_number(p, "g", 0.8)}};
    } else {
      fail(n, "unsupported phase function (isotropic or hg)");
    }
    finish(n, p);
    return ph;
  }

  // Mitsuba's homogeneous and heterogeneous media: σ_t = scale · sigma_t (grey: backlight's
  // extinction is the same in R, G and B), albedo (default 0.75), phase (default isotropic).
  json medium(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    if (type != "homogeneous" && type != "heterogeneous")
      fail(n, "unsupported medium type (homogeneous or heterogeneous)");
    Props p = props(n);
    VolumeValue sigma{json(1.0)}, albedo{json(0.75)};
    pugi::xml_node sigma_at = n, albedo_at = n;
    bool sigma_given = false, albedo_given = false;
    json ph = {{"type", "isotropic"}};
    bool phase_given = false;
    auto take = [&](const std::string& name, const pugi::xml_node& at, VolumeValue v) {
      if (name == "sigma_t") {
        if (sigma_given) fail(at, "sigma_t given twice");
        sigma = std::move(v), sigma_at = at, sigma_given = true;
      } else if (name == "albedo") {
        if (albedo_given) fail(at, "albedo given twice");
        albedo = std::move(v), albedo_at = at, albedo_given = true;
      } else {
        fail(at, "unexpected volume '" + name + "' in a medium (sigma_t or albedo)");
      }
    };
    for (const char* name : {"sigma_t", "albedo"})
      if (has(p, name)) take(name, get(p, name), {constant(get(p, name))});
    for (const pugi::xml_node& o : p.objects) {
      const pugi::xml_node c = resolve(o);
      if (tag(c) == "phase") {
        if (phase_given) fail(o, "a second phase function");
        ph = phase(c), phase_given = true;
      } else if (tag(c) == "volume") {
        take(o.attribute("name").value(), o, volume(c));
      } else {
        fail(o, "unexpected element in a medium");
      }
    }
    if (sigma.value.is_array()) fail(sigma_at, "sigma_t must be the same in R, G and B (grey extinction)");
    if (has(p, "sample_emitters") && !get_bool(p, "sample_emitters", true))
      fail(get(p, "sample_emitters"), "sample_emitters false is not supported (light is always sampled)");
    json m;
    if (sigma.grid) {
      if (type == "homogeneous") fail(sigma_at, "a homogeneous medium takes a constant sigma_t");
      m = {{"type", "grid"}, {"density", sigma.value}};
      if (!sigma.box.is_null()) m["bbox"] = sigma.box;
      if (albedo.grid && albedo.box != sigma.box)
        fail(albedo_at, "the albedo grid must fill the same box as the sigma_t grid");
    } else {
      // A constant sigma_t fills the shapes that name the medium: backlight's homogeneous medium.
      if (albedo.grid) fail(albedo_at, "an albedo grid needs a sigma_t grid");
      m = {{"type", "homogeneous"}, {"density", sigma.value}};
    }
    m["albedo"] = albedo.value;
    m["scale"] = get_number(p, "scale", 1.0);
    m["phase"] = ph;
    finish(n, p, {"has_spectral_extinction"});
    return m;
  }

  void environment(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    if (type != "constant" && type != "envmap") fail(n, "unsupported emitter at the top level (constant or envmap)");
    if (root_.contains("environment")) fail(n, "a second environment emitter");
    origins_.push_back({"/environment", where(n)});
    Props p = props(n);
    if (type == "envmap") {
      // Mitsuba's lookup (bilinear, u = 0 at −z) is the environment's "mitsuba" convention; its
      // bitmap is radiance, 8-bit files sRGB-decoded.
      if (!has(p, "filename")) fail(n, "envmap needs a filename");
      json env = {{"type", "envmap"},
                  {"file", get_string(p, "filename", "")},
                  {"convention", "mitsuba"},
                  {"color_space", "auto"},
                  {"scale", get_number(p, "scale", 1.0)}};
      if (has(p, "to_world")) {
        const pugi::xml_node t = get(p, "to_world");
        const Transform m = transform(t);
        for (int i = 0; i < 4; ++i)
          for (int j = 0; j < 4; ++j)
            if (std::abs(m.m[i][j] - (i == j ? 1.f : 0.f)) > 1e-6f)
              fail(t, "envmap to_world must be the identity (rotated environments are not supported)");
      }
      for (const pugi::xml_node& x : p.objects) fail(x, "unexpected element in an emitter");
      finish(n, p, {"mis_compensation"});
      root_["environment"] = env;
      return;
    }
    json radiance = texturable(n, p, "radiance", 1.0);
    if (radiance.is_object()) fail(n, "a textured constant emitter is not supported");
    if (radiance.is_number()) radiance = json::array({radiance, radiance, radiance});
    for (const pugi::xml_node& x : p.objects) fail(x, "unexpected element in an emitter");
    finish(n, p);
    root_["environment"] = {{"type", "constant"}, {"radiance", radiance}};
  }
};

}  // namespace

std::unique_ptr<Scene> load_xml_scene(const std::string& path) {
  XmlScene xml(path, read_input_file(path));
  const json translated = xml.translate();
  std::unique_ptr<Scene> scene;
  try {
    scene = build_json_scene(translated, path);
  } catch (const InputError& e) {
    throw InputError(xml.relocate(e.what()));
  }
  // A scene that fails to load gets its one error line only; one that loads, its warnings.
  for (const std::string& w : xml.warnings()) std::fprintf(stderr, "%s\n", w.c_str());
  return scene;
}

}  // namespace bl
