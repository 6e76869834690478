// glTF 2.0 (.gltf/.glb) loading through tinygltf: meshes with node transforms and vertex
// colours, cameras, metallic-roughness materials and emissive materials as area lights. What
// backlight cannot render as glTF specifies (morph targets in use, skins, alpha cut-outs and
// blending, orthographic or mirrored cameras, nearest filtering) is refused by name; what it
// skips or ignores (points and lines, meshes under nodes scaled to 0, normal and occlusion maps)
// gets one warning per file.
#include <tiny_gltf.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <set>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/image_io.h"
#include "engine/scene/gltf_json_checks.h"
#include "engine/scene/mesh_io.h"
#include "engine/scene/scene_load.h"

namespace bl {

namespace fs = std::filesystem;

namespace {

std::string first_line(std::string s) {
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
  if (auto nl = s.find('\n'); nl != std::string::npos) s.resize(nl);
  return s;
}

// The JSON of a .gltf file, or of a .glb's first chunk (binary glTF: 12-byte header, then chunks
// of length, type, data; the first is the JSON).
std::string gltf_json_text(const std::string& path, bool binary) {
  limits::require_at_most(path, "file size", uint64_t(fs::file_size(path)), limits::kFileBytes);
  std::ifstream f(path, std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  if (!binary) return bytes;
  if (bytes.size() < 20 || bytes.compare(0, 4, "glTF") != 0) throw file_error(path, "invalid glTF: not a binary glTF");
  // Version 1 GLB files lay their chunks out differently; tinygltf would read them as version 2.
  uint32_t version = 0;
  std::memcpy(&version, bytes.data() + 4, 4);
  if (version != 2)
    throw file_error(path, "invalid glTF: binary glTF version " + std::to_string(version) + " (expected 2)");
  uint32_t length = 0;
  std::memcpy(&length, bytes.data() + 12, 4);
  if (length > bytes.size() - 20)
    throw file_error(path, "invalid glTF: the JSON chunk extends past the end of the file");
  return bytes.substr(20, length);
}

// File access for tinygltf (the glTF itself, external buffers and images): only regular files,
// of bounded size, with paths used as written. tinygltf's defaults would read a directory or a
// device named by a `uri` (its size then reads as 2^63 and the allocation fails) and expand
// paths through wordexp.
bool gltf_file_exists(const std::string& path, void*) {
  std::error_code ec;
  return fs::is_regular_file(path, ec);
}
std::string gltf_expand_path(const std::string& path, void*) { return path; }
bool gltf_read_file(std::vector<unsigned char>* out, std::string* err, const std::string& path, void*) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) {
    if (err) *err += "'" + path.substr(0, 200) + "' is not a regular file\n";
    return false;
  }
  const auto size = fs::file_size(path, ec);
  if (ec || size > limits::kFileBytes) {
    if (err)
      *err += "'" + path.substr(0, 200) + "' exceeds the limit of " + std::to_string(limits::kFileBytes) + " bytes\n";
    return false;
  }
  std::ifstream f(path, std::ios::binary);
  out->resize(size_t(size));
  if (size > 0 && !f.read(reinterpret_cast<char*>(out->data()), std::streamsize(size))) {
    if (err) *err += "cannot read '" + path.substr(0, 200) + "'\n";
    return false;
  }
  return true;
}
bool gltf_write_file(std::string*, const std::string&, const std::vector<unsigned char>&, void*) { return false; }
// Images: the header's size is checked before tinygltf's decoder allocates for it (a 389 KB PNG
// claiming 20000² pixels took 3 GB before the texture limit refused it).
bool gltf_load_image(tinygltf::Image* image, const int index, std::string* err, std::string* warn, int req_width,
                     int req_height, const unsigned char* bytes, int size, void* user) {
  try {
    check_encoded_image("image " + std::to_string(index), bytes, size_t(std::max(size, 0)));
  } catch (const InputError& e) {
    if (err) *err += std::string(e.what()) + "\n";
    return false;
  }
  return tinygltf::LoadImageData(image, index, err, warn, req_width, req_height, bytes, size, user);
}

tinygltf::Model read_model(const std::string& path) {
  require_input_file(path);
  tinygltf::TinyGLTF loader;
  loader.SetFsCallbacks({gltf_file_exists, gltf_expand_path, gltf_read_file, gltf_write_file, nullptr});
  loader.SetImageLoader(gltf_load_image, nullptr);
  tinygltf::Model model;
  std::string err, warn;
  std::string ext = fs::path(path).extension().string();
  for (auto& c : ext) c = char(std::tolower(c));
  // tinygltf's JSON parser recurses without a bound (60k-deep `extras` overflow the stack).
  const std::string json_text = gltf_json_text(path, ext == ".glb");
  limits::check_json_depth(path, json_text);
  const nlohmann::json doc = nlohmann::json::parse(json_text, nullptr, false);
  // Else tinygltf reports the syntax error.
  if (!doc.is_discarded() && doc.is_object()) gltf_json::check_gltf_json(path, doc);
  bool ok = ext == ".glb" ? loader.LoadBinaryFromFile(&model, &err, &warn, path)
                          : loader.LoadASCIIFromFile(&model, &err, &warn, path);
  if (!ok || !err.empty())
    throw file_error(path, "invalid glTF: " + (err.empty() ? std::string("cannot parse") : first_line(err)));
  return model;
}

// The determinant of a transform's linear part, in double: its sign tells whether it mirrors, and
// it is 0 for a transform that scales to 0.
double linear_determinant(const Transform& t) {
  const auto m = [&](int r, int c) { return double(t.m[r][c]); };
  return m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1)) - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0)) +
         m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
}

std::string number_text(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}

// Channel `c` of pixel `i` of a decoded glTF image, in [0, 1]. tinygltf decodes 8-bit images to
// bytes and 16-bit PNGs to two bytes per channel, in the machine's byte order.
float texel(const tinygltf::Image& img, size_t i, int c) {
  const size_t k = i * size_t(img.component) + size_t(c);
  if (img.bits == 16) {
    uint16_t v;
    std::memcpy(&v, img.image.data() + 2 * k, 2);
    return float(v) / 65535.f;
  }
  return float(img.image[k]) / 255.f;
}

// A node's local transform: its matrix, or T · R · S. The specification's constraints are checked
// rather than the values used as they come: a matrix must be affine (decomposable into TRS) and
// a rotation a unit quaternion (an unnormalized one would scale the mesh by its squared length).
Transform node_local(const tinygltf::Node& node, int index, const std::string& path) {
  const std::string what = "node " + std::to_string(index) + " ('" + node.name.substr(0, 100) + "')";
  auto check = [&](const std::vector<double>& values, size_t size, const char* name) {
    if (!values.empty() && values.size() != size)
      throw file_error(path, what + ": " + name + " needs " + std::to_string(size) + " numbers, not " +
                                 std::to_string(values.size()));
    for (double v : values)
      if (!std::isfinite(v)) throw file_error(path, what + ": " + name + " holds a non-finite value");
  };
  check(node.matrix, 16, "matrix");
  check(node.scale, 3, "scale");
  check(node.rotation, 4, "rotation");
  check(node.translation, 3, "translation");
  Transform t;
  if (node.matrix.size() == 16) {
    // glTF matrices are column-major.
    for (int r = 0; r < 4; ++r)
      for (int c = 0; c < 4; ++c) t.m[r][c] = float(node.matrix[size_t(c * 4 + r)]);
    if (t.m[3][0] != 0.f || t.m[3][1] != 0.f || t.m[3][2] != 0.f || t.m[3][3] != 1.f)
      throw file_error(path, what + ": matrix is not affine (its last row must be 0, 0, 0, 1)");
    return t;
  }
  if (node.scale.size() == 3) t = Transform::scale({float(node.scale[0]), float(node.scale[1]), float(node.scale[2])});
  if (node.rotation.size() == 4) {
    const double norm = std::sqrt(node.rotation[0] * node.rotation[0] + node.rotation[1] * node.rotation[1] +
                                  node.rotation[2] * node.rotation[2] + node.rotation[3] * node.rotation[3]);
    if (!(std::abs(norm - 1.0) <= 1e-3))
      throw file_error(path, what + ": rotation is not a unit quaternion (its length is " + std::to_string(norm) + ")");
    // Exporters round to a few digits: the small drift tolerated above is normalized away.
    const float x = float(node.rotation[0] / norm), y = float(node.rotation[1] / norm),
                z = float(node.rotation[2] / norm), w = float(node.rotation[3] / norm);
    // Unit quaternion (x, y, z, w) → rotation matrix.
    Transform r;
    r.m[0][0] = 1 - 2 * (y * y + z * z);
    r.m[0][1] = 2 * (x * y - z * w);
    r.m[0][2] = 2 * (x * z + y * w);
    r.m[1][0] = 2 * (x * y + z * w);
    r.m[1][1] = 1 - 2 * (x * x + z * z);
    r.m[1][2] = 2 * (y * z - x * w);
    r.m[2][0] = 2 * (x * z - y * w);
    r.m[2][1] = 2 * (y * z + x * w);
    r.m[2][2] = 1 - 2 * (x * x + y * y);
    t = r * t;
  }
  if (node.translation.size() == 3)
    t = Transform::translate({float(node.translation[0]), float(node.translation[1]), float(node.translation[2])}) * t;
  return t;
}

// The bytes of accessor `index` whose elements are `element_size` bytes: every index on the way
// (accessor, buffer view, buffer) is checked, and the last element must end inside the buffer view
// (which must end inside its buffer), as the specification requires; a stride shorter than an
// element would overlap the elements.
struct AccessorBytes {
  const unsigned char* data;
  size_t stride, count;
};
AccessorBytes accessor_bytes(const tinygltf::Model& model, int index, size_t element_size, const std::string& path) {
  const std::string what = "accessor " + std::to_string(index);
  if (index < 0 || size_t(index) >= model.accessors.size()) throw file_error(path, what + " is out of range");
  const auto& acc = model.accessors[size_t(index)];
  if (acc.bufferView < 0 || size_t(acc.bufferView) >= model.bufferViews.size())
    throw file_error(path, what + " has no buffer view");
  const auto& view = model.bufferViews[size_t(acc.bufferView)];
  if (view.buffer < 0 || size_t(view.buffer) >= model.buffers.size())
    throw file_error(path, "buffer view references a missing buffer");
  const auto& buf = model.buffers[size_t(view.buffer)];
  // tinygltf reads an absent byteStride as 0 and refuses one that is not a multiple of 4 up to 252.
  if (view.byteStride && view.byteStride < element_size)
    throw file_error(path, what + ": byteStride " + std::to_string(view.byteStride) + " of buffer view " +
                               std::to_string(acc.bufferView) + " is less than the element size (" +
                               std::to_string(element_size) + " bytes)");
  const uint64_t stride = view.byteStride ? view.byteStride : element_size;
  // Every offset and extent in 64-bit checked arithmetic: counts near 2^64 must not wrap around.
  limits::require_at_most(path, what + ": element count", acc.count, 3 * limits::kMeshElements);
  uint64_t view_end = 0, span = 0, end_in_view = 0;
  if (!limits::checked_add(view.byteOffset, view.byteLength, view_end) || view_end > buf.data.size())
    throw file_error(path, "buffer view " + std::to_string(acc.bufferView) + " reads past the end of its buffer");
  bool fits = true;
  if (acc.count > 0)
    fits = limits::checked_mul(stride, acc.count - 1, span) && limits::checked_add(span, element_size, span);
  fits = fits && limits::checked_add(acc.byteOffset, span, end_in_view);
  if (!fits || end_in_view > view.byteLength) throw file_error(path, what + " reads past the end of its buffer view");
  return {buf.data.data() + view.byteOffset + acc.byteOffset, size_t(stride), size_t(acc.count)};
}

// `bytes` bytes at `offset` into buffer view `view_index`, bounds-checked like accessor_bytes
// (64-bit checked arithmetic; within the view and its buffer).
const unsigned char* view_bytes(const tinygltf::Model& model, int view_index, int64_t offset, uint64_t bytes,
                                const std::string& what, const std::string& path) {
  if (view_index < 0 || size_t(view_index) >= model.bufferViews.size())
    throw file_error(path, what + ": buffer view out of range");
  const auto& view = model.bufferViews[size_t(view_index)];
  if (view.buffer < 0 || size_t(view.buffer) >= model.buffers.size())
    throw file_error(path, "buffer view references a missing buffer");
  const auto& buf = model.buffers[size_t(view.buffer)];
  uint64_t end_in_view = 0, start = 0, end = 0;
  const bool fits = offset >= 0 && limits::checked_add(uint64_t(offset), bytes, end_in_view) &&
                    end_in_view <= view.byteLength && limits::checked_add(view.byteOffset, uint64_t(offset), start) &&
                    limits::checked_add(start, bytes, end) && end <= buf.data.size();
  if (!fits) throw file_error(path, what + " reads past the end of its buffer view");
  return buf.data.data() + start;
}

uint32_t read_index_value(const unsigned char* p, size_t size) {
  return size == 1   ? p[0]
         : size == 2 ? uint32_t(p[0] | (p[1] << 8))
                     : uint32_t(p[0] | (p[1] << 8) | (p[2] << 16) | (uint32_t(p[3]) << 24));
}

const char* component_type_name(int type) {
  switch (type) {
    case TINYGLTF_COMPONENT_TYPE_BYTE:
      return "BYTE";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
      return "UNSIGNED_BYTE";
    case TINYGLTF_COMPONENT_TYPE_SHORT:
      return "SHORT";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT:
      return "UNSIGNED_SHORT";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT:
      return "UNSIGNED_INT";
    case TINYGLTF_COMPONENT_TYPE_FLOAT:
      return "FLOAT";
  }
  return "unknown";
}

const char* type_name(int type) {
  switch (type) {
    case TINYGLTF_TYPE_SCALAR:
      return "SCALAR";
    case TINYGLTF_TYPE_VEC2:
      return "VEC2";
    case TINYGLTF_TYPE_VEC3:
      return "VEC3";
    case TINYGLTF_TYPE_VEC4:
      return "VEC4";
    case TINYGLTF_TYPE_MAT2:
      return "MAT2";
    case TINYGLTF_TYPE_MAT3:
      return "MAT3";
    case TINYGLTF_TYPE_MAT4:
      return "MAT4";
  }
  return "unknown";
}

size_t index_size(int component_type) {
  return component_type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE    ? 1
         : component_type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ? 2
         : component_type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT   ? 4
                                                                    : 0;
}

// Reads accessor `index` as floats (count × components). A sparse accessor is its base (the
// buffer view, or zeros when it has none) with `sparse.count` elements substituted.
std::vector<float> read_floats(const tinygltf::Model& model, int index, int components, const std::string& path) {
  if (index < 0 || size_t(index) >= model.accessors.size()) throw file_error(path, "accessor index out of range");
  const auto& acc = model.accessors[size_t(index)];
  const std::string what = "accessor " + std::to_string(index);
  // Floats, or integers (texture coordinates in core glTF; any attribute with
  // KHR_mesh_quantization), normalized to [0, 1] / [-1, 1] when the accessor says so.
  const int type = acc.componentType;
  const size_t csize = type == TINYGLTF_COMPONENT_TYPE_FLOAT                                                     ? 4
                       : type == TINYGLTF_COMPONENT_TYPE_BYTE || type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE   ? 1
                       : type == TINYGLTF_COMPONENT_TYPE_SHORT || type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ? 2
                                                                                                                 : 0;
  if (!csize || tinygltf::GetNumComponentsInType(uint32_t(acc.type)) != components)
    throw file_error(path, what + " has an unsupported type");
  const size_t element = size_t(components) * csize;
  auto decode = [&](const unsigned char* src, float* dst) {
    for (int c = 0; c < components; ++c, src += csize) {
      float v;
      switch (type) {
        case TINYGLTF_COMPONENT_TYPE_FLOAT:
          std::memcpy(&v, src, 4);
          break;
        case TINYGLTF_COMPONENT_TYPE_BYTE:
          v = float(int8_t(src[0]));
          break;
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          v = float(src[0]);
          break;
        case TINYGLTF_COMPONENT_TYPE_SHORT:
          v = float(int16_t(uint16_t(src[0] | src[1] << 8)));
          break;
        default:
          v = float(uint16_t(src[0] | src[1] << 8));
          break;
      }
      if (acc.normalized) {
        if (type == TINYGLTF_COMPONENT_TYPE_BYTE) v = std::max(v / 127.f, -1.f);
        if (type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE) v /= 255.f;
        if (type == TINYGLTF_COMPONENT_TYPE_SHORT) v = std::max(v / 32767.f, -1.f);
        if (type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT) v /= 65535.f;
      }
      dst[c] = v;
    }
  };
  std::vector<float> out;
  if (acc.bufferView >= 0) {
    const AccessorBytes bytes = accessor_bytes(model, index, element, path);
    out.resize(bytes.count * size_t(components));
    for (size_t i = 0; i < bytes.count; ++i) decode(bytes.data + i * bytes.stride, &out[i * size_t(components)]);
  } else {
    // Without a buffer view an accessor reads as zeros (the specification's rule; a sparse
    // accessor then substitutes its elements). No bytes in the file back these zeros: the count
    // alone is bounded, by the mesh limit.
    limits::require_at_most(path, what + ": element count", acc.count, limits::kMeshElements);
    out.assign(acc.count * size_t(components), 0.f);
  }
  if (acc.sparse.isSparse) {
    const auto& sp = acc.sparse;
    const std::string swhat = what + " (sparse)";
    if (sp.count < 1 || uint64_t(sp.count) > acc.count)
      throw file_error(
          path, swhat + ": count " + std::to_string(sp.count) + " is not in [1, " + std::to_string(acc.count) + "]");
    const size_t isize = index_size(sp.indices.componentType);
    if (!isize) throw file_error(path, swhat + ": unsupported index type");
    const size_t n = size_t(sp.count);
    const unsigned char* idx =
        view_bytes(model, sp.indices.bufferView, sp.indices.byteOffset, uint64_t(n) * isize, swhat + " indices", path);
    const unsigned char* val =
        view_bytes(model, sp.values.bufferView, sp.values.byteOffset, uint64_t(n) * element, swhat + " values", path);
    for (size_t k = 0; k < n; ++k) {
      const uint32_t i = read_index_value(idx + k * isize, isize);
      if (uint64_t(i) >= acc.count) throw file_error(path, swhat + ": index " + std::to_string(i) + " is out of range");
      decode(val + k * element, &out[size_t(i) * size_t(components)]);
    }
  }
  for (float v : out)
    if (!std::isfinite(v)) throw file_error(path, what + " holds non-finite values");
  return out;
}

// The indices of primitive `where`: SCALARs of unsigned bytes, shorts or ints (the specification's
// types), from a dense accessor.
std::vector<uint32_t> read_indices(const tinygltf::Model& model, int index, const std::string& where,
                                   const std::string& path) {
  if (index < 0 || size_t(index) >= model.accessors.size())
    throw file_error(path, where + ": index accessor out of range");
  const auto& acc = model.accessors[size_t(index)];
  const std::string what = where + ": indices (accessor " + std::to_string(index) + ")";
  if (acc.type != TINYGLTF_TYPE_SCALAR)
    throw file_error(path, what + ": type " + type_name(acc.type) + " (expected SCALAR)");
  const size_t size = index_size(acc.componentType);
  if (!size)
    throw file_error(path, what + ": component type " + component_type_name(acc.componentType) +
                               " (expected UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT)");
  if (acc.sparse.isSparse)
    throw file_error(path, "accessor " + std::to_string(index) + ": sparse triangle indices are not supported");
  const AccessorBytes bytes = accessor_bytes(model, index, size, path);
  std::vector<uint32_t> out(bytes.count);
  for (size_t i = 0; i < bytes.count; ++i) out[i] = read_index_value(bytes.data + i * bytes.stride, size);
  return out;
}

// The textures of a material backlight reads, with their names for messages.
std::vector<std::pair<const char*, const tinygltf::TextureInfo*>> material_textures(const tinygltf::Material& gm) {
  std::vector<std::pair<const char*, const tinygltf::TextureInfo*>> used;
  if (gm.pbrMetallicRoughness.baseColorTexture.index >= 0)
    used.push_back({"base colour", &gm.pbrMetallicRoughness.baseColorTexture});
  if (gm.emissiveTexture.index >= 0) used.push_back({"emissive", &gm.emissiveTexture});
  if (gm.pbrMetallicRoughness.metallicRoughnessTexture.index >= 0)
    used.push_back({"metallic-roughness", &gm.pbrMetallicRoughness.metallicRoughnessTexture});
  return used;
}

// The uv set (TEXCOORD_n) a material's textures read. backlight meshes carry one uv set, so the
// base colour, emissive and metallic-roughness textures of one material must agree on it.
int material_tex_coord(const tinygltf::Model& model, int material, const std::string& path) {
  if (material < 0 || size_t(material) >= model.materials.size()) return 0;
  const auto& gm = model.materials[size_t(material)];
  const auto used = material_textures(gm);
  for (size_t i = 1; i < used.size(); ++i)
    if (used[i].second->texCoord != used[0].second->texCoord)
      throw file_error(path, "material '" + gm.name.substr(0, 100) + "': " + used[0].first + " and " + used[i].first +
                                 " textures use different uv sets (TEXCOORD_" +
                                 std::to_string(used[0].second->texCoord) + ", TEXCOORD_" +
                                 std::to_string(used[i].second->texCoord) + "); backlight meshes carry one");
  const int set = used.empty() ? 0 : used[0].second->texCoord;
  if (set < 0 || set > 7) throw file_error(path, "material '" + gm.name.substr(0, 100) + "': texCoord out of range");
  return set;
}

// KHR_texture_transform of a texture reference: uv' = T(offset) · R(rotation) · S(scale) · uv.
// Applied to the mesh's uvs at load, so the textures of one material must share it.
struct UvTransform {
  double offset[2] = {0, 0}, rotation = 0, scale[2] = {1, 1};
  bool operator==(const UvTransform& o) const {
    return offset[0] == o.offset[0] && offset[1] == o.offset[1] && rotation == o.rotation && scale[0] == o.scale[0] &&
           scale[1] == o.scale[1];
  }
};
UvTransform texture_transform(const tinygltf::ExtensionMap& ext, const std::string& where, const std::string& path) {
  UvTransform t;
  auto it = ext.find("KHR_texture_transform");
  if (it == ext.end()) return t;
  const tinygltf::Value& v = it->second;
  auto pair = [&](const char* key, double* out) {
    if (!v.Has(key)) return;
    const tinygltf::Value& a = v.Get(key);
    if (!a.IsArray() || a.ArrayLen() != 2 || !a.Get(0).IsNumber() || !a.Get(1).IsNumber())
      throw file_error(path, where + ": KHR_texture_transform " + key + " must be two numbers");
    out[0] = a.Get(0).GetNumberAsDouble(), out[1] = a.Get(1).GetNumberAsDouble();
  };
  pair("offset", t.offset);
  pair("scale", t.scale);
  if (v.Has("rotation")) {
    if (!v.Get("rotation").IsNumber())
      throw file_error(path, where + ": KHR_texture_transform rotation must be a number");
    t.rotation = v.Get("rotation").GetNumberAsDouble();
  }
  if (v.Has("texCoord")) throw file_error(path, where + ": KHR_texture_transform texCoord overrides are not supported");
  for (double d : {t.offset[0], t.offset[1], t.rotation, t.scale[0], t.scale[1]})
    if (!std::isfinite(d) || std::abs(d) > 1e6)
      throw file_error(path, where + ": KHR_texture_transform values must be finite and at most 1e6");
  return t;
}
void apply_texture_transform(const tinygltf::Model& model, int material, std::vector<float>& uv,
                             const std::string& path) {
  if (material < 0 || size_t(material) >= model.materials.size()) return;
  const auto& gm = model.materials[size_t(material)];
  const std::string where = "material '" + gm.name.substr(0, 100) + "'";
  const auto used = material_textures(gm);
  if (used.empty()) return;
  const UvTransform t = texture_transform(used[0].second->extensions, where, path);
  for (size_t i = 1; i < used.size(); ++i)
    if (!(texture_transform(used[i].second->extensions, where, path) == t))
      throw file_error(path, where + ": " + used[0].first + " and " + used[i].first +
                                 " textures have different KHR_texture_transforms");
  if (t == UvTransform{}) return;
  const double c = std::cos(t.rotation), s = std::sin(t.rotation);
  for (size_t i = 0; i + 1 < uv.size(); i += 2) {
    const double u = uv[i] * t.scale[0], v = uv[i + 1] * t.scale[1];
    // The extension's GLSL: rotation = mat3(cos, sin, 0, -sin, cos, 0, 0, 0, 1), column-major.
    uv[i] = float(c * u - s * v + t.offset[0]);
    uv[i + 1] = float(s * u + c * v + t.offset[1]);
  }
}

// COLOR_0 as linear RGB per vertex: VEC3 or VEC4 of floats or of normalized unsigned bytes/shorts,
// the types the specification allows. `rgb` is empty when every colour is white, so such a mesh
// costs and renders exactly like one without colours; alpha matters only to a material whose
// alphaMode is not OPAQUE, which needs its smallest value.
struct VertexColors {
  std::vector<Vec3f> rgb;
  float min_alpha = 1.f;
};
VertexColors read_vertex_colors(const tinygltf::Model& model, int index, const std::string& mesh,
                                const std::string& path) {
  if (index < 0 || size_t(index) >= model.accessors.size()) throw file_error(path, "accessor index out of range");
  const auto& acc = model.accessors[size_t(index)];
  const std::string what = "mesh '" + mesh.substr(0, 100) + "': COLOR_0 (accessor " + std::to_string(index) + ")";
  const int components = acc.type == TINYGLTF_TYPE_VEC3 ? 3 : acc.type == TINYGLTF_TYPE_VEC4 ? 4 : 0;
  const bool normalized_unsigned = acc.normalized && (acc.componentType == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                                                      acc.componentType == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT);
  if (!components || (acc.componentType != TINYGLTF_COMPONENT_TYPE_FLOAT && !normalized_unsigned))
    throw file_error(path, what + ": expected VEC3 or VEC4 of floats or normalized unsigned bytes or shorts");
  const std::vector<float> v = read_floats(model, index, components, path);
  VertexColors colors;
  bool white = true;
  for (size_t i = 0; i + size_t(components) <= v.size(); i += size_t(components)) {
    for (int k = 0; k < components; ++k)
      if (!(v[i + size_t(k)] >= 0.f && v[i + size_t(k)] <= 1.f))
        throw file_error(path, what + ": colour values must be in [0, 1]");
    const Vec3f c(v[i], v[i + 1], v[i + 2]);
    white = white && c.x == 1.f && c.y == 1.f && c.z == 1.f;
    colors.rgb.push_back(c);
    if (components == 4) colors.min_alpha = std::min(colors.min_alpha, v[i + 3]);
  }
  if (white) colors.rgb.clear();
  return colors;
}

struct Primitive {
  Mesh mesh;  // world space, unpadded
  int material = -1;
  std::string name;
  std::string where;             // "mesh 'name' primitive k", for messages
  float min_vertex_alpha = 1.f;  // COLOR_0's smallest alpha
};

// The element count of accessor `index` (0 when the index is invalid: reading it reports that).
uint64_t accessor_count(const tinygltf::Model& model, int index) {
  return index >= 0 && size_t(index) < model.accessors.size() ? uint64_t(model.accessors[size_t(index)].count) : 0;
}

// The component types the specification allows for POSITION, NORMAL and TEXCOORD_n: floats, and
// normalized unsigned bytes and shorts for texture coordinates; KHR_mesh_quantization adds
// integer positions and uvs and normalized integer normals. Any other type would be decoded as
// raw integers, e.g. positions in units of 1/65535 read as thousands.
void check_attribute_type(const tinygltf::Model& model, const std::string& attribute, int index, bool quantized,
                          const std::string& mesh, const std::string& path) {
  if (index < 0 || size_t(index) >= model.accessors.size()) return;  // read_floats reports it
  const auto& acc = model.accessors[size_t(index)];
  const int type = acc.componentType;
  if (type == TINYGLTF_COMPONENT_TYPE_FLOAT) return;
  const bool integer = type == TINYGLTF_COMPONENT_TYPE_BYTE || type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                       type == TINYGLTF_COMPONENT_TYPE_SHORT || type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT;
  const bool signed_type = type == TINYGLTF_COMPONENT_TYPE_BYTE || type == TINYGLTF_COMPONENT_TYPE_SHORT;
  bool core = false, extension = false;
  if (attribute == "POSITION") {
    extension = integer;
  } else if (attribute == "NORMAL") {
    extension = signed_type && acc.normalized;
  } else {  // TEXCOORD_n
    core = integer && !signed_type && acc.normalized;
    extension = integer;
  }
  if (core || (quantized && extension)) return;
  throw file_error(path, "mesh '" + mesh.substr(0, 100) + "': " + attribute + " (accessor " + std::to_string(index) +
                             "): component type " + component_type_name(type) +
                             (acc.normalized ? " (normalized)" : "") +
                             (extension ? " needs the KHR_mesh_quantization extension" : " is not allowed"));
}

// The triangles of a primitive of mode TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN, as a list. A
// strip's odd triangles swap their last two vertices so that every triangle keeps the winding of
// the first (the specification's p_i = {v_i, v_(i+1+i%2), v_(i+2-i%2)}); a fan's triangles share
// its first vertex.
std::vector<uint32_t> triangle_list(int mode, const std::vector<uint32_t>& v) {
  if (mode == TINYGLTF_MODE_TRIANGLES) return v;
  std::vector<uint32_t> out;
  for (size_t i = 0; i + 2 < v.size(); ++i) {
    if (mode == TINYGLTF_MODE_TRIANGLE_FAN)
      out.insert(out.end(), {v[0], v[i + 1], v[i + 2]});
    else if (i % 2 == 0)
      out.insert(out.end(), {v[i], v[i + 1], v[i + 2]});
    else
      out.insert(out.end(), {v[i], v[i + 2], v[i + 1]});
  }
  return out;
}

// Every triangle primitive (triangles, strips and fans) of the default scene in world space, as
// triangle lists; points and lines have no surface and are skipped, with one warning for the
// file added to `warnings`. Vertex colours (COLOR_0), and the uv set the material's textures
// need, only when `file_materials` (they belong to the file's materials, which a JSON scene's
// glTF shape does not use).
std::vector<Primitive> collect_primitives(const tinygltf::Model& model, const std::string& path,
                                          const Transform& to_world, std::vector<std::pair<Transform, int>>* cameras,
                                          bool file_materials, std::vector<std::string>& warnings) {
  std::vector<Primitive> out;
  const auto uses = [&](const char* extension) {
    const auto& used = model.extensionsUsed;
    const auto& required = model.extensionsRequired;
    return std::find(used.begin(), used.end(), extension) != used.end() ||
           std::find(required.begin(), required.end(), extension) != required.end();
  };
  const bool quantized = uses("KHR_mesh_quantization");
  // Point and line primitives, each counted once however often its mesh is instanced.
  std::set<std::pair<int, size_t>> unrendered;
  std::string first_unrendered;
  // Meshes under a node scaled to 0 (a common way to hide an object): nothing of them is drawn.
  size_t hidden_meshes = 0;
  std::string first_hidden;
  // Totals over every instance, counted in a first pass that reads nothing: one mesh under
  // thousands of nodes, or one accessor in thousands of primitives, costs its size every time.
  uint64_t total_vertices = 0, total_indices = 0, total_shapes = 0;
  bool counting = true;
  std::function<void(int, const Transform&, int)> visit = [&](int ni, const Transform& parent, int depth) {
    if (ni < 0 || size_t(ni) >= model.nodes.size()) throw file_error(path, "invalid node hierarchy");
    if (depth > limits::kNodeDepth)
      throw file_error(path, "invalid node hierarchy: nesting exceeds the limit of " +
                                 std::to_string(limits::kNodeDepth) + " levels (or a cycle)");
    const auto& node = model.nodes[size_t(ni)];
    const std::string node_name =
        "node " + std::to_string(ni) + (node.name.empty() ? "" : " ('" + node.name.substr(0, 100) + "')");
    // Skinned vertices are placed by their joints, not by the node: drawn unskinned they would
    // stand in their bind pose wherever the node is.
    if (node.skin >= 0) throw file_error(path, node_name + ": skins (skeletal animation) are not supported");
    Transform world = parent * node_local(node, ni, path);
    const double det = linear_determinant(world);
    if (node.camera >= 0 && cameras && !counting) cameras->push_back({world, node.camera});
    if (node.mesh >= 0 && size_t(node.mesh) >= model.meshes.size())
      throw file_error(path, "node references a missing mesh");
    // A node scaled to 0 (a common way to hide an object) draws nothing. One that flattens its
    // mesh (determinant 0, rank 2) is skipped too: its normals are undefined.
    const bool hidden = node.mesh >= 0 && det == 0;
    if (hidden && !counting && hidden_meshes++ == 0) {
      const std::string& mesh = model.meshes[size_t(node.mesh)].name;
      first_hidden = node_name + ": its world transform scales to 0 (determinant 0), so its mesh '" +
                     (mesh.empty() ? "mesh" + std::to_string(node.mesh) : mesh.substr(0, 100)) + "' is not rendered";
    }
    if (node.mesh >= 0 && !hidden) {
      const auto& gm = model.meshes[size_t(node.mesh)];
      for (size_t pi = 0; pi < gm.primitives.size(); ++pi) {
        const auto& prim = gm.primitives[pi];
        const std::string where = "mesh '" +
                                  (gm.name.empty() ? "mesh" + std::to_string(node.mesh) : gm.name.substr(0, 100)) +
                                  "' primitive " + std::to_string(pi);
        const int mode = prim.mode == -1 ? TINYGLTF_MODE_TRIANGLES : prim.mode;  // -1: absent
        if (mode < TINYGLTF_MODE_POINTS || mode > TINYGLTF_MODE_TRIANGLE_FAN)
          throw file_error(path, where + ": invalid mode " + std::to_string(prim.mode) + " (expected 0 to 6)");
        if (mode < TINYGLTF_MODE_TRIANGLES) {
          if (unrendered.insert({node.mesh, pi}).second && first_unrendered.empty()) first_unrendered = where;
          continue;
        }
        if (prim.material < -1)
          throw file_error(path, where + ": material " + std::to_string(prim.material) + " is out of range");
        auto pos_it = prim.attributes.find("POSITION");
        if (pos_it == prim.attributes.end()) throw file_error(path, "primitive without POSITION");
        // Morph targets move the vertices by Σ weight_k · target_k, with the node's weights, else
        // the mesh's, else 0. backlight does not apply them: it reads a primitive only where
        // they move nothing.
        if (!prim.targets.empty()) {
          const bool own = !node.weights.empty();
          const std::vector<double>& weights = own ? node.weights : gm.weights;
          const std::string whose = own ? node_name + " weights" : "mesh weights";
          if (!weights.empty() && weights.size() != prim.targets.size())
            throw file_error(path, where + ": " + std::to_string(weights.size()) + " " + whose + " for " +
                                       std::to_string(prim.targets.size()) + " morph targets");
          for (const double w : weights)
            if (w != 0)
              throw file_error(path,
                               where + ": morph targets with weights other than 0 (" + whose + ") are not supported");
        }
        if (counting) {
          const uint64_t vertices = accessor_count(model, pos_it->second);
          const uint64_t corners = prim.indices >= 0 ? accessor_count(model, prim.indices) : vertices;
          limits::add_to_total(path, "mesh instance count", total_shapes, 1, limits::kShapes);
          limits::add_to_total(path, "total vertex count (all mesh instances)", total_vertices, vertices,
                               limits::kSceneElements);
          limits::add_to_total(path, "total triangle count (all mesh instances)", total_indices,
                               mode == TINYGLTF_MODE_TRIANGLES ? corners / 3
                               : corners < 3                   ? 0
                                                               : corners - 2,
                               limits::kSceneElements);
          continue;
        }
        Primitive p;
        for (const auto& [attribute, index] : prim.attributes)
          if (attribute == "POSITION" || attribute == "NORMAL" || attribute.rfind("TEXCOORD_", 0) == 0)
            check_attribute_type(model, attribute, index, quantized, gm.name, path);
        std::vector<float> pos = read_floats(model, pos_it->second, 3, path);
        for (size_t i = 0; i + 2 < pos.size(); i += 3)
          p.mesh.positions.push_back(world.point({pos[i], pos[i + 1], pos[i + 2]}));
        if (auto it = prim.attributes.find("NORMAL"); it != prim.attributes.end()) {
          std::vector<float> nrm = read_floats(model, it->second, 3, path);
          for (size_t i = 0; i + 2 < nrm.size(); i += 3)
            p.mesh.normals.push_back(world.normal({nrm[i], nrm[i + 1], nrm[i + 2]}));
        }
        const std::string uv_set = "TEXCOORD_" + std::to_string(material_tex_coord(model, prim.material, path));
        if (auto it = prim.attributes.find(uv_set); it != prim.attributes.end()) {
          std::vector<float> uv = read_floats(model, it->second, 2, path);
          apply_texture_transform(model, prim.material, uv, path);
          for (size_t i = 0; i + 1 < uv.size(); i += 2) p.mesh.uvs.push_back({uv[i], uv[i + 1]});
        } else if (file_materials && prim.material >= 0 && size_t(prim.material) < model.materials.size() &&
                   !material_textures(model.materials[size_t(prim.material)]).empty()) {
          // Without its uv set the material's textures would be sampled at one point.
          throw file_error(path, where + ": its material's textures read " + uv_set + ", which it does not have");
        }
        if (auto it = prim.attributes.find("COLOR_0"); file_materials && it != prim.attributes.end()) {
          VertexColors colors = read_vertex_colors(model, it->second, gm.name, path);
          p.mesh.colors = std::move(colors.rgb);
          p.min_vertex_alpha = colors.min_alpha;
        }
        std::vector<uint32_t> corners;
        if (prim.indices >= 0) {
          corners = read_indices(model, prim.indices, where, path);
        } else {
          for (uint32_t i = 0; i < p.mesh.positions.size(); ++i) corners.push_back(i);
        }
        if (mode == TINYGLTF_MODE_TRIANGLES && corners.size() % 3 != 0)
          throw file_error(
              path,
              where + ": " +
                  (prim.indices >= 0 ? "indices (accessor " + std::to_string(prim.indices) + ")"
                                     : "POSITION (accessor " + std::to_string(pos_it->second) + ") without indices") +
                  ": count " + std::to_string(corners.size()) + " is not a multiple of 3 (mode TRIANGLES)");
        p.mesh.indices = triangle_list(mode, corners);
        if ((!p.mesh.normals.empty() && p.mesh.normals.size() != p.mesh.positions.size()) ||
            (!p.mesh.uvs.empty() && p.mesh.uvs.size() != p.mesh.positions.size()) ||
            (!p.mesh.colors.empty() && p.mesh.colors.size() != p.mesh.positions.size()))
          throw file_error(path, "attribute counts disagree in mesh '" + gm.name + "'");
        for (uint32_t i : p.mesh.indices)
          if (i >= p.mesh.positions.size())
            throw file_error(path, "triangle index out of range in mesh '" + gm.name + "'");
        // glTF winding is counter-clockwise seen from the front, i.e. (p1−p0)×(p2−p0) is the front
        // normal; a mirroring node transform reverses it.
        if (det < 0)
          for (size_t t = 0; t + 2 < p.mesh.indices.size(); t += 3)
            std::swap(p.mesh.indices[t + 1], p.mesh.indices[t + 2]);
        p.material = prim.material;
        p.where = where;
        p.name = (gm.name.empty() ? "mesh" + std::to_string(node.mesh) : gm.name) +
                 (gm.primitives.size() > 1 ? "_" + std::to_string(pi) : "");
        out.push_back(std::move(p));
      }
    }
    for (int c : node.children) visit(c, world, depth + 1);
  };
  if (model.nodes.empty()) return out;
  // glTF node graphs are forests: a node with two parents (a DAG) would be visited once per path
  // to it, 2^depth times in the worst case, so it is rejected before any traversal.
  std::vector<int> parent(model.nodes.size(), -1);
  for (size_t n = 0; n < model.nodes.size(); ++n)
    for (int c : model.nodes[n].children) {
      if (c < 0 || size_t(c) >= model.nodes.size())
        throw file_error(path, "invalid node hierarchy (child out of range)");
      if (parent[size_t(c)] >= 0 || size_t(c) == n)
        throw file_error(path, "invalid node hierarchy: node " + std::to_string(c) +
                                   " has more than one parent (glTF requires a tree)");
      parent[size_t(c)] = int(n);
    }
  int scene_index = model.defaultScene >= 0 ? model.defaultScene : 0;
  std::vector<int> roots;
  if (!model.scenes.empty()) {
    if (size_t(scene_index) >= model.scenes.size()) throw file_error(path, "default scene out of range");
    roots = model.scenes[size_t(scene_index)].nodes;
  } else {
    for (size_t n = 0; n < model.nodes.size(); ++n)
      if (parent[n] < 0) roots.push_back(int(n));
  }
  std::set<int> seen_roots;
  for (int n : roots) {
    if (n < 0 || size_t(n) >= model.nodes.size()) throw file_error(path, "invalid node hierarchy (root out of range)");
    if (parent[size_t(n)] >= 0 || !seen_roots.insert(n).second)
      throw file_error(path,
                       "invalid node hierarchy: root node " + std::to_string(n) + " has a parent or is listed twice");
  }
  // With one parent per node, the depth limit in `visit` also catches cycles.
  for (int n : roots) visit(n, to_world, 0);
  counting = false;
  for (int n : roots) visit(n, to_world, 0);
  if (!unrendered.empty())
    warnings.push_back("backlight: " + path + ": warning: " + first_unrendered + ": points/lines are not rendered" +
                       (unrendered.size() > 1
                            ? " (nor are " + std::to_string(unrendered.size() - 1) + " more point/line primitives)"
                            : ""));
  if (hidden_meshes)
    warnings.push_back("backlight: " + path + ": warning: " + first_hidden +
                       (hidden_meshes > 1
                            ? " (nor are the meshes of " + std::to_string(hidden_meshes - 1) + " more such nodes)"
                            : ""));
  return out;
}

// Names made unique with a suffix "_2", "_3", ...: the first free one, found in amortised constant
// time per name (a file can instance one mesh 10^6 times; probing from "_2" each time was
// quadratic).
class UniqueNames {
 public:
  std::string make(const std::string& base) {
    std::string n = base;
    if (used_.count(n)) {
      int& k = next_.try_emplace(base, 2).first->second;
      for (;; ++k) {
        n.assign(base).append("_").append(std::to_string(k));
        if (!used_.count(n)) break;
      }
      ++k;
    }
    used_.insert(n);
    return n;
  }

 private:
  std::set<std::string> used_;
  std::map<std::string, int> next_;
};

std::string sanitize(std::string name) {
  for (auto& c : name)
    if (c == '.' || c == ' ' || c == '=' || c == '/' || c == '\\' || static_cast<unsigned char>(c) < 0x20 || c == 0x7f)
      c = '_';  // names become file names (and one-line messages)
  return name;
}

}  // namespace

std::vector<Mesh> load_gltf_meshes_unguarded(const std::string& path, const Transform& to_world,
                                             std::vector<std::string>& warnings);
std::unique_ptr<Scene> load_gltf_scene_unguarded(const std::string& path, std::vector<std::string>& warnings);

// Every index in the file is checked where it is used; `.at()` backs that up, and an index that
// still slips through becomes this one-line error instead of an internal one.
template <class F>
auto guarded(const std::string& path, F&& load) {
  try {
    return load();
  } catch (const std::out_of_range&) {
    throw file_error(path, "invalid glTF: an index (texture, image, sampler, camera or buffer) is out of range");
  }
}

std::vector<Mesh> load_gltf_meshes(const std::string& path, const Transform& to_world,
                                   std::vector<std::string>& warnings) {
  return guarded(path, [&] { return load_gltf_meshes_unguarded(path, to_world, warnings); });
}

// Warnings are printed once the file has loaded, so that a file that fails gets its one error
// line only (as load_xml_scene does).
std::vector<Mesh> load_gltf_meshes(const std::string& path, const Transform& to_world) {
  std::vector<std::string> warnings;
  std::vector<Mesh> meshes = load_gltf_meshes(path, to_world, warnings);
  for (const std::string& w : warnings) std::fprintf(stderr, "%s\n", w.c_str());
  return meshes;
}

std::unique_ptr<Scene> load_gltf_scene(const std::string& path) {
  std::vector<std::string> warnings;
  std::unique_ptr<Scene> scene = guarded(path, [&] { return load_gltf_scene_unguarded(path, warnings); });
  for (const std::string& w : warnings) std::fprintf(stderr, "%s\n", w.c_str());
  return scene;
}

std::vector<Mesh> load_gltf_meshes_unguarded(const std::string& path, const Transform& to_world,
                                             std::vector<std::string>& warnings) {
  tinygltf::Model model = read_model(path);
  std::vector<Mesh> meshes;
  for (auto& p : collect_primitives(model, path, to_world, nullptr, false, warnings))
    meshes.push_back(std::move(p.mesh));
  return meshes;
}

std::unique_ptr<Scene> load_gltf_scene_unguarded(const std::string& path, std::vector<std::string>& warnings) {
  tinygltf::Model model = read_model(path);
  auto scene = std::make_unique<Scene>();
  scene->source = path;
  std::vector<std::pair<Transform, int>> cameras;
  std::vector<Primitive> prims = collect_primitives(model, path, Transform(), &cameras, true, warnings);
  if (prims.empty()) throw file_error(path, "no triangle meshes in the default scene");
  // Each material used gets its own copy of its base colour texture (3 floats per texel): many
  // materials naming one small, highly compressed image must not add up past the limit, so the
  // total is counted from the decoded sizes before any parameter is built.
  {
    uint64_t planned = 0;
    std::set<int> counted;
    for (const auto& p : prims) {
      if (p.material < 0 || size_t(p.material) >= model.materials.size() || !counted.insert(p.material).second)
        continue;
      const auto& gm = model.materials[size_t(p.material)];
      for (const int t : {gm.pbrMetallicRoughness.baseColorTexture.index, gm.emissiveTexture.index,
                          gm.pbrMetallicRoughness.metallicRoughnessTexture.index}) {
        if (t < 0 || size_t(t) >= model.textures.size()) continue;
        const int src = model.textures[size_t(t)].source;
        if (src < 0 || size_t(src) >= model.images.size()) continue;
        const auto& img = model.images[size_t(src)];
        limits::add_to_total(
            path, "total parameter size (texels of every material's textures)", planned,
            limits::checked_product(path, "texture size",
                                    {uint64_t(std::max(0, img.width)), uint64_t(std::max(0, img.height)), 3},
                                    limits::kParamValues),
            limits::kParamValues);
      }
    }
  }

  // Materials, created on first use; names come from the file (made unique and '.'-free).
  std::map<int, int> material_of;
  UniqueNames material_names;
  auto unique = [&](const std::string& n) { return material_names.make(sanitize(n)); };
  auto add_param = [&](const std::string& name, std::vector<int> shape, std::vector<float> value, float lo, float hi) {
    Param p;
    p.name = name;
    p.shape = std::move(shape);
    p.value = std::move(value);
    p.lower = lo;
    p.upper = hi;
    validate_param(p, path);
    TextureSlot s;
    s.param = scene->params.add(std::move(p), path);
    return s;
  };
  // A texture's decoded 8- or 16-bit RGB(A) image, checked, and its wrap mode. `owner` names what
  // refers to a missing texture, `what` the image in the other errors.
  struct TextureImage {
    const tinygltf::Image* img;
    Wrap wrap;
  };
  auto texture_image = [&](int texture, const std::string& owner, const std::string& what) {
    if (size_t(texture) >= model.textures.size()) throw file_error(path, owner + " references a missing texture");
    const auto& tex = model.textures[size_t(texture)];
    if (tex.source < 0 || size_t(tex.source) >= model.images.size())
      throw file_error(path, "texture " + std::to_string(texture) + " references a missing image");
    const auto& img = model.images[size_t(tex.source)];
    // tinygltf keeps the uri of an external image only, and only warns when it cannot read one.
    const std::string image =
        "image " + std::to_string(tex.source) + (img.uri.empty() ? std::string() : " '" + img.uri.substr(0, 200) + "'");
    if (img.image.empty() && !img.uri.empty())
      throw file_error(path, what + ": " + image + ": file not found or unreadable");
    if (img.image.empty() || img.width <= 0 || img.height <= 0 || img.component < 3 ||
        (img.bits != 8 && img.bits != 16))
      throw file_error(path, what + ": " + image + " could not be decoded as 8- or 16-bit RGB(A)");
    limits::check_image_size(path + ": image " + std::to_string(tex.source), uint64_t(img.width), uint64_t(img.height));
    if (img.image.size() < size_t(img.width) * size_t(img.height) * size_t(img.component) * size_t(img.bits / 8))
      throw file_error(path, "image " + std::to_string(tex.source) + " holds fewer pixels than its size");
    if (tex.sampler >= 0 && size_t(tex.sampler) >= model.samplers.size())
      throw file_error(path, "texture references a missing sampler");
    const int wrap = tex.sampler >= 0 ? model.samplers[size_t(tex.sampler)].wrapS : 10497;
    if (tex.sampler >= 0) {
      const auto& sampler = model.samplers[size_t(tex.sampler)];
      if (sampler.magFilter == TINYGLTF_TEXTURE_FILTER_NEAREST)
        throw file_error(path, "sampler " + std::to_string(tex.sampler) +
                                   ": magFilter 9728 (NEAREST) is not supported (bitmap textures are bilinear)");
      for (const int w : {sampler.wrapS, sampler.wrapT})
        if (w != 33071 && w != 33648 && w != 10497)
          throw file_error(path, "sampler " + std::to_string(tex.sampler) + ": wrap mode " + std::to_string(w) +
                                     " is not one of 33071 (clamp), 33648 (mirrored repeat) and 10497 (repeat)");
      // A bitmap parameter has one wrap mode for both axes (wrapT was ignored before).
      if (sampler.wrapS != sampler.wrapT)
        throw file_error(path, "sampler " + std::to_string(tex.sampler) + ": wrapS " + std::to_string(sampler.wrapS) +
                                   " and wrapT " + std::to_string(sampler.wrapT) +
                                   " differ (one wrap mode for both axes is supported)");
    }
    return TextureImage{&img, wrap == 33071 ? Wrap::Clamp : wrap == 33648 ? Wrap::Mirror : Wrap::Repeat};
  };
  // An sRGB glTF texture as a bitmap parameter: linear texels × `factor`, at most `upper`.
  auto texture_param = [&](int texture, const std::vector<float>& factor, float upper, const std::string& name,
                           const std::string& what) {
    const TextureImage t = texture_image(texture, name + ":", what);
    const auto& img = *t.img;
    std::vector<float> v(size_t(img.width) * size_t(img.height) * 3);
    for (size_t i = 0; i < size_t(img.width) * size_t(img.height); ++i)
      for (int c = 0; c < 3; ++c)
        v[i * 3 + size_t(c)] = std::min(upper, srgb_to_linear(texel(img, i, c)) * factor[size_t(c)]);
    TextureSlot slot = add_param(name, {img.height, img.width, 3}, std::move(v), 0.f, upper);
    slot.bitmap = true;
    slot.wrap = t.wrap;
    return slot;
  };
  // A linear glTF texture's channel `channel`, f(texel in [0, 1]) per texel, for a
  // one-channel bitmap parameter (metallicRoughnessTexture: roughness in G, metallic in B).
  struct ChannelMap {
    int height = 0, width = 0;
    std::vector<float> values;
    Wrap wrap = Wrap::Repeat;
  };
  auto read_channel = [&](int texture, int channel, const std::function<float(float)>& f, const std::string& what) {
    const TextureImage t = texture_image(texture, what, what);
    const auto& img = *t.img;
    ChannelMap map;
    map.height = img.height, map.width = img.width;
    map.values.resize(size_t(img.width) * size_t(img.height));
    for (size_t i = 0; i < map.values.size(); ++i) map.values[i] = f(texel(img, i, channel));
    map.wrap = t.wrap;
    return map;
  };
  auto channel_param = [&](ChannelMap map, const std::string& name, float upper) {
    for (float& v : map.values) v = std::min(v, upper);
    TextureSlot slot = add_param(name, {map.height, map.width, 1}, std::move(map.values), 0.f, upper);
    scene->params[slot.param].srgb = false;  // a linear texture's channel
    slot.bitmap = true;
    slot.wrap = map.wrap;
    return slot;
  };
  auto material_for = [&](int gi) {
    if (auto it = material_of.find(gi); it != material_of.end()) return it->second;
    Material m;
    tinygltf::Material gm;
    if (gi >= 0) {
      if (size_t(gi) >= model.materials.size()) throw file_error(path, "primitive references a missing material");
      gm = model.materials[size_t(gi)];
    }
    m.name = unique(gm.name.empty() ? "material" + std::to_string(gi < 0 ? 0 : gi) : gm.name);
    m.two_sided = true;  // glTF's doubleSided=false is a culling hint; shading stays two-sided
    const auto& pbr = gm.pbrMetallicRoughness;
    if (!(pbr.roughnessFactor >= 0 && pbr.roughnessFactor <= 1) ||
        !(pbr.metallicFactor >= 0 && pbr.metallicFactor <= 1))
      throw file_error(path, "material '" + gm.name + "': roughnessFactor and metallicFactor must be in [0, 1]");
    if (pbr.baseColorFactor.size() < 3)
      throw file_error(path, "material '" + gm.name + "': baseColorFactor needs 4 values");
    std::vector<float> base(pbr.baseColorFactor.begin(), pbr.baseColorFactor.begin() + 3);
    // Metallic 0 and 1 are the pure lobes (and keep their parameter names); anything between is
    // the specification's blend of the two. A metallicRoughnessTexture (linear; roughness in G,
    // metallic in B, each times its factor) makes both bitmaps, and the blend unless its metallic
    // texels are all 0 or all 1.
    const int mr_texture = pbr.metallicRoughnessTexture.index;
    const float metallic_factor = float(pbr.metallicFactor), roughness_factor = float(pbr.roughnessFactor);
    ChannelMap metallic_map;
    bool all_zero = metallic_factor == 0.f, all_one = metallic_factor == 1.f;
    if (mr_texture >= 0) {
      metallic_map = read_channel(
          mr_texture, 2, [&](float b) { return b * metallic_factor; },
          "material '" + gm.name.substr(0, 100) + "': metallic-roughness texture");
      const auto& v = metallic_map.values;
      all_zero = std::all_of(v.begin(), v.end(), [](float x) { return x == 0.f; });
      all_one = std::all_of(v.begin(), v.end(), [](float x) { return x == 1.f; });
    }
    m.type = all_zero ? BsdfType::RoughPlastic : all_one ? BsdfType::RoughConductor : BsdfType::MetallicRoughness;
    if (mr_texture >= 0) {
      // GGX α = (perceptual roughness)² per texel.
      m.roughness =
          channel_param(read_channel(
                            mr_texture, 1, [&](float g) { return (g * roughness_factor) * (g * roughness_factor); },
                            "material '" + gm.name.substr(0, 100) + "': metallic-roughness texture"),
                        m.name + ".roughness", 4.f);
    } else {
      const float alpha = roughness_factor * roughness_factor;
      m.roughness = add_param(m.name + ".roughness", {1}, {alpha}, 0.f, 4.f);
    }
    if (m.type == BsdfType::MetallicRoughness)
      m.metallic = mr_texture >= 0 ? channel_param(std::move(metallic_map), m.name + ".metallic", 1.f)
                                   : add_param(m.name + ".metallic", {1}, {metallic_factor}, 0.f, 1.f);
    TextureSlot color;
    const std::string key = m.type == BsdfType::RoughConductor ? ".specular"
                            : m.type == BsdfType::RoughPlastic ? ".albedo"
                                                               : ".base_color";
    if (pbr.baseColorTexture.index >= 0) {
      color = texture_param(pbr.baseColorTexture.index, base, 1.f, m.name + key, "base colour texture");
    } else {
      color = add_param(m.name + key, {3}, base, 0.f, 1.f);
    }
    (m.type == BsdfType::RoughConductor ? m.specular : m.albedo) = color;
    scene->materials.push_back(std::move(m));
    return material_of[gi] = int(scene->materials.size() - 1);
  };

  // glTF's alphaMode: OPAQUE ignores alpha, MASK draws only where alpha ≥ alphaCutoff and BLEND
  // composites by alpha. backlight's surfaces are opaque, so MASK and BLEND are read only where
  // they draw exactly that: alpha = baseColorFactor[3] × base-colour texture alpha × COLOR_0 alpha
  // is 1 everywhere for BLEND, ≥ alphaCutoff everywhere for MASK. The product of the three minima
  // is a lower bound of alpha: a cut-out it cannot rule out is refused.
  std::map<int, float> texture_min_alpha;
  auto check_alpha = [&](const Primitive& p) {
    const auto& gm = model.materials[size_t(p.material)];
    if (gm.alphaMode == "OPAQUE") return;
    const auto& pbr = gm.pbrMetallicRoughness;
    const double factor = pbr.baseColorFactor.size() > 3 ? pbr.baseColorFactor[3] : 1.0;
    float texture = 1.f;
    if (const int t = pbr.baseColorTexture.index; t >= 0) {
      auto it = texture_min_alpha.find(t);
      if (it == texture_min_alpha.end()) {
        const tinygltf::Image& img = *texture_image(t, "base colour texture", "base colour texture").img;
        float lowest = 1.f;
        if (img.component == 4)
          for (size_t i = 0; i < size_t(img.width) * size_t(img.height); ++i)
            lowest = std::min(lowest, texel(img, i, 3));
        it = texture_min_alpha.emplace(t, lowest).first;
      }
      texture = it->second;
    }
    const double alpha = factor * texture * p.min_vertex_alpha;
    const bool mask = gm.alphaMode == "MASK";
    if (mask ? alpha >= gm.alphaCutoff : alpha == 1.0) return;
    std::string sources;
    auto source = [&](double value, const std::string& name) {
      if (value < 1) sources += (sources.empty() ? "" : ", ") + name + number_text(value);
    };
    source(factor, "baseColorFactor alpha ");
    source(texture, "base colour texture alpha down to ");
    source(p.min_vertex_alpha, "COLOR_0 alpha down to ");
    throw file_error(
        path,
        p.where + ": material '" + gm.name.substr(0, 100) + "': alphaMode " + gm.alphaMode +
            (mask ? " cuts out where alpha < alphaCutoff " + number_text(gm.alphaCutoff) : " blends where alpha < 1") +
            ", and alpha here goes down to " + number_text(alpha) + (sources.empty() ? "" : " (" + sources + ")") +
            ": backlight's surfaces are opaque (make the material OPAQUE, or its alpha 1)");
  };
  for (const auto& p : prims)
    if (p.material >= 0 && size_t(p.material) < model.materials.size()) check_alpha(p);

  // A normal map or an occlusion map changes shading without changing what is drawn: both are
  // ignored, with one warning for the file naming the first material that has them.
  {
    std::set<int> seen;
    std::string first;
    size_t more = 0;
    for (const auto& p : prims) {
      if (p.material < 0 || size_t(p.material) >= model.materials.size() || !seen.insert(p.material).second) continue;
      const auto& gm = model.materials[size_t(p.material)];
      const bool normal = gm.normalTexture.index >= 0, occlusion = gm.occlusionTexture.index >= 0;
      if (!normal && !occlusion) continue;
      if (!first.empty()) {
        ++more;
        continue;
      }
      first = "material '" + gm.name.substr(0, 100) +
              "': " + (normal ? "normalTexture (shading uses the mesh's normals)" : "") +
              (normal && occlusion ? " and " : "") +
              (occlusion ? "occlusionTexture (path tracing computes occlusion itself)" : "") +
              (normal && occlusion ? " are" : " is") + " ignored";
    }
    if (!first.empty())
      warnings.push_back("backlight: " + path + ": warning: " + first +
                         (more ? " (so are those of " + std::to_string(more) + " more materials)" : ""));
  }

  UniqueNames shape_names;
  std::map<int, TextureSlot> emission_of;  // glTF material → its emissive texture parameter
  for (auto& p : prims) {
    Mesh mesh = std::move(p.mesh);
    mesh.name = shape_names.make(sanitize(p.name));
    mesh.material = material_for(p.material);
    finalize_mesh(mesh, Transform(), false, path + ": mesh '" + mesh.name + "'");
    if (p.material >= 0) {
      const auto& gm = model.materials[size_t(p.material)];
      double strength = 1.0;
      if (auto it = gm.extensions.find("KHR_materials_emissive_strength");
          it != gm.extensions.end() && it->second.Has("emissiveStrength")) {
        const tinygltf::Value& v = it->second.Get("emissiveStrength");
        // GetNumberAsDouble reads a string or an object as 0, which would turn the light off.
        strength = v.IsNumber() ? v.GetNumberAsDouble() : -1.0;
        if (!(strength >= 0 && std::isfinite(strength)))
          throw file_error(path, "material '" + gm.name.substr(0, 100) +
                                     "': KHR_materials_emissive_strength emissiveStrength must be a number ≥ 0");
      }
      std::vector<float> e;
      for (size_t c = 0; c < 3 && c < gm.emissiveFactor.size(); ++c)
        e.push_back(float(gm.emissiveFactor[c] * strength));
      if (e.size() == 3 && (e[0] > 0 || e[1] > 0 || e[2] > 0)) {
        AreaEmitter em;
        em.mesh = int(scene->meshes.size());
        // emissiveTexture (sRGB) × emissiveFactor × strength is one bitmap parameter per material,
        // `<material>.emission`, shared by its shapes; constant emission is per shape.
        if (gm.emissiveTexture.index >= 0) {
          auto it = emission_of.find(p.material);
          if (it == emission_of.end()) {
            const std::string material_name = scene->materials[size_t(mesh.material)].name;
            it = emission_of
                     .emplace(p.material, texture_param(gm.emissiveTexture.index, e, 1e30f, material_name + ".emission",
                                                        "emissive texture"))
                     .first;
          }
          em.radiance = it->second;
        } else {
          em.radiance = add_param(mesh.name + ".radiance", {3}, e, 0.f, 1e30f);
        }
        mesh.emitter = int(scene->area_emitters.size());
        scene->area_emitters.push_back(std::move(em));
      }
    }
    scene->meshes.push_back(std::move(mesh));
  }

  // glTF clips at view-space depth zfar when one is given (else the projection is infinite), and
  // backlight's camera rays are not clipped. As for Mitsuba's far_clip (scene_xml.cpp), a zfar
  // that nothing reaches cannot change the image and is ignored; one that clips a shape is
  // refused. The view space is the camera node's world transform M inverted: a point p lies at
  // depth −((c0 × c1) · (p − o)) / det M, with c0, c1 the first two columns of M's linear part and
  // o its translation.
  auto check_zfar = [&](const tinygltf::PerspectiveCamera& pc, const Transform& xf, double det,
                        const std::string& what) {
    if (pc.zfar <= 0) return;  // absent (an explicit value ≤ 0 is refused in the JSON)
    if (!(pc.zfar > pc.znear)) throw file_error(path, what + ": zfar must exceed znear");
    const Vec3d c0(xf.m[0][0], xf.m[1][0], xf.m[2][0]), c1(xf.m[0][1], xf.m[1][1], xf.m[2][1]);
    const Vec3d back = cross(c0, c1) * (1.0 / det), origin(xf.m[0][3], xf.m[1][3], xf.m[2][3]);
    for (const Mesh& m : scene->meshes)
      for (size_t v = 0; v < m.vertex_count(); ++v) {
        const double depth = -dot(back, Vec3d(m.positions[v]) - origin);
        if (depth > pc.zfar)
          throw file_error(path, what + ": zfar " + number_text(pc.zfar) + " clips shape '" + m.name + "' (at depth " +
                                     number_text(depth) +
                                     ") (camera rays are not clipped here: give a zfar beyond the scene, or none)");
      }
  };

  // Cameras: every camera of the default scene (perspective: others are refused), else one
  // framing the bounding box.
  for (auto& [xf, ci] : cameras) {
    if (ci < 0 || size_t(ci) >= model.cameras.size()) throw file_error(path, "node references a missing camera");
    const auto& gc = model.cameras[size_t(ci)];
    if (gc.type != "perspective")
      throw file_error(path, "camera " + std::to_string(ci) + ": " + gc.type.substr(0, 100) +
                                 " cameras are not supported (perspective ones are)");
    // The JSON scenes' limit on fov: the film plane of a wider view is numerically unusable.
    if (!(gc.perspective.yfov > 0 && gc.perspective.yfov <= 179.9 * M_PI / 180.0))
      throw file_error(path, "camera " + std::to_string(ci) + ": yfov must be in (0, π) and at most 179.9°");
    if (gc.perspective.aspectRatio < 0)
      throw file_error(path, "camera " + std::to_string(ci) + ": negative aspectRatio");
    if (!(gc.perspective.znear > 0))
      throw file_error(path, "camera " + std::to_string(ci) + ": znear must be positive");
    // The view is the camera node's world transform inverted: one that mirrors would mirror the
    // image, which backlight's cameras (an origin, a target and an up vector) cannot.
    const double det = linear_determinant(xf);
    if (det < 0)
      throw file_error(path, "camera " + std::to_string(ci) +
                                 ": its node's world transform mirrors (determinant < 0); backlight's cameras cannot "
                                 "mirror the image");
    if (!(det > 0)) throw file_error(path, "camera " + std::to_string(ci) + ": its node's world transform scales to 0");
    check_zfar(gc.perspective, xf, det, "camera " + std::to_string(ci));
    Camera c;
    // Unique among shapes and cameras (their pose parameters are named after them).
    c.name = shape_names.make(sanitize(gc.name.empty() ? "camera" + std::to_string(ci) : gc.name));
    c.fov_axis = Camera::FovAxis::Y;  // glTF's yfov
    c.fov_degrees = float(gc.perspective.yfov * 180.0 / M_PI);
    double aspect = gc.perspective.aspectRatio > 0 ? gc.perspective.aspectRatio : 1.0;
    c.width = 512;
    const double height = std::round(512.0 / aspect);
    limits::check_image_size(path + ": camera " + std::to_string(ci), 512,
                             height > 1e12 ? uint64_t(1e12) : uint64_t(std::max(1.0, height)));
    c.height = int(std::max(1.0, height));
    c.origin = xf.point({0, 0, 0});
    c.target = c.origin + normalize(xf.vector({0, 0, -1}));
    c.up = normalize(xf.vector({0, 1, 0}));
    c.near_clip = float(std::max(1e-4, gc.perspective.znear));
    scene->cameras.push_back(c);
  }
  if (scene->cameras.empty()) {
    Vec3f lo(1e30f), hi(-1e30f);
    for (const auto& m : scene->meshes)
      for (size_t i = 0; i < m.vertex_count(); ++i)
        for (int k = 0; k < 3; ++k)
          lo[k] = std::min(lo[k], m.positions[i][k]), hi[k] = std::max(hi[k], m.positions[i][k]);
    Vec3f center = (lo + hi) * 0.5f;
    float radius = 0.5f * length(hi - lo);
    // The bounding sphere fits the 40° cone of the film's smaller side, so it stays in view at any
    // resolution (--resolution 256x192 or 192x256 alike).
    Camera c;
    c.name = shape_names.make("default");
    c.fov_degrees = 40.f;
    c.fov_axis = Camera::FovAxis::Smaller;
    c.target = center;
    c.origin =
        center + Vec3f(0, 0.3f, 1.f) * (radius / std::tan(20.f * kPi / 180.f) / length(Vec3f(0, 0.3f, 1.f)) * 1.1f);
    scene->cameras.push_back(c);
  }
  // A default sky: white when nothing emits, dim otherwise so the emitters dominate.
  scene->environment.present = true;
  scene->environment.is_map = false;
  float sky = scene->area_emitters.empty() ? 1.f : 0.1f;
  scene->environment.param = add_param("environment.radiance", {3}, {sky, sky, sky}, 0.f, 1e30f).param;
  scene->add_geometry_params();
  scene->prepare();
  return scene;
}

}  // namespace bl
