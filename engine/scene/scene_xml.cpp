// Mitsuba 3 XML scenes (pugixml), translated into backlight's JSON scene and built by its loader.
//
// Supported: <default>/$name substitution, id/<ref> (ids are global, nested ones too), shapes
// obj, ply (without normals: Mitsuba's angle-weighted vertex normals), rectangle, cube (Mitsuba's
// mesh and uvs), sphere (tessellated, Mitsuba's uvs), to_world (matrix, lookat, translate,
// rotate, scale in document order), bsdfs diffuse, roughconductor (eta/k → Schlick), conductor,
// roughplastic, plastic, twosided, null, textures bitmap, emitters area, constant and envmap
// (identity to_world), sensor perspective (rigid to_world) with film hdrfilm, rfilter and a
// sampler, integrators path/prb/volpath/prbvolpath with Mitsuba's defaults, media homogeneous and
// heterogeneous (grey σ_t, a gridvolume .vol with a scale-and-translate to_world, constvolume
// values, phase isotropic or hg) as shape interiors/exteriors and sensor media under volpath or
// prbvolpath. Anything else is an error naming the plugin and its line; attributes that do not
// change the image (file formats, a far_clip nothing reaches, …) give one warning.
#include <pugixml.hpp>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <system_error>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/json_node.h"
#include "engine/scene/mesh_io.h"
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

  // Mitsuba ends each camera ray at depth far_clip along the view axis (default 1e4; its secondary
  // rays are not clipped); backlight's camera has no far plane. Checked on the built scene, where
  // the meshes are in world space: a far_clip that nothing reaches cannot change the image. A
  // homogeneous medium that may extend beyond all shapes (a camera's, or a shape's exterior) is
  // left at far_clip by Mitsuba's camera rays, which then escape to the environment: that weighs
  // at most exp(−σ_t · far_clip), nothing in float once σ_t · far_clip ≥ 100.
  void check_far_clips(const Scene& scene) {
    for (size_t i = 0; i < far_clips_.size() && i < scene.cameras.size(); ++i) {
      const FarClip& clip = far_clips_[i];
      const Camera& cam = scene.cameras[i];
      const Vec3d origin(cam.origin), forward = normalize(Vec3d(cam.target) - origin);
      const std::string head = clip.given_at.empty()
                                   ? clip.sensor + ": Mitsuba's default far_clip " + number_text(clip.distance)
                                   : clip.given_at + ": far_clip " + number_text(clip.distance);
      const std::string remedy = " (camera rays are not clipped here: give a far_clip beyond the scene)";
      auto check_depth_of = [&](const Vec3f& p, const std::string& what) {
        const double depth = dot(Vec3d(p) - origin, forward);
        if (depth > clip.distance)
          throw file_error(path_, head + " clips " + what + " (at depth " + number_text(depth) + ")" + remedy);
      };
      for (const Mesh& m : scene.meshes)
        for (size_t v = 0; v < m.vertex_count(); ++v) check_depth_of(m.positions[v], "shape '" + m.name + "'");
      std::set<int> open_media;  // media that may reach beyond every shape
      if (cam.medium >= 0) open_media.insert(cam.medium);
      for (const Mesh& m : scene.meshes)
        if (m.exterior >= 0) open_media.insert(m.exterior);
      for (size_t k = 0; k < scene.media.size(); ++k) {
        const Medium& m = scene.media[k];
        if (m.grid) {
          for (int c = 0; c < 8; ++c)
            check_depth_of({c & 1 ? m.bbox_max.x : m.bbox_min.x, c & 2 ? m.bbox_max.y : m.bbox_min.y,
                            c & 4 ? m.bbox_max.z : m.bbox_min.z},
                           "the grid of medium '" + m.name + "'");
        } else if (open_media.count(int(k))) {
          const double sigma = double(scene.params[m.density].value[0]) * scene.params[m.scale].value[0];
          if (sigma * clip.distance < 100)
            throw file_error(path_, head + " ends camera rays inside medium '" + m.name +
                                        "', which may extend beyond it (σ_t · far_clip = " +
                                        number_text(sigma * clip.distance) + " < 100)" + remedy);
        }
      }
      if (!clip.given_at.empty())
        warnings_.push_back("backlight: " + path_ + ": warning: " + clip.given_at +
                            ": ignored (nothing in the scene lies beyond it)");
    }
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
    }
    collect_ids(scene);
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
    json& it = root_["integrator"];
    if (!integrator_) {
      // Mitsuba renders nothing without an integrator; backlight renders <integrator type="path"/>.
      warn(scene, "integrator", "no <integrator>: rendered as <integrator type=\"path\"/> (max_depth -1, rr_depth 5)");
      it["max_depth"] = -1;
      it["rr_depth"] = 5;
    }
    // Mitsuba's path and prb integrators do not see media (null-bsdf boundaries are passed through
    // as if in vacuum): a medium in such a scene would be rendered, silently, where Mitsuba ignores it.
    const std::string type = integrator_ ? attr(integrator_, "type") : "path";
    if ((type == "path" || type == "prb") && root_.contains("media") && !root_["media"].empty()) {
      const std::string what = "integrator '" + type + "' ignores media in Mitsuba 3: use volpath or prbvolpath";
      if (integrator_) fail(integrator_, what);
      fail(scene, "no <integrator>, so " + what);
    }
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
  pugi::xml_node integrator_;  // the scene's <integrator>, once read
  // Per camera: its far_clip, and where it was given (empty: Mitsuba's default) and the sensor.
  struct FarClip {
    double distance;
    std::string given_at, sensor;
  };
  std::vector<FarClip> far_clips_;

  // ---- diagnostics -------------------------------------------------------------------------
  static std::string number_text(double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%g", v);
    return b;
  }
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

  // Element nesting, counted on the raw text before pugixml builds the tree. Markup that holds
  // '<' or '>' without being an element — quoted attribute values, comments, CDATA, processing
  // instructions, a DOCTYPE with its internal subset — is skipped whole, so it never counts as
  // nesting (a '>' inside a value used to hide the "/>" that closes its element). Anything
  // unterminated ends the scan: pugixml reports it as malformed.
  void check_depth() const {
    const std::string& s = text_;
    const size_t npos = std::string::npos;
    auto skip_past = [&](size_t from, const char* end) {
      const size_t at = s.find(end, from);
      return at == npos ? npos : at + std::strlen(end);
    };
    int depth = 0;
    size_t i = 0;
    while (i < s.size() && (i = s.find('<', i)) != npos) {
      if (s.compare(i, 4, "<!--") == 0) {
        i = skip_past(i + 4, "-->");
      } else if (s.compare(i, 9, "<![CDATA[") == 0) {
        i = skip_past(i + 9, "]]>");
      } else if (s.compare(i, 2, "<?") == 0) {
        i = skip_past(i + 2, "?>");
      } else if (s.compare(i, 2, "<!") == 0) {  // <!DOCTYPE …>, with its [ … ] internal subset
        int brackets = 0;
        size_t j = i + 2;
        for (; j < s.size(); ++j) {
          const char c = s[j];
          if (c == '"' || c == '\'') {
            j = s.find(c, j + 1);
            if (j == npos) break;
          } else if (c == '[') {
            ++brackets;
          } else if (c == ']') {
            --brackets;
          } else if (c == '>' && brackets <= 0) {
            break;
          }
        }
        i = j == npos || j >= s.size() ? npos : j + 1;
      } else if (s.compare(i, 2, "</") == 0) {
        --depth;
        i = skip_past(i + 2, ">");
      } else {
        // A start tag: attribute values are quoted and may hold '>' and "/>".
        size_t j = i + 1;
        for (; j < s.size() && s[j] != '>'; ++j)
          if (s[j] == '"' || s[j] == '\'') {
            j = s.find(s[j], j + 1);
            if (j == npos) break;
          }
        if (j == npos || j >= s.size()) break;
        if (s[j - 1] != '/' && ++depth > kXmlDepth)
          throw file_error(path_, "line " + std::to_string(line_at(i)) + ": elements nested deeper than " +
                                      std::to_string(kXmlDepth));
        i = j + 1;
      }
    }
  }

  // Mitsuba's ids are global: an object declared inside another (a <bsdf id="m"> in a <shape>) can
  // be referenced from anywhere. A walk with its own stack (the nesting is bounded, but need not
  // cost C++ stack); a <ref>'s id names its target and declares nothing.
  void collect_ids(const pugi::xml_node& scene) {
    std::vector<pugi::xml_node> stack;
    // Children pushed last to first: they come off the stack in document order, so a duplicate
    // is reported at its second occurrence.
    for (pugi::xml_node c = scene.last_child(); c; c = c.previous_sibling()) stack.push_back(c);
    while (!stack.empty()) {
      const pugi::xml_node n = stack.back();
      stack.pop_back();
      if (n.type() != pugi::node_element || tag(n) == "ref") continue;
      if (pugi::xml_attribute id = n.attribute("id"))
        if (!ids_.emplace(id.value(), n).second) fail(n, "duplicate id '" + std::string(id.value()) + "'");
      for (pugi::xml_node c = n.last_child(); c; c = c.previous_sibling()) stack.push_back(c);
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
      if (t == "spectrum" && n.attribute("filename"))
        fail(n, "spectra read from files are not supported (RGB only: give an <rgb> value)");
      if (t == "spectrum" && n.attribute("type"))
        fail(n, "spectrum type '" + attr(n, "type") + "' is not supported (RGB only: give an <rgb> value)");
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

  // A lookat without `up` (or with a zero one): Mitsuba takes the first tangent of
  // coordinate_system(dir) (Duff et al. 2017, "Building an orthonormal basis, revisited"; backlight's
  // Frame::s), with its sign conventions: sign(+0) = +1 for the basis, but mulsign and mulsign_neg
  // read the sign bit, so −0 counts as negative there.
  static Vec3d mitsuba_default_up(const Vec3d& n) {
    const double sign = n.z >= 0 ? 1.0 : -1.0, a = -1.0 / (sign + n.z), b = n.x * n.y * a;
    const bool negative = std::signbit(n.z);
    auto mulsign = [&](double v) { return negative ? -v : v; };
    return {mulsign(n.x * n.x * a) + 1.0, mulsign(b), -mulsign(n.x)};
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
        // Mitsuba's look_at, in double as its parser computes it.
        auto vec3d = [&](const char* name) {
          const std::vector<double> v = numbers(c, attr(c, name));
          if (v.size() != 3) fail(c, std::string("'") + name + "' needs three values");
          return Vec3d(v[0], v[1], v[2]);
        };
        const Vec3d o = vec3d("origin"), target = vec3d("target");
        const Vec3d dir = normalize(target - o);
        Vec3d up = c.attribute("up") ? vec3d("up") : Vec3d(0.0);
        if (up.x == 0 && up.y == 0 && up.z == 0) up = mitsuba_default_up(dir);
        Vec3d left = cross(up, dir);
        if (!(length(target - o) > 0) || !(length(left) > 0))
          fail(c, "degenerate lookat (origin = target or up ∥ direction)");
        left = normalize(left);
        const Vec3d new_up = cross(dir, left);
        const Vec3d cols[4] = {left, new_up, dir, o};
        for (int j = 0; j < 4; ++j)
          step.m[0][j] = float(cols[j].x), step.m[1][j] = float(cols[j].y), step.m[2][j] = float(cols[j].z);
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
  // Mitsuba compares booleans without regard to case ("True", "FALSE").
  bool get_bool(Props& p, const std::string& name, bool fallback) {
    if (!has(p, name)) return fallback;
    const pugi::xml_node n = get(p, name);
    const std::string v = lowercase(attr(n, "value"));
    if (v == "true") return true;
    if (v == "false") return false;
    fail(n, "expected true or false");
  }
  static std::string lowercase(std::string s) {
    for (char& c : s) c = char(std::tolower(static_cast<unsigned char>(c)));
    return s;
  }
  // A `filename` property, checked here so that a missing file names the XML element that asked for
  // it (the JSON loader, which reads it, resolves it the same way: relative to the scene's folder).
  std::string get_file(Props& p, const std::string& name) {
    const pugi::xml_node n = get(p, name);
    const std::string value = attr(n, "value");
    if (value.empty()) fail(n, "empty file name");
    fs::path file(value);
    if (file.is_relative()) file = fs::path(path_).parent_path() / file;
    std::error_code ec;
    const fs::file_status status = fs::status(file, ec);
    if (ec && ec != std::errc::no_such_file_or_directory) fail(n, "'" + value + "': " + ec.message());
    if (!fs::exists(status)) fail(n, "file '" + value + "' not found");
    if (!fs::is_regular_file(status)) fail(n, "'" + value + "' is not a regular file");
    return value;
  }
  // An index of refraction: a <float>, or a <string> naming one of Mitsuba's materials
  // (render/ior.h: Hecht's values at 589 nm), as Mitsuba's lookup_ior reads it.
  double get_ior(Props& p, const std::string& name, double fallback) {
    if (!has(p, name)) return fallback;
    const pugi::xml_node n = get(p, name);
    if (tag(n) != "string") return value(n);
    static const std::pair<const char*, double> kIors[] = {
        {"vacuum", 1.0},      {"helium", 1.000036},        {"hydrogen", 1.000132},
        {"air", 1.000277},    {"carbon dioxide", 1.00045}, {"water", 1.3330},
        {"acetone", 1.36},    {"ethanol", 1.361},          {"carbon tetrachloride", 1.461},
        {"glycerol", 1.4729}, {"benzene", 1.501},          {"silicone oil", 1.52045},
        {"bromine", 1.661},   {"water ice", 1.31},         {"fused quartz", 1.458},
        {"pyrex", 1.470},     {"acrylic glass", 1.49},     {"polypropylene", 1.49},
        {"bk7", 1.5046},      {"sodium chloride", 1.544},  {"amber", 1.55},
        {"pet", 1.5750},      {"diamond", 2.419}};
    const std::string wanted = lowercase(attr(n, "value"));
    std::string names;
    for (const auto& [ior_name, ior] : kIors) {
      if (wanted == ior_name) return double(float(ior));  // Mitsuba's table holds floats
      names += std::string(names.empty() ? "" : ", ") + ior_name;
    }
    fail(n, "unknown index of refraction '" + wanted + "' (a <float>, or one of Mitsuba's names: " + names + ")");
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
    for (const pugi::xml_node& o : p.objects) fail(o, "unexpected element in a bitmap texture");
    if (!has(p, "filename")) fail(n, "bitmap needs a filename");
    json t = {{"type", "bitmap"}, {"file", get_file(p, "filename")}};
    const std::string wrap = get_string(p, "wrap_mode", "repeat");
    if (wrap != "repeat" && wrap != "clamp" && wrap != "mirror")
      fail(n, "wrap_mode '" + wrap + "' is not supported (repeat, mirror or clamp)");
    t["wrap"] = wrap;
    if (get_bool(p, "raw", false)) t["color_space"] = "linear";
    // Backlight's bitmap lookup is bilinear only (kernels/texture/bitmap.h).
    const std::string filter = get_string(p, "filter_type", "bilinear");
    if (filter == "nearest")
      fail(get(p, "filter_type"), "filter_type 'nearest' is not supported (bitmap textures are bilinear)");
    if (filter != "bilinear") fail(get(p, "filter_type"), "unknown filter_type '" + filter + "' (bilinear)");
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

  // Mitsuba's plastics scale their diffuse lobe by 1/(η² (1 − F_dr)): light scattered back and
  // forth under the coat. F_dr is Mitsuba's fresnel_diffuse_reflectance(e) at e = 1/η (seen from
  // inside): Egan and Hilgeman's fit for e < 1, else d'Eon and Irving's polynomial in 1/e.
  // Backlight's roughplastic has no such factor.
  static std::string plastic_diffuse_note(double eta) {
    const double e = 1.0 / eta, x = eta;
    const double fdr = e < 1.0
                           ? 0.0636 * x + 0.6681 + e * (0.7099 - 1.4399 * e)
                           : 0.919317 + x * (-3.4793 + x * (6.75335 + x * (-7.80989 + x * (4.98554 - 1.36881 * x))));
    char factor[32];
    std::snprintf(factor, sizeof factor, "%.3g", 1.0 / (eta * eta * (1.0 - fdr)));
    return std::string("Mitsuba scales a plastic's diffuse lobe by 1/(η²(1 − F_dr)) for internal scattering (") +
           factor + " here), backlight's roughplastic does not: its diffuse reflection differs by about that factor";
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
      if (!has(p, "eta") && spec != json::array({1.0, 1.0, 1.0}))
        warn(n, "conductor_none",
             "Mitsuba's material \"none\" reflects specular_reflectance at every angle; here it is Schlick's F0, "
             "rising towards 1 at grazing angles (0.3 becomes 0.46 at 75 degrees)");
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
      // Mitsuba's defaults: polypropylene inside, air outside.
      const double int_ior = get_ior(p, "int_ior", double(1.49f)), ext_ior = get_ior(p, "ext_ior", double(1.000277f));
      if (!(int_ior > 0 && ext_ior > 0)) fail(n, "int_ior and ext_ior must be positive");
      if (has(p, "specular_reflectance") && color(get(p, "specular_reflectance")) != json::array({1.0, 1.0, 1.0}))
        fail(n, "specular_reflectance other than 1 is not supported");
      if (get_bool(p, "nonlinear", false))
        fail(get(p, "nonlinear"), "nonlinear true (colour shifts from internal scattering) is not supported");
      warn(n, "plastic_diffuse", plastic_diffuse_note(int_ior / ext_ior));
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
    // sample_visible only chooses how microfacet normals are sampled, not the BSDF's value.
    finish(n, p,
           type == "roughconductor" || type == "roughplastic" ? std::set<std::string>{"sample_visible"}
                                                              : std::set<std::string>{});
    return m;
  }

  void integrator(const pugi::xml_node& n) {
    const std::string type = plugin_type(n);
    if (type != "path" && type != "prb" && type != "volpath" && type != "prbvolpath")
      fail(n, "unsupported integrator (path, prb, volpath or prbvolpath)");
    if (integrator_) fail(n, "a second <integrator> (Mitsuba 3 takes one per scene)");
    integrator_ = n;
    Props p = props(n);
    json& it = root_["integrator"];
    origins_.push_back({"/integrator", where(n)});
    // Mitsuba's defaults, always written (backlight's own default depth is 6): path and volpath
    // (C++ MonteCarloIntegrator) trace until Russian roulette ends a path, prb and prbvolpath
    // (Python ADIntegrator) stop at 6 segments; rr_depth 5, and Mitsuba refuses rr_depth < 1,
    // where backlight's 0 would turn roulette off.
    it["max_depth"] = get_integer(p, "max_depth", type == "prb" || type == "prbvolpath" ? 6 : -1, -1, 1 << 20);
    if (has(p, "rr_depth") && value(p.values.at("rr_depth")) == 0)
      fail(get(p, "rr_depth"), "rr_depth must be at least 1 in Mitsuba 3 (0 is refused there)");
    it["rr_depth"] = get_integer(p, "rr_depth", 5, 1, 1 << 20);
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
    cam["fov_axis"] = lowercase(get_string(p, "fov_axis", "x"));  // Mitsuba lowercases it
    const double near_clip = get_number(p, "near_clip", 0.01), far_clip = get_number(p, "far_clip", 1e4);
    cam["near_clip"] = near_clip;
    if (!(far_clip > near_clip)) fail(has(p, "far_clip") ? get(p, "far_clip") : n, "far_clip must exceed near_clip");
    far_clips_.push_back({far_clip, has(p, "far_clip") ? where(get(p, "far_clip")) : "", where(n)});
    Transform t;
    if (has(p, "to_world")) {
      const pugi::xml_node tn = get(p, "to_world");
      t = transform(tn);
      check_sensor_transform(tn, t);
    }
    // Mitsuba's camera looks along +z of its frame with +y up (+x to the left of the image).
    const Vec3f o = t.point({0, 0, 0}), forward = t.vector({0, 0, 1}), up = t.vector({0, 1, 0});
    if (!(length(forward) > 0.f) || !(length(up) > 0.f)) fail(n, "degenerate to_world");
    const Vec3f target = o + normalize(forward);
    cam["origin"] = {o.x, o.y, o.z};
    cam["target"] = {target.x, target.y, target.z};
    cam["up"] = {up.x, up.y, up.z};
    int width = 768, height = 576;
    long spp = 4, seed = 0;  // Mitsuba's default sampler: independent, 4 samples per pixel, seed 0
    pugi::xml_node film, sampler;
    for (const pugi::xml_node& o2 : p.objects) {
      const pugi::xml_node c = resolve(o2);
      if (tag(c) == "film") {
        if (film) fail(o2, "a second <film> (Mitsuba 3 takes one per sensor)");
        film = c;
        if (plugin_type(c) != "hdrfilm") fail(c, "unsupported film (hdrfilm only)");
        Props f = props(c);
        width = int(get_integer(f, "width", 768, 1, long(limits::kImageSide)));
        height = int(get_integer(f, "height", 576, 1, long(limits::kImageSide)));
        if (width < 1 || height < 1) fail(c, "film size must be positive");
        limits::check_image_size(path_ + ": " + where(c), uint64_t(width), uint64_t(height));
        pugi::xml_node filter;
        for (const pugi::xml_node& r : f.objects) {
          if (tag(r) != "rfilter") fail(r, "unexpected element in a film");
          if (filter) fail(r, "a second <rfilter> (Mitsuba 3 takes one per film)");
          filter = r;
          rfilter(r);
        }
        if (has(f, "crop_width") || has(f, "crop_height") || has(f, "crop_offset_x") || has(f, "crop_offset_y"))
          fail(c, "crop windows are not supported");
        finish(c, f, {"pixel_format", "component_format", "file_format", "banner", "sample_border", "rgb_gamma"});
        if (!filter) warn(c, "rfilter", "no rfilter: Mitsuba's default (gaussian) is rendered as a box filter");
      } else if (tag(c) == "medium") {
        if (std::string(o2.attribute("name").value()) != "medium") fail(o2, "a sensor's medium is named medium");
        if (cam.contains("medium")) fail(o2, "a second sensor medium");
        cam["medium"] = medium_name(c);
      } else if (tag(c) == "sampler") {
        if (sampler) fail(o2, "a second <sampler> (Mitsuba 3 takes one per sensor)");
        sampler = c;
        Props s = props(c);
        const std::string st = plugin_type(c);
        if (st != "independent" && st != "stratified" && st != "multijitter" && st != "orthogonal" && st != "ldsampler")
          fail(c, "unknown sampler type");
        if (st != "independent") warn(c, "sampler", "sampler '" + st + "' is rendered with independent samples");
        spp = get_integer(s, "sample_count", 4, 1, long(limits::kSpp));
        seed = get_integer(s, "seed", 0, 0, 4294967295L);
        for (const pugi::xml_node& x : s.objects) fail(x, "unexpected element in a sampler");
        finish(c, s, {"jitter", "scramble_type"});
      } else {
        fail(c, "unexpected element in a sensor");
      }
    }
    if (!film)
      warn(n, "film", "no film: Mitsuba's default hdrfilm (768 × 576, gaussian rfilter) is rendered with a box filter");
    // Backlight has one sample count and seed per scene; Mitsuba one per sensor.
    json& it = root_["integrator"];
    const pugi::xml_node at = sampler ? sampler : n;
    if (it.contains("spp") && it["spp"] != spp)
      fail(at, "sensors with different sample counts are not supported (" + std::to_string(spp) + " here, " +
                   std::to_string(it["spp"].get<long>()) + " before)");
    if (it.contains("seed") && it["seed"] != seed) fail(at, "sensors with different sampler seeds are not supported");
    it["spp"] = spp;
    it["seed"] = seed;
    cam["resolution"] = {width, height};
    finish(n, p, {"shutter_open", "shutter_close", "srf"});
    origins_.push_back({"/cameras/" + std::to_string(root_["cameras"].size()), where(n)});
    root_["cameras"].push_back(cam);
  }

  // Mitsuba's sensor to_world is a rigid motion: it refuses scale factors (M·Mᵀ ≠ I beyond 1e-3, its
  // has_scale()), and a mirroring one would flip the image, which a camera given by origin, target
  // and up cannot express.
  void check_sensor_transform(const pugi::xml_node& n, const Transform& t) const {
    if (t.m[3][0] != 0.f || t.m[3][1] != 0.f || t.m[3][2] != 0.f || t.m[3][3] != 1.f)
      fail(n, "a sensor to_world must be affine (last row 0, 0, 0, 1)");
    for (int i = 0; i < 3; ++i)
      for (int j = i; j < 3; ++j) {
        const double dot =
            double(t.m[i][0]) * t.m[j][0] + double(t.m[i][1]) * t.m[j][1] + double(t.m[i][2]) * t.m[j][2];
        if (std::abs(dot - (i == j ? 1.0 : 0.0)) > 1e-3)
          fail(n, "a sensor to_world with scale factors or shear is not supported (Mitsuba 3 refuses it too)");
      }
    const double det = double(t.m[0][0]) * (double(t.m[1][1]) * t.m[2][2] - double(t.m[1][2]) * t.m[2][1]) -
                       double(t.m[0][1]) * (double(t.m[1][0]) * t.m[2][2] - double(t.m[1][2]) * t.m[2][0]) +
                       double(t.m[0][2]) * (double(t.m[1][0]) * t.m[2][1] - double(t.m[1][1]) * t.m[2][0]);
    if (det < 0) fail(n, "a mirroring sensor to_world (negative determinant) is not supported");
  }

  // Mitsuba's reconstruction filters and their properties. Backlight's film weighs a sample by the
  // box of its pixel, Mitsuba's box filter (which takes no properties); the others are rendered as
  // that box with one warning, their parameters read and checked but not used.
  void rfilter(const pugi::xml_node& r) {
    const std::string type = plugin_type(r);
    Props p = props(r);
    for (const pugi::xml_node& o : p.objects) fail(o, "unexpected element in a reconstruction filter");
    static const std::map<std::string, std::vector<std::string>> kFilters = {
        {"box", {}},        {"tent", {"radius"}},  {"gaussian", {"stddev"}}, {"mitchell", {"B", "C"}},
        {"catmullrom", {}}, {"lanczos", {"lobes"}}};
    const auto it = kFilters.find(type);
    if (it == kFilters.end()) fail(r, "unsupported rfilter (box, tent, gaussian, mitchell, catmullrom or lanczos)");
    for (const std::string& name : it->second)
      if (has(p, name)) value(get(p, name));
    if (type != "box") warn(r, "rfilter", "reconstruction filter '" + type + "' is rendered as a box filter");
    finish(r, p);
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
      s["file"] = get_file(p, "filename");
      if (type == "obj") s["flip_tex_coords"] = get_bool(p, "flip_tex_coords", true);
      if (get_bool(p, "face_normals", false))
        s["face_normals"] = true;
      else
        smooth_normals(n, s, to_world);
    } else if (type == "rectangle") {
      // Mitsuba's rectangle: [−1, 1]² at z = 0, normal +z, uv (0, 0) at (−1, −1).
      s["type"] = "mesh";
      s["positions"] = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
      s["normals"] = {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}, {0, 0, 1}};
      s["uvs"] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      s["indices"] = {{0, 1, 2}, {0, 2, 3}};
    } else if (type == "cube") {
      mitsuba_cube(s);
    } else if (type == "sphere") {
      s["type"] = "sphere";
      const double radius = get_number(p, "radius", 1.0);
      if (!(radius > 0)) fail(n, "radius must be positive");
      Vec3f center{0, 0, 0};
      if (has(p, "center")) center = xyz(get(p, "center"), 0.f);
      // Backlight's tessellated sphere has v = 0 at −z, Mitsuba's v = θ/π from +z (u = φ/2π from
      // +x about z in both): mirrored in z, the one is the other. The mirror reverses the winding,
      // which the loader restores for any mirroring transform (normals stay outward).
      to_world = to_world * Transform::translate(center) * Transform::scale(Vec3f(float(radius))) *
                 Transform::scale({1.f, 1.f, -1.f});
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
        if (s.contains("emitter")) fail(o, "a shape with two emitters (Mitsuba 3 takes one)");
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

  // Mitsuba's cube (shapes/cube.cpp): [−1, 1]³, four vertices per face sharing its normal, each face
  // mapped onto the unit square by the same uv pattern, two triangles {4s, 4s+1, 4s+2} and
  // {4s+3, 4s, 4s+2} per face s. Backlight's own cube lays its uvs out differently.
  static void mitsuba_cube(json& s) {
    static const int kNormals[6][3] = {{0, -1, 0}, {0, 1, 0}, {1, 0, 0}, {0, 0, 1}, {-1, 0, 0}, {0, 0, -1}};
    // Corner c of each vertex is at (±1, ±1, ±1), bit k of c the sign of axis k.
    static const int kCorners[24] = {1, 5, 4, 0, 3, 2, 6, 7, 1, 3, 7, 5, 5, 7, 6, 4, 4, 6, 2, 0, 3, 1, 0, 2};
    static const int kUvs[4][2] = {{0, 1}, {1, 1}, {1, 0}, {0, 0}};
    json positions = json::array(), normals = json::array(), uvs = json::array(), indices = json::array();
    for (int face = 0; face < 6; ++face) {
      for (int k = 0; k < 4; ++k) {
        const int c = kCorners[4 * face + k];
        positions.push_back({c & 1 ? 1 : -1, c & 2 ? 1 : -1, c & 4 ? 1 : -1});
        normals.push_back({kNormals[face][0], kNormals[face][1], kNormals[face][2]});
        uvs.push_back({kUvs[k][0], kUvs[k][1]});
      }
      const int v = 4 * face;
      indices.push_back({v, v + 1, v + 2});
      indices.push_back({v + 3, v, v + 2});
    }
    s["type"] = "mesh";
    s["positions"] = positions;
    s["normals"] = normals;
    s["uvs"] = uvs;
    s["indices"] = indices;
  }

  // An obj/ply shape whose file has no normals: Mitsuba shades it with vertex normals it computes
  // (unless face_normals), in world space, after to_world. The mesh is read here, given those
  // normals and written into the scene inline, in world space; a file with normals stays a file.
  void smooth_normals(const pugi::xml_node& n, json& s, Transform& to_world) {
    const std::string file = (fs::path(path_).parent_path() / s["file"].get<std::string>()).string();
    Mesh mesh = s["type"] == "obj" ? read_obj(file, s["flip_tex_coords"].get<bool>()) : read_ply(file);
    if (!mesh.normals.empty()) return;
    // Inline JSON is costly (a 490k-vertex grid: 660 MB at the peak instead of 170 MB, 1.7 s
    // instead of 0.45 s): beyond this size a file must bring its own normals.
    constexpr size_t kMaxVertices = size_t(1) << 20;
    if (mesh.positions.size() > kMaxVertices)
      fail(n, "'" + s["file"].get<std::string>() + "' has no vertex normals and more than " +
                  std::to_string(kMaxVertices) +
                  " vertices, too many to compute Mitsuba's here: add normals to the file or set face_normals");
    const float det = to_world.m[0][0] * (to_world.m[1][1] * to_world.m[2][2] - to_world.m[1][2] * to_world.m[2][1]) -
                      to_world.m[0][1] * (to_world.m[1][0] * to_world.m[2][2] - to_world.m[1][2] * to_world.m[2][0]) +
                      to_world.m[0][2] * (to_world.m[1][0] * to_world.m[2][1] - to_world.m[1][1] * to_world.m[2][0]);
    if (det == 0.f)  // as the loader words it
      throw file_error(path_,
                       where(n) + " ('" + s["name"].get<std::string>() + "'): degenerate transform (zero scale)");
    for (Vec3f& q : mesh.positions) q = to_world.point(q);
    mesh.normals = angle_weighted_normals(mesh.positions, mesh.indices);
    json positions = json::array(), normals = json::array(), uvs = json::array(), indices = json::array();
    for (size_t i = 0; i < mesh.positions.size(); ++i) {
      positions.push_back({mesh.positions[i].x, mesh.positions[i].y, mesh.positions[i].z});
      normals.push_back({mesh.normals[i].x, mesh.normals[i].y, mesh.normals[i].z});
      if (!mesh.uvs.empty()) uvs.push_back({mesh.uvs[i].x, mesh.uvs[i].y});
    }
    for (size_t t = 0; t + 2 < mesh.indices.size(); t += 3)
      indices.push_back({mesh.indices[t], mesh.indices[t + 1], mesh.indices[t + 2]});
    s = {{"name", s["name"]},
         {"type", "mesh"},
         {"positions", std::move(positions)},
         {"normals", std::move(normals)},
         {"indices", std::move(indices)}};
    if (!mesh.uvs.empty()) s["uvs"] = std::move(uvs);
    // In world space already; and a mirroring to_world keeps Mitsuba's winding (the loader would
    // reverse it), so that the normals computed from it agree with the faces.
    to_world = Transform();
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
    v.value = {{"type", "vol"}, {"file", get_file(p, "filename")}};
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
      if (albedo.grid) fail(albedo_at, "an albedo grid needs a sigma_t grid");
      // Mitsuba's heterogeneous medium exists only inside its sigma_t volume's box: for a constant,
      // the unit cube through the volume's to_world, however far the shapes that name it reach.
      if (type == "heterogeneous")
        fail(sigma_at,
             "a heterogeneous medium with a constant sigma_t fills only the unit cube (through the volume's to_world) "
             "in Mitsuba 3, which is not supported: use a homogeneous medium or a gridvolume");
      // A constant sigma_t fills the shapes that name the medium: backlight's homogeneous medium.
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
                  {"file", get_file(p, "filename")},
                  {"convention", "mitsuba"},
                  {"color_space", "auto"},
                  {"scale", get_number(p, "scale", 1.0)}};
      // to_world orients the map: its linear part turns directions (Mitsuba applies it to vectors,
      // so a translation does nothing and is dropped); it must be a rotation (checked by the JSON
      // loader, which names the element through origins_).
      if (has(p, "to_world")) {
        const Transform m = transform(get(p, "to_world"));
        json rows = json::array();
        for (int i = 0; i < 4; ++i)
          rows.push_back(
              {i < 3 ? m.m[i][0] : 0.f, i < 3 ? m.m[i][1] : 0.f, i < 3 ? m.m[i][2] : 0.f, i < 3 ? 0.f : 1.f});
        env["transform"] = {{"matrix", rows}};
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
  xml.check_far_clips(*scene);
  // A scene that fails to load gets its one error line only; one that loads, its warnings.
  for (const std::string& w : xml.warnings()) std::fprintf(stderr, "%s\n", w.c_str());
  return scene;
}

}  // namespace bl
