#include "engine/scene/mesh_io.h"

#include <tiny_obj_loader.h>

#include <bit>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <unordered_map>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/json_node.h"

namespace bl {

namespace fs = std::filesystem;

namespace {

void check_finite(const std::string& path, const char* what, float v) {
  if (!std::isfinite(v)) throw file_error(path, std::string(what) + " is NaN or infinite");
}

// The tokens of one line, split at spaces and tabs.
std::vector<std::string> tokens_of(const std::string& line) {
  std::vector<std::string> out;
  std::istringstream s(line);
  for (std::string t; s >> t;) out.push_back(t);
  return out;
}

// The text without its comments: '#' to the end of a line, on any line ("f 1 2 3 # top"). Files
// written by hand put them after data; tinyobjloader and the checks below took only whole comment
// lines and refused such a face ("'#' is not a face vertex"). Line ends stay, so line numbers do.
// One copying pass (erasing each comment in place would be quadratic in a file of many).
std::string without_comments(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  bool comment = false;
  for (const char c : text) {
    if (c == '\n' || c == '\r')
      comment = false;
    else if (c == '#')
      comment = true;
    if (!comment) out.push_back(c);
  }
  return out;
}

// tinyobjloader reads what it cannot parse as 0 ("v nan 0 0", "v abc 0 0") and face indices with
// atoi (an index past 2^31 wraps around to a valid vertex), so the numbers of the lines it reads
// are checked first: v, vn and vt values are finite decimal numbers (its grammar: no nan, inf or
// hex), face indices integers that fit its int, at least 3 of them per face.
void check_obj_numbers(const std::string& path, const std::string& text) {
  size_t line_number = 0;
  for (size_t at = 0; at < text.size();) {
    // Lines end in \n, \r\n or \r, as tinyobjloader reads them.
    size_t eol = text.find_first_of("\r\n", at);
    if (eol == std::string::npos) eol = text.size();
    const std::vector<std::string> tokens = tokens_of(text.substr(at, eol - at));
    at = eol + (text.compare(eol, 2, "\r\n") == 0 ? 2 : 1);
    ++line_number;
    if (tokens.empty()) continue;
    const std::string& key = tokens[0];
    const std::string where = "line " + std::to_string(line_number) + ": ";
    if (key == "v" || key == "vn" || key == "vt") {
      size_t values = 0;
      for (size_t i = 1; i < tokens.size(); ++i, ++values) {
        const std::string& t = tokens[i];
        char* end = nullptr;
        const double v = std::strtod(t.c_str(), &end);
        if (t.find_first_not_of("0123456789+-.eE") != std::string::npos || end != t.c_str() + t.size() ||
            !std::isfinite(v))
          throw file_error(path, where + "'" + t.substr(0, 40) + "' in a '" + key + "' line is not a finite number");
      }
      if (values < (key == "vt" ? 1u : 3u))
        throw file_error(path, where + "a '" + key + "' line needs " + (key == "vt" ? "a value" : "3 values"));
    } else if (key == "f") {
      for (size_t i = 1; i < tokens.size(); ++i) {
        // v, v/vt, v//vn or v/vt/vn: one to three components, the first one required.
        std::istringstream parts(tokens[i]);
        int component = 0;
        for (std::string c; std::getline(parts, c, '/'); ++component) {
          if (c.empty() && component > 0) continue;
          const bool integer =
              !c.empty() && c.find_first_not_of("0123456789", c[0] == '-' ? 1 : 0) == std::string::npos && c != "-";
          if (!integer || component > 2)
            throw file_error(
                path, where + "'" + tokens[i].substr(0, 40) + "' is not a face vertex (v, v/vt, v//vn or v/vt/vn)");
          errno = 0;
          const long long index = std::strtoll(c.c_str(), nullptr, 10);
          if (errno == ERANGE || index < -2147483647 || index > 2147483647)
            throw file_error(path, where + "face index " + c.substr(0, 40) + " is out of range");
        }
      }
      // tinyobjloader drops a face of one or two vertices with a warning nobody reads.
      if (tokens.size() < 4)
        throw file_error(path, where + "a face needs at least 3 vertices, not " + std::to_string(tokens.size() - 1) +
                                   " (lines are 'l')");
    }
  }
}

}  // namespace

Mesh read_obj(const std::string& path, bool flip_tex_coords) {
  const std::string text = without_comments(read_input_file(path));
  check_obj_numbers(path, text);
  tinyobj::ObjReaderConfig config;
  config.triangulate = false;  // fans below: tinyobjloader's polygon triangulation trusts its input
  config.vertex_color = false;
  tinyobj::ObjReader reader;
  // Materials are not read (an .mtl file next to it is ignored): backlight's come from the scene.
  if (!reader.ParseFromString(text, "", config)) {
    std::string msg = reader.Error();
    while (!msg.empty() && (msg.back() == '\n' || msg.back() == '\r')) msg.pop_back();
    throw file_error(path, "malformed OBJ (" + msg + ")");
  }
  const tinyobj::attrib_t& a = reader.GetAttrib();
  const size_t nv = a.vertices.size() / 3, nn = a.normals.size() / 3, nt = a.texcoords.size() / 2;
  // One pass to decide whether every corner has a normal and a uv (else the mesh gets none).
  bool normals = true, uvs = true;
  size_t corners = 0;
  for (const auto& shape : reader.GetShapes())
    for (const auto& idx : shape.mesh.indices) {
      if (idx.vertex_index < 0 || size_t(idx.vertex_index) >= nv)
        throw file_error(path,
                         "face refers to vertex " + std::to_string(idx.vertex_index + 1) + " of " + std::to_string(nv));
      if (idx.normal_index >= 0 && size_t(idx.normal_index) >= nn)
        throw file_error(path,
                         "face refers to normal " + std::to_string(idx.normal_index + 1) + " of " + std::to_string(nn));
      if (idx.texcoord_index >= 0 && size_t(idx.texcoord_index) >= nt)
        throw file_error(path, "face refers to texture coordinate " + std::to_string(idx.texcoord_index + 1) + " of " +
                                   std::to_string(nt));
      normals = normals && idx.normal_index >= 0;
      uvs = uvs && idx.texcoord_index >= 0;
      ++corners;
    }
  limits::require_at_most(path, "corner count", corners, limits::kMeshElements);
  Mesh m;
  struct Key {
    int v, n, t;
    bool operator==(const Key& o) const { return v == o.v && n == o.n && t == o.t; }
  };
  struct KeyHash {
    size_t operator()(const Key& k) const {
      return std::hash<uint64_t>()((uint64_t(uint32_t(k.v)) << 32) ^ (uint64_t(uint32_t(k.n)) << 16) ^
                                   uint64_t(uint32_t(k.t)));
    }
  };
  std::unordered_map<Key, uint32_t, KeyHash> index_of;
  auto vertex = [&](const tinyobj::index_t& idx) {
    const Key key{idx.vertex_index, normals ? idx.normal_index : -1, uvs ? idx.texcoord_index : -1};
    auto [it, fresh] = index_of.try_emplace(key, uint32_t(m.positions.size()));
    if (fresh) {
      const size_t v = size_t(key.v);
      const Vec3f p{a.vertices[3 * v], a.vertices[3 * v + 1], a.vertices[3 * v + 2]};
      check_finite(path, "a vertex position", p.x + p.y + p.z);
      m.positions.push_back(p);
      if (normals) {
        const size_t n = size_t(key.n);
        m.normals.push_back({a.normals[3 * n], a.normals[3 * n + 1], a.normals[3 * n + 2]});
        check_finite(path, "a normal", m.normals.back().x + m.normals.back().y + m.normals.back().z);
      }
      if (uvs) {
        const size_t t = size_t(key.t);
        Vec2f uv{a.texcoords[2 * t], a.texcoords[2 * t + 1]};
        if (flip_tex_coords) uv.y = 1.f - uv.y;
        check_finite(path, "a texture coordinate", uv.x + uv.y);
        m.uvs.push_back(uv);
      }
    }
    return it->second;
  };
  for (const auto& shape : reader.GetShapes()) {
    size_t at = 0;
    for (const unsigned char count : shape.mesh.num_face_vertices) {
      if (at + count > shape.mesh.indices.size()) throw file_error(path, "malformed OBJ (face list)");
      if (count >= 3) {
        const uint32_t first = vertex(shape.mesh.indices[at]);
        for (size_t k = 1; k + 1 < count; ++k) {
          const uint32_t b = vertex(shape.mesh.indices[at + k]), c = vertex(shape.mesh.indices[at + k + 1]);
          m.indices.insert(m.indices.end(), {first, b, c});
        }
      }
      at += count;
    }
  }
  if (m.indices.empty()) throw file_error(path, "the OBJ file has no faces");
  return m;
}

namespace {

enum class PlyType { I8, U8, I16, U16, I32, U32, F32, F64 };

bool ply_type(const std::string& name, PlyType& t) {
  static const std::pair<const char*, PlyType> table[] = {
      {"char", PlyType::I8},   {"int8", PlyType::I8},     {"uchar", PlyType::U8},   {"uint8", PlyType::U8},
      {"short", PlyType::I16}, {"int16", PlyType::I16},   {"ushort", PlyType::U16}, {"uint16", PlyType::U16},
      {"int", PlyType::I32},   {"int32", PlyType::I32},   {"uint", PlyType::U32},   {"uint32", PlyType::U32},
      {"float", PlyType::F32}, {"float32", PlyType::F32}, {"double", PlyType::F64}, {"float64", PlyType::F64}};
  for (const auto& [n, v] : table)
    if (name == n) return t = v, true;
  return false;
}

size_t ply_size(PlyType t) {
  switch (t) {
    case PlyType::I8:
    case PlyType::U8:
      return 1;
    case PlyType::I16:
    case PlyType::U16:
      return 2;
    case PlyType::I32:
    case PlyType::U32:
    case PlyType::F32:
      return 4;
    case PlyType::F64:
      return 8;
  }
  return 1;
}

struct PlyProperty {
  std::string name;
  PlyType type = PlyType::F32;
  bool list = false;
  PlyType count_type = PlyType::U8;
};

struct PlyElement {
  std::string name;
  uint64_t count = 0;
  std::vector<PlyProperty> properties;
};

// Reads values of a PLY body, ASCII or binary, with every read bounds-checked.
class PlyBody {
 public:
  PlyBody(const std::string& path, const std::string& data, size_t at, int format)
      : path_(path), data_(data), at_(at), format_(format) {}

  double read(PlyType t) {
    if (format_ == 0) return ascii();
    const size_t n = ply_size(t);
    if (at_ + n > data_.size()) throw file_error(path_, "PLY data ends early");
    unsigned char b[8];
    std::memcpy(b, data_.data() + at_, n);
    at_ += n;
    const bool big = format_ == 2;
    if (big != (std::endian::native == std::endian::big))
      for (size_t i = 0; i < n / 2; ++i) std::swap(b[i], b[n - 1 - i]);
    switch (t) {
      case PlyType::I8:
        return double(int8_t(b[0]));
      case PlyType::U8:
        return double(b[0]);
      case PlyType::I16: {
        int16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::U16: {
        uint16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::I32: {
        int32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::U32: {
        uint32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::F32: {
        float v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::F64: {
        double v;
        std::memcpy(&v, b, 8);
        return v;
      }
    }
    return 0;
  }
  size_t remaining() const { return data_.size() - at_; }
  // A list's length: each item takes at least a byte, so it cannot exceed what is left.
  uint64_t list_length(PlyType count_type) {
    const double n = read(count_type);
    if (!(n >= 0) || n > double(remaining()) || n != std::floor(n))
      throw file_error(path_, "PLY list length out of range");
    return uint64_t(n);
  }
  // Reads past one property (a value, or a whole list).
  void skip(const PlyProperty& p) {
    if (!p.list) {
      read(p.type);
      return;
    }
    for (uint64_t j = 0, n = list_length(p.count_type); j < n; ++j) read(p.type);
  }

 private:
  double ascii() {
    while (at_ < data_.size() && std::isspace(static_cast<unsigned char>(data_[at_]))) ++at_;
    const size_t start = at_;
    while (at_ < data_.size() && !std::isspace(static_cast<unsigned char>(data_[at_]))) ++at_;
    if (start == at_) throw file_error(path_, "PLY data ends early");
    const std::string token = data_.substr(start, at_ - start);
    char* end = nullptr;
    const double v = std::strtod(token.c_str(), &end);
    if (end != token.c_str() + token.size()) throw file_error(path_, "PLY value '" + token + "' is not a number");
    return v;
  }
  const std::string& path_;
  const std::string& data_;
  size_t at_;
  int format_;  // 0 ascii, 1 binary little endian, 2 binary big endian
};

}  // namespace

Mesh read_ply(const std::string& path) {
  const std::string data = read_input_file(path);
  // Header: lines up to "end_header".
  std::vector<PlyElement> elements;
  int format = -1;
  size_t at = 0;
  bool first = true, ended = false;
  while (at < data.size() && !ended) {
    size_t eol = data.find('\n', at);
    if (eol == std::string::npos) throw file_error(path, "PLY header has no end_header line");
    std::string line = data.substr(at, eol - at);
    at = eol + 1;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream s(line);
    std::string word;
    s >> word;
    if (first) {
      if (word != "ply") throw file_error(path, "not a PLY file (no 'ply' magic line)");
      first = false;
      continue;
    }
    if (word == "format") {
      std::string f, version;
      s >> f >> version;
      if (f == "ascii")
        format = 0;
      else if (f == "binary_little_endian")
        format = 1;
      else if (f == "binary_big_endian")
        format = 2;
      else
        throw file_error(path, "unknown PLY format '" + f + "'");
    } else if (word == "element") {
      PlyElement e;
      std::string count;
      s >> e.name >> count;
      // Read as text: an unsigned stream read takes "-4" for 2^64 − 4.
      errno = 0;
      if (!s || count.empty() || count.find_first_not_of("0123456789") != std::string::npos)
        throw file_error(path, "malformed PLY element line '" + line + "' (the count must be a whole number ≥ 0)");
      e.count = std::strtoull(count.c_str(), nullptr, 10);
      if (errno == ERANGE) throw file_error(path, "PLY element count " + count + " is out of range");
      limits::require_at_most(path, "PLY element count", e.count, limits::kMeshElements);
      elements.push_back(e);
    } else if (word == "property") {
      if (elements.empty()) throw file_error(path, "PLY property before any element");
      PlyProperty p;
      std::string type;
      s >> type;
      if (type == "list") {
        std::string count_type, item_type;
        s >> count_type >> item_type >> p.name;
        p.list = true;
        if (!ply_type(count_type, p.count_type) || !ply_type(item_type, p.type))
          throw file_error(path, "unknown PLY list types in '" + line + "'");
        if (p.count_type == PlyType::F32 || p.count_type == PlyType::F64)
          throw file_error(path, "PLY list count type '" + count_type + "' is not an integer type in '" + line + "'");
      } else {
        s >> p.name;
        if (!ply_type(type, p.type)) throw file_error(path, "unknown PLY property type '" + type + "'");
      }
      if (p.name.empty()) throw file_error(path, "malformed PLY property line '" + line + "'");
      elements.back().properties.push_back(p);
    } else if (word == "end_header") {
      ended = true;
    } else if (word != "comment" && word != "obj_info" && !word.empty()) {
      throw file_error(path, "unknown PLY header line '" + line + "'");
    }
  }
  if (!ended) throw file_error(path, "PLY header has no end_header line");
  if (format < 0) throw file_error(path, "PLY header has no format line");

  Mesh m;
  PlyBody body(path, data, at, format);
  uint64_t vertex_count = 0;
  bool have_vertices = false, have_faces = false;
  for (const PlyElement& e : elements) {
    // The least an entry can take: its scalar sizes and list counts (binary), or a digit and a
    // separator per value (ASCII). A count the rest of the file cannot hold is refused before
    // anything is allocated.
    uint64_t least = 0;
    for (const PlyProperty& p : e.properties) least += format == 0 ? 2 : ply_size(p.list ? p.count_type : p.type);
    if (least == 0 ? e.count > body.remaining() : e.count > body.remaining() / least)
      throw file_error(path, "PLY element '" + e.name + "' is larger than the file");
    if (e.name == "vertex") {
      have_vertices = true;
      vertex_count = e.count;
      auto find = [&](std::initializer_list<const char*> names) {
        for (size_t i = 0; i < e.properties.size(); ++i)
          for (const char* n : names)
            if (!e.properties[i].list && e.properties[i].name == n) return int(i);
        return -1;
      };
      const int x = find({"x"}), y = find({"y"}), z = find({"z"});
      if (x < 0 || y < 0 || z < 0) throw file_error(path, "PLY vertices need x, y and z");
      const int nx = find({"nx"}), ny = find({"ny"}), nz = find({"nz"});
      const int u = find({"u", "s", "texture_u", "texture_s"}), v = find({"v", "t", "texture_v", "texture_t"});
      const bool normals = nx >= 0 && ny >= 0 && nz >= 0, uvs = u >= 0 && v >= 0;
      m.positions.reserve(size_t(e.count) + 1);
      std::vector<double> values(e.properties.size());
      for (uint64_t i = 0; i < e.count; ++i) {
        for (size_t k = 0; k < e.properties.size(); ++k) {
          const PlyProperty& p = e.properties[k];
          if (p.list) {
            body.skip(p);
            values[k] = 0;
          } else {
            values[k] = body.read(p.type);
          }
        }
        const Vec3f pos{float(values[size_t(x)]), float(values[size_t(y)]), float(values[size_t(z)])};
        check_finite(path, "a vertex position", pos.x + pos.y + pos.z);
        m.positions.push_back(pos);
        if (normals)
          m.normals.push_back({float(values[size_t(nx)]), float(values[size_t(ny)]), float(values[size_t(nz)])});
        if (uvs) m.uvs.push_back({float(values[size_t(u)]), float(values[size_t(v)])});
      }
    } else if (e.name == "face") {
      if (!have_vertices) throw file_error(path, "PLY faces come before the vertices");
      have_faces = true;
      int list = -1;
      for (size_t i = 0; i < e.properties.size(); ++i)
        if (e.properties[i].list &&
            (e.properties[i].name == "vertex_indices" || e.properties[i].name == "vertex_index"))
          list = int(i);
      if (list < 0) throw file_error(path, "PLY faces need a vertex_indices list");
      std::vector<uint32_t> face;
      for (uint64_t i = 0; i < e.count; ++i) {
        for (size_t k = 0; k < e.properties.size(); ++k) {
          const PlyProperty& p = e.properties[k];
          if (int(k) != list) {
            body.skip(p);
            continue;
          }
          face.clear();
          for (uint64_t j = 0, n = body.list_length(p.count_type); j < n; ++j) {
            const double idx = body.read(p.type);
            if (!(idx >= 0) || idx >= double(vertex_count) || idx != std::floor(idx))
              throw file_error(
                  path, "PLY face refers to vertex " + std::to_string(idx) + " of " + std::to_string(vertex_count));
            face.push_back(uint32_t(idx));
          }
          if (face.size() < 3)  // was dropped without a word
            throw file_error(path, "PLY face " + std::to_string(i) + " has " + std::to_string(face.size()) +
                                       " vertex indices (a face needs at least 3)");
          for (size_t j = 1; j + 1 < face.size(); ++j) {
            limits::require_at_most(path, "triangle count", m.indices.size() / 3 + 1, limits::kMeshElements);
            m.indices.insert(m.indices.end(), {face[0], face[j], face[j + 1]});
          }
        }
      }
    } else {
      for (uint64_t i = 0; i < e.count; ++i)
        for (const PlyProperty& p : e.properties) body.skip(p);
    }
  }
  if (!have_vertices || !have_faces || m.indices.empty()) throw file_error(path, "the PLY file has no faces");
  for (const Vec3f& n : m.normals) check_finite(path, "a normal", n.x + n.y + n.z);
  for (const Vec2f& uv : m.uvs) check_finite(path, "a texture coordinate", uv.x + uv.y);
  return m;
}

std::vector<Vec3f> angle_weighted_normals(const std::vector<Vec3f>& positions, const std::vector<uint32_t>& indices) {
  std::vector<Vec3d> sum(positions.size(), Vec3d(0.0));
  // The angle between unit vectors, accurate near 0 and π (Mitsuba's unit_angle).
  auto unit_angle = [](const Vec3d& a, const Vec3d& b) {
    const double pi = 3.14159265358979323846;
    return dot(a, b) < 0 ? pi - 2 * std::asin(length(a + b) / 2) : 2 * std::asin(length(a - b) / 2);
  };
  for (size_t t = 0; t + 2 < indices.size(); t += 3) {
    const uint32_t i[3] = {indices[t], indices[t + 1], indices[t + 2]};
    const Vec3d p[3] = {Vec3d(positions[i[0]]), Vec3d(positions[i[1]]), Vec3d(positions[i[2]])};
    const Vec3d n = cross(p[1] - p[0], p[2] - p[0]);
    if (!(dot(n, n) > 0)) continue;
    const Vec3d unit = n / length(n);
    for (int k = 0; k < 3; ++k) {
      const Vec3d a = p[(k + 1) % 3] - p[k], b = p[(k + 2) % 3] - p[k];
      sum[i[k]] += unit * unit_angle(a / length(a), b / length(b));
    }
  }
  std::vector<Vec3f> normals(positions.size());
  for (size_t v = 0; v < sum.size(); ++v) {
    const double l = length(sum[v]);
    normals[v] = l > 0 ? Vec3f(sum[v] / l) : Vec3f(1.f, 0.f, 0.f);
  }
  return normals;
}

Mesh make_sphere(int segments) {
  Mesh m;
  const int rings = segments / 2;
  const float pi = 3.14159265358979f;
  // The seam (u = 1) repeats u = 0 and each pole row one point, bit for bit (sin(2π) and sin(π) in
  // float are not 0, and 0 · a negative cosine is −0): a medium bounded by a sphere was "not
  // closed" (its vertices weld by bitwise position).
  for (int j = 0; j <= rings; ++j) {
    const float v = float(j) / float(rings), theta = pi * (1.f - v);  // v = 0 at the south pole (−z)
    const bool pole = j == 0 || j == rings;
    for (int i = 0; i <= segments; ++i) {
      const float u = float(i) / float(segments), phi = i == segments ? 0.f : 2.f * pi * u;
      const Vec3f n = pole ? Vec3f{0.f, 0.f, j == 0 ? -1.f : 1.f}
                           : Vec3f{std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta)};
      m.positions.push_back(n);
      m.normals.push_back(n);
      m.uvs.push_back({u, v});
    }
  }
  const uint32_t row = uint32_t(segments + 1);
  for (int j = 0; j < rings; ++j)
    for (int i = 0; i < segments; ++i) {
      const uint32_t a = uint32_t(j) * row + uint32_t(i), b = a + 1, c = a + row, d = c + 1;
      // Counter-clockwise seen from outside: (b − a) × (c − a) points outwards.
      if (j > 0) m.indices.insert(m.indices.end(), {a, b, c});
      if (j + 1 < rings) m.indices.insert(m.indices.end(), {b, d, c});
    }
  return m;
}

}  // namespace bl
