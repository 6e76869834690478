#pragma once
// Checks on a glTF file's JSON, made before tinygltf reads it (engine/scene/scene_gltf.cpp alone
// uses them). tinygltf reads some malformed or out-of-range properties leniently — a negative
// index or a rotation that is not an array as if absent, an explicit aspectRatio of 0 like an
// absent one, a version it cannot read as 2.0 — and words a few errors confusingly; each check here
// refuses such a file with a message naming the object at fault.
#include <nlohmann/json.hpp>

#include <cstdio>
#include <set>
#include <string>

#include "engine/core/errors.h"

namespace bl::gltf_json {

// "node 3 ('name')" or "node 3": an object of a top-level array, for messages.
inline std::string object_name(const char* kind, size_t index, const nlohmann::json& object) {
  const auto name = object.find("name");
  return std::string(kind) + " " + std::to_string(index) +
         (name != object.end() && name->is_string() ? " ('" + name->get<std::string>().substr(0, 100) + "')" : "");
}

// A value as the file spells it, shortened for a one-line message.
inline std::string spelled(const nlohmann::json& value) {
  const std::string text = value.dump();
  return text.size() > 40 ? text.substr(0, 40) + "..." : text;
}

// Property `key` of `object`, when present, is a non-negative integer (an index, an offset):
// tinygltf reads a negative or non-integer one as absent.
inline void require_natural(const std::string& path, const std::string& owner, const nlohmann::json& object,
                            const char* key) {
  const auto it = object.find(key);
  if (it != object.end() && !it->is_number_unsigned())
    throw file_error(
        path, (owner.empty() ? "" : owner + ": ") + key + " must be a non-negative integer, not " + spelled(*it));
}

// The elements of the top-level array `key` that are objects, with their indices (tinygltf
// reports a malformed list).
template <class F>
void for_each_object(const nlohmann::json& doc, const char* key, F&& f) {
  const auto list = doc.find(key);
  if (list == doc.end() || !list->is_array()) return;
  for (size_t i = 0; i < list->size(); ++i)
    if ((*list)[i].is_object()) f(i, (*list)[i]);
}

// asset.version is "major.minor": a 2.x file is read (a newer minor version only adds what a 2.0
// reader may ignore), unless its minVersion says it needs more than 2.0. glTF 1.0 files differ
// throughout, and tinygltf would read them as 2.0.
inline void check_asset_version(const std::string& path, const nlohmann::json& doc) {
  const auto asset = doc.find("asset");
  if (asset == doc.end() || !asset->is_object()) return;  // tinygltf reports a missing asset
  auto version_of = [&](const char* key, int& major, int& minor) {
    const auto it = asset->find(key);
    if (it == asset->end()) return false;
    char rest = 0;
    if (!it->is_string() || std::sscanf(it->get<std::string>().c_str(), "%d.%d%c", &major, &minor, &rest) != 2 ||
        major < 0 || minor < 0)
      throw file_error(path, std::string("asset.") + key + " " + spelled(*it) + " is not of the form major.minor");
    return true;
  };
  int major = 0, minor = 0;
  if (version_of("version", major, minor) && major != 2)
    throw file_error(path, "asset.version " + std::to_string(major) + "." + std::to_string(minor) +
                               ": backlight reads glTF 2.x files only");
  if (version_of("minVersion", major, minor) && (major > 2 || (major == 2 && minor > 0)))
    throw file_error(path, "asset.minVersion " + std::to_string(major) + "." + std::to_string(minor) +
                               ": the file needs a glTF reader of that version (backlight reads glTF 2.0)");
}

// A file that requires an extension we do not implement (Draco or meshopt compression, ...) is
// refused by name before tinygltf reads it: its buffers would otherwise fail with messages about
// missing files or buffer views.
inline void check_required_extensions(const std::string& path, const nlohmann::json& doc) {
  static const std::set<std::string> implemented = {"KHR_mesh_quantization", "KHR_texture_transform",
                                                    "KHR_materials_emissive_strength"};
  const auto it = doc.find("extensionsRequired");
  if (it == doc.end()) return;
  if (!it->is_array()) throw file_error(path, "invalid glTF: extensionsRequired must be an array of names");
  for (const auto& name : *it) {
    if (!name.is_string()) throw file_error(path, "invalid glTF: extensionsRequired must be an array of names");
    if (implemented.count(name.get<std::string>())) continue;
    throw file_error(path, "requires the glTF extension '" + name.get<std::string>().substr(0, 100) +
                               "', which backlight does not support");
  }
}

// A perspective camera's yfov and znear are required (tinygltf's message for a missing yfov
// speaks of an orthographic camera); aspectRatio and zfar are optional, and tinygltf reads an
// absent one and an explicit 0 alike (as 0), so an explicit value that is not positive is caught
// in the JSON itself.
inline void check_cameras(const std::string& path, const nlohmann::json& doc) {
  for_each_object(doc, "cameras", [&](size_t i, const nlohmann::json& camera) {
    const std::string what = "camera " + std::to_string(i);
    const auto type = camera.find("type");
    if (type == camera.end() || *type != "perspective") return;  // tinygltf checks the other types
    const auto perspective = camera.find("perspective");
    if (perspective == camera.end() || !perspective->is_object())
      throw file_error(path, what + ": a perspective camera needs a perspective object");
    for (const char* key : {"yfov", "znear"})
      if (!perspective->contains(key)) throw file_error(path, what + ": perspective." + key + " is missing");
    for (const char* key : {"aspectRatio", "zfar"}) {
      const auto value = perspective->find(key);
      if (value != perspective->end() && !(value->is_number() && value->get<double>() > 0))
        throw file_error(path, what + ": " + key + " must be a positive number");
    }
  });
}

// A node has a matrix or translation/rotation/scale, never both (the schema's rule). tinygltf
// reads TRS only when there is no matrix, so a node with both is caught in the JSON itself: its
// TRS would otherwise be dropped without a word. A transform or weights property that is not an
// array of numbers, and a negative camera, mesh or skin index, tinygltf reads as absent.
inline void check_nodes(const std::string& path, const nlohmann::json& doc) {
  for_each_object(doc, "nodes", [&](size_t i, const nlohmann::json& node) {
    const std::string what = object_name("node", i, node);
    if (node.contains("matrix") &&
        (node.contains("translation") || node.contains("rotation") || node.contains("scale")))
      throw file_error(path,
                       what + ": has both a matrix and translation/rotation/scale (glTF allows one or the other)");
    for (const char* key : {"matrix", "translation", "rotation", "scale", "weights"}) {
      const auto value = node.find(key);
      if (value == node.end()) continue;
      bool numbers = value->is_array();
      for (size_t k = 0; numbers && k < value->size(); ++k) numbers = (*value)[k].is_number();
      if (!numbers) throw file_error(path, what + ": " + key + " must be an array of numbers, not " + spelled(*value));
    }
    for (const char* key : {"camera", "mesh", "skin"}) require_natural(path, what, node, key);
  });
}

// Indices and offsets tinygltf reads as absent (or as 0) when they are negative or not integers:
// the default scene, an accessor's buffer view and byte offset, a buffer view's offset and stride
// (a byteOffset of -48 read the data from offset 0), a primitive's indices, material and mode (a
// material of -1 rendered with the default material), a texture's sampler and source, an image's
// buffer view and a material's textures. A mesh without primitives (the schema asks for at least
// one) drew nothing without a word. A byteStride of 0, which the schema does not allow either, is
// read as tightly packed data, as tinygltf does: it says nothing else.
inline void check_indices(const std::string& path, const nlohmann::json& doc) {
  require_natural(path, "", doc, "scene");
  for_each_object(doc, "accessors", [&](size_t i, const nlohmann::json& accessor) {
    for (const char* key : {"bufferView", "byteOffset"})
      require_natural(path, "accessor " + std::to_string(i), accessor, key);
  });
  for_each_object(doc, "bufferViews", [&](size_t i, const nlohmann::json& view) {
    for (const char* key : {"buffer", "byteOffset", "byteLength", "byteStride"})
      require_natural(path, object_name("buffer view", i, view), view, key);
  });
  for_each_object(doc, "textures", [&](size_t i, const nlohmann::json& texture) {
    for (const char* key : {"sampler", "source"})
      require_natural(path, object_name("texture", i, texture), texture, key);
  });
  for_each_object(doc, "images", [&](size_t i, const nlohmann::json& image) {
    require_natural(path, object_name("image", i, image), image, "bufferView");
  });
  for_each_object(doc, "meshes", [&](size_t i, const nlohmann::json& mesh) {
    const auto primitives = mesh.find("primitives");
    if (primitives == mesh.end() || !primitives->is_array()) return;
    if (primitives->empty())
      throw file_error(path, object_name("mesh", i, mesh) + ": has no primitives (glTF asks for at least one)");
    for (size_t k = 0; k < primitives->size(); ++k)
      if ((*primitives)[k].is_object())
        for (const char* key : {"indices", "material", "mode"})
          require_natural(path, object_name("mesh", i, mesh) + " primitive " + std::to_string(k), (*primitives)[k],
                          key);
  });
  for_each_object(doc, "materials", [&](size_t i, const nlohmann::json& material) {
    const std::string what = object_name("material", i, material);
    auto texture_info = [&](const nlohmann::json& parent, const char* key) {
      const auto info = parent.find(key);
      if (info != parent.end() && info->is_object()) require_natural(path, what + ": " + key, *info, "index");
    };
    for (const char* key : {"normalTexture", "occlusionTexture", "emissiveTexture"}) texture_info(material, key);
    const auto pbr = material.find("pbrMetallicRoughness");
    if (pbr != material.end() && pbr->is_object())
      for (const char* key : {"baseColorTexture", "metallicRoughnessTexture"}) texture_info(*pbr, key);
  });
}

// Material factors the specification bounds and tinygltf does not check: baseColorFactor (4
// numbers) in [0, 1] (a texture would otherwise be scaled past 1 and clamped), emissiveFactor (3)
// ≥ 0 (backlight uses values above 1 as they are), metallicFactor and roughnessFactor numbers in
// [0, 1], alphaMode one of its three values and alphaCutoff ≥ 0. A factor of another JSON type
// (a string "0.2", an object) is refused: tinygltf silently used the default in its place (a
// roughness "0.2" rendered as 1, "metallicFactor": "0" as a metal, emission "1 1 1" as none).
inline void check_material_factors(const std::string& path, const nlohmann::json& doc) {
  for_each_object(doc, "materials", [&](size_t i, const nlohmann::json& material) {
    const std::string what = object_name("material", i, material);
    auto numbers_in = [&](const nlohmann::json& parent, const char* key, size_t count, double lo, double hi,
                          const char* range) {
      const auto value = parent.find(key);
      if (value == parent.end()) return;
      if (!value->is_array() || value->size() != count)
        throw file_error(path, what + ": " + key + " must be an array of " + std::to_string(count) + " numbers, not " +
                                   spelled(*value));
      for (const auto& v : *value)
        if (!v.is_number() || !(v.get<double>() >= lo && v.get<double>() <= hi))
          throw file_error(path, what + ": " + key + " values must be " + range + ", not " + spelled(*value));
    };
    auto number_in_unit = [&](const nlohmann::json& parent, const char* key) {
      const auto value = parent.find(key);
      if (value != parent.end() && !(value->is_number() && value->get<double>() >= 0 && value->get<double>() <= 1))
        throw file_error(path, what + ": " + key + " must be a number in [0, 1], not " + spelled(*value));
    };
    const auto pbr = material.find("pbrMetallicRoughness");
    if (pbr != material.end() && pbr->is_object()) {
      numbers_in(*pbr, "baseColorFactor", 4, 0, 1, "in [0, 1]");
      number_in_unit(*pbr, "metallicFactor");
      number_in_unit(*pbr, "roughnessFactor");
    }
    numbers_in(material, "emissiveFactor", 3, 0, 1e30, "≥ 0");
    const auto mode = material.find("alphaMode");
    if (mode != material.end() && *mode != "OPAQUE" && *mode != "MASK" && *mode != "BLEND")
      throw file_error(path, what + ": alphaMode " + spelled(*mode) + " is not OPAQUE, MASK or BLEND");
    const auto cutoff = material.find("alphaCutoff");
    if (cutoff != material.end() && !(cutoff->is_number() && cutoff->get<double>() >= 0))
      throw file_error(path, what + ": alphaCutoff must be a number ≥ 0, not " + spelled(*cutoff));
  });
}

// Every check above, on the parsed JSON of a .gltf or of a .glb's JSON chunk.
inline void check_gltf_json(const std::string& path, const nlohmann::json& doc) {
  check_asset_version(path, doc);
  check_required_extensions(path, doc);
  check_cameras(path, doc);
  check_nodes(path, doc);
  check_indices(path, doc);
  check_material_factors(path, doc);
}

}  // namespace bl::gltf_json
