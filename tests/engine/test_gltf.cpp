// glTF loading details a user meets on real files: the default camera (a file without one) keeps
// the whole model in view at any film aspect, a file that requires an extension backlight does
// not implement is refused by the extension's name, metallic factors between 0 and 1 blend the
// two lobes, and vertex colours (COLOR_0) multiply the base colour, gradients included. What
// backlight cannot render as the specification says is refused by name, and what it ignores
// warns once per file.
#include <unistd.h>
#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include "engine/core/errors.h"
#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/io/image_io.h"
#include "engine/scene/scene_load.h"

using namespace bl;
namespace fs = std::filesystem;

namespace {
struct TempDir {
  fs::path dir = fs::temp_directory_path() / ("backlight-test-gltf-" + std::to_string(::getpid()));
  TempDir() { fs::create_directories(dir); }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
  std::string operator()(const std::string& name) const { return (dir / name).string(); }
};

// A 2 × 2 × 2 grey cube centred at the origin (8 vertices, 12 triangles) in cube.bin, and a glTF
// around it; `extra` is spliced into the top-level object.
std::string write_cube(const TempDir& tmp, const std::string& name, const std::string& extra = "") {
  const float p[8][3] = {{-1, -1, -1}, {1, -1, -1}, {1, 1, -1}, {-1, 1, -1},
                         {-1, -1, 1},  {1, -1, 1},  {1, 1, 1},  {-1, 1, 1}};
  const uint16_t idx[36] = {0, 2, 1, 0, 3, 2, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4,
                            3, 7, 6, 3, 6, 2, 0, 4, 7, 0, 7, 3, 1, 2, 6, 1, 6, 5};
  std::ofstream bin(tmp("cube.bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(p), sizeof p);
  bin.write(reinterpret_cast<const char*>(idx), sizeof idx);
  bin.close();
  std::ofstream(tmp(name)) << R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"name": "cube", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
  "materials": [{"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1],
                 "metallicFactor": 0, "roughnessFactor": 1}}],
  "buffers": [{"uri": "cube.bin", "byteLength": 168}],
  "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 96}, {"buffer": 0, "byteOffset": 96, "byteLength": 72}],
  "accessors": [{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3", "min": [-1, -1, -1], "max": [1, 1, 1]},
                {"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}])"
                           << extra << "}";
  return tmp(name);
}

// How many border pixels see the cube rather than the white sky (radiance exactly 1).
int border_hits(const Image& img) {
  int hits = 0;
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x)
      if (x == 0 || y == 0 || x == img.width - 1 || y == img.height - 1) hits += img.at(x, y, 1) != 1.f;
  return hits;
}
}  // namespace

TEST_CASE("a glTF without a camera is framed for the film's aspect", "[gltf]") {
  TempDir tmp;
  const std::string file = write_cube(tmp, "cube.gltf");
  for (const auto& [w, h] : {std::pair{64, 32}, std::pair{32, 64}, std::pair{48, 48}}) {
    CAPTURE(w, h);
    auto scene = load_scene(file);
    REQUIRE(scene->cameras.size() == 1);
    Camera& cam = scene->cameras[0];
    cam.width = w, cam.height = h;
    cam.update();
    const Image img = render(*scene, {0, 2, 1, false});
    CHECK(img.at(w / 2, h / 2, 1) < 0.6f);  // the cube is there
    CHECK(border_hits(img) == 0);           // and all of it
    // Negative control: the same 40° on the wide side (the old framing) cuts the cube off on a
    // film that is not square.
    if (w != h) {
      cam.fov_axis = w > h ? Camera::FovAxis::X : Camera::FovAxis::Y;
      cam.update();
      CHECK(border_hits(render(*scene, {0, 2, 1, false})) > 0);
    }
  }
}

TEST_CASE("fov_axis follows Mitsuba 3: x, y, diagonal, smaller, larger", "[gltf][camera]") {
  Camera c;
  c.fov_degrees = 60.f;
  c.width = 200, c.height = 100;
  const float t = std::tan(30.f * kPi / 180.f);
  auto check = [&](Camera::FovAxis axis, float tx, float ty) {
    c.fov_axis = axis;
    c.update();
    CHECK(c.tan_x == Approx(tx));
    CHECK(c.tan_y == Approx(ty));
  };
  check(Camera::FovAxis::X, t, t / 2);
  check(Camera::FovAxis::Y, 2 * t, t);
  check(Camera::FovAxis::Smaller, 2 * t, t);  // height is the smaller side
  check(Camera::FovAxis::Larger, t, t / 2);
  check(Camera::FovAxis::Diagonal, t * 2 / std::sqrt(5.f), t / std::sqrt(5.f));
}

TEST_CASE("a required glTF extension backlight lacks is refused by name", "[gltf][errors]") {
  TempDir tmp;
  auto error_of = [](const std::string& path) {
    try {
      load_scene(path);
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  const std::string draco = write_cube(
      tmp, "draco.gltf",
      R"(, "extensionsUsed": ["KHR_draco_mesh_compression"], "extensionsRequired": ["KHR_draco_mesh_compression"])");
  const std::string e = error_of(draco);
  CHECK(e.find("draco.gltf: requires the glTF extension 'KHR_draco_mesh_compression'") != std::string::npos);
  CHECK(e.find('\n') == std::string::npos);
  // A control character in the name stays out of the one-line message.
  const std::string odd = write_cube(tmp, "odd.gltf", R"(, "extensionsRequired": ["EXT_a\nb"])");
  const std::string e2 = error_of(odd);
  CHECK(e2.find("EXT_a?b") != std::string::npos);
  CHECK(e2.find('\n') == std::string::npos);
  // Used but not required: loads (the extension is optional by the spec).
  CHECK(error_of(write_cube(tmp, "used.gltf", R"(, "extensionsUsed": ["EXT_unknown_thing"])")).empty());
  CHECK(error_of(write_cube(tmp, "bad.gltf", R"(, "extensionsRequired": "KHR_x")")).find("must be an array") !=
        std::string::npos);
}

namespace {
// A quad (4 vertices, 2 triangles) whose POSITION accessor is sparse: `with_base` keeps a base
// buffer view of four vertices at the origin, otherwise the base is zeros. The sparse part
// substitutes vertices 1, 2 and 3 (vertex 0 stays at the origin).
std::string write_sparse_quad(const TempDir& tmp, const std::string& name, bool with_base,
                              const std::string& sparse_override = "") {
  const float base[4][3] = {};
  const uint16_t idx[6] = {0, 1, 2, 0, 2, 3};
  const uint16_t sparse_idx[3] = {1, 2, 3};
  const float sparse_val[3][3] = {{1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
  std::ofstream bin(tmp(name + ".bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(base), sizeof base);              // 0..48
  bin.write(reinterpret_cast<const char*>(idx), sizeof idx);                // 48..60
  bin.write(reinterpret_cast<const char*>(sparse_idx), sizeof sparse_idx);  // 60..66
  bin.write("\0\0", 2);                                                     // 66..68 (align)
  bin.write(reinterpret_cast<const char*>(sparse_val), sizeof sparse_val);  // 68..104
  bin.close();
  const std::string sparse = sparse_override.empty() ? R"("sparse": {"count": 3,
      "indices": {"bufferView": 2, "componentType": 5123}, "values": {"bufferView": 3}})"
                                                     : sparse_override;
  std::ofstream(tmp(name)) << R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"name": "quad", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
  "buffers": [{"uri": ")" + name + R"(.bin", "byteLength": 104}],
  "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12},
                  {"buffer": 0, "byteOffset": 60, "byteLength": 6}, {"buffer": 0, "byteOffset": 68, "byteLength": 36}],
  "accessors": [{)" + (with_base ? std::string(R"("bufferView": 0, )") : std::string()) +
                                  R"("componentType": 5126, "count": 4, "type": "VEC3",
                 "min": [0, 0, 0], "max": [1, 1, 0], )" +
                                  sparse + R"(},
                {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]})";
  return tmp(name);
}
}  // namespace

TEST_CASE("sparse accessors substitute their elements, with or without a base buffer view", "[gltf]") {
  TempDir tmp;
  for (const bool with_base : {true, false}) {
    CAPTURE(with_base);
    auto scene = load_scene(write_sparse_quad(tmp, with_base ? "based.gltf" : "zeros.gltf", with_base));
    REQUIRE(scene->meshes.size() == 1);
    const Mesh& m = scene->meshes[0];
    REQUIRE(m.vertex_count() == 4);
    const float want[4][3] = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
    for (int v = 0; v < 4; ++v)
      for (int k = 0; k < 3; ++k) CHECK(m.positions[size_t(v)][k] == want[v][k]);
  }
  auto error_of = [](const std::string& path) {
    try {
      load_scene(path);
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  // An index past the accessor, values past their view, a count past the accessor's.
  CHECK(error_of(write_sparse_quad(tmp, "j.gltf", true, R"("sparse": {"count": 1,
      "indices": {"bufferView": 3, "componentType": 5125}, "values": {"bufferView": 3}})"))
            .find("is out of range") != std::string::npos);  // 1.0f read as an index: 1065353216
  CHECK(error_of(write_sparse_quad(tmp, "k.gltf", true, R"("sparse": {"count": 3,
      "indices": {"bufferView": 2, "componentType": 5123}, "values": {"bufferView": 3, "byteOffset": 4}})"))
            .find("reads past the end of its buffer view") != std::string::npos);
  CHECK(error_of(write_sparse_quad(tmp, "l.gltf", true, R"("sparse": {"count": 5,
      "indices": {"bufferView": 2, "componentType": 5123}, "values": {"bufferView": 3}})"))
            .find("count 5 is not in [1, 4]") != std::string::npos);
}

namespace {
// A 2 × 2 quad facing +z that emits its texture (left texel red, right texel green) through
// TEXCOORD_1; TEXCOORD_0 is all zeros, so a loader reading the wrong set shows one colour.
std::string write_emissive_quad(const TempDir& tmp, const std::string& name, const std::string& base_texture = "") {
  Image tex(2, 1, 3);
  tex.at(0, 0, 0) = 1.f;
  tex.at(1, 0, 1) = 1.f;
  write_image(tmp("emit.png"), tex);
  const float pos[4][3] = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
  const float uv0[4][2] = {};
  const float uv1[4][2] = {{0, 1}, {1, 1}, {1, 0}, {0, 0}};
  const uint16_t idx[6] = {0, 1, 2, 0, 2, 3};
  std::ofstream bin(tmp(name + ".bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(pos), sizeof pos);  // 0..48
  bin.write(reinterpret_cast<const char*>(uv0), sizeof uv0);  // 48..80
  bin.write(reinterpret_cast<const char*>(uv1), sizeof uv1);  // 80..112
  bin.write(reinterpret_cast<const char*>(idx), sizeof idx);  // 112..124
  bin.close();
  std::ofstream(tmp(name)) << R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"name": "quad", "primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1, "TEXCOORD_1": 2},
              "indices": 3, "material": 0}]}],
  "materials": [{"name": "glow", "emissiveFactor": [1, 1, 1], "emissiveTexture": {"index": 0, "texCoord": 1},
                 "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0)" +
                                  base_texture + R"(}}],
  "textures": [{"source": 0}], "images": [{"uri": "emit.png"}],
  "buffers": [{"uri": ")" + name + R"(.bin", "byteLength": 124}],
  "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                  {"buffer": 0, "byteOffset": 80, "byteLength": 32}, {"buffer": 0, "byteOffset": 112, "byteLength": 12}],
  "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-1, -1, 0], "max": [1, 1, 0]},
                {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
                {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}]})";
  return tmp(name);
}
}  // namespace

TEST_CASE("emissive textures emit through the uv set their texCoord names", "[gltf]") {
  TempDir tmp;
  auto scene = load_scene(write_emissive_quad(tmp, "glow.gltf"));
  const int h = scene->params.find("glow.emission");
  REQUIRE(h >= 0);
  CHECK(scene->params[h].shape == std::vector<int>{1, 2, 3});
  REQUIRE(scene->area_emitters.size() == 1);
  Camera& cam = scene->cameras[0];
  cam.width = 32, cam.height = 32;
  cam.update();
  const Image img = render(*scene, {0, 4, 1, false});
  // Quad spans the middle of the view: left quarter-point red, right quarter-point green.
  const int y = 16;
  const float* left = &img.data[(size_t(y) * 32 + 11) * 3];
  const float* right = &img.data[(size_t(y) * 32 + 20) * 3];
  INFO("left " << left[0] << " " << left[1] << " " << left[2] << ", right " << right[0] << " " << right[1] << " "
               << right[2]);
  CHECK(left[0] > 2 * left[1]);
  CHECK(right[1] > 2 * right[0]);
  CHECK(left[2] < 0.2f * left[0]);  // not the white of an ignored texture
  // One uv set per mesh: a base colour texture on another set is refused by name.
  try {
    load_scene(write_emissive_quad(tmp, "two.gltf", R"(, "baseColorTexture": {"index": 0, "texCoord": 0})"));
    FAIL("two uv sets accepted");
  } catch (const InputError& e) {
    CHECK(std::string(e.what()).find("different uv sets (TEXCOORD_0, TEXCOORD_1)") != std::string::npos);
  }
}

namespace {
std::string replace_in_file(const std::string& path, const std::string& from, const std::string& to) {
  std::ifstream f(path);
  std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  const size_t at = text.find(from);
  REQUIRE(at != std::string::npos);
  text.replace(at, from.size(), to);
  std::ofstream(path) << text;
  return path;
}
}  // namespace

TEST_CASE("KHR_texture_transform moves the uvs as the extension's GLSL defines", "[gltf]") {
  TempDir tmp;
  // Offset 0.5 and scale 0.5 in u: every point of the quad samples the right (green) texel.
  auto scene = load_scene(replace_in_file(
      write_emissive_quad(tmp, "shift.gltf"), R"("texCoord": 1})",
      R"("texCoord": 1, "extensions": {"KHR_texture_transform": {"offset": [0.5, 0], "scale": [0.5, 1]}}})"));
  const Mesh& m = scene->meshes[0];
  REQUIRE(m.uvs.size() == 4);
  CHECK(m.uvs[0].x == Approx(0.5f));  // (0, 1) → (0.5, 1)
  CHECK(m.uvs[1].x == Approx(1.0f));  // (1, 1) → (1, 1)
  CHECK(m.uvs[0].y == Approx(1.0f));
  // Rotation by π/2: (u, v) → (u cos − v sin, u sin + v cos) = (−v, u).
  auto rotated = load_scene(
      replace_in_file(write_emissive_quad(tmp, "rot.gltf"), R"("texCoord": 1})",
                      R"("texCoord": 1, "extensions": {"KHR_texture_transform": {"rotation": 1.5707963267948966}}})"));
  const Mesh& r = rotated->meshes[0];
  REQUIRE(r.uvs.size() == 4);
  CHECK(r.uvs[1].x == Approx(-1.f).margin(1e-6));  // (1, 1) → (−1, 1)
  CHECK(r.uvs[1].y == Approx(1.f).margin(1e-6));
  CHECK(r.uvs[3].x == Approx(0.f).margin(1e-6));  // (0, 0) → (0, 0)
  // Required by the file: loads, since it is implemented.
  CHECK_NOTHROW(load_scene(replace_in_file(write_emissive_quad(tmp, "req.gltf"), R"({"asset")",
                                           R"({"extensionsRequired": ["KHR_texture_transform"], "asset")")));
  // A texCoord override inside the transform is refused by name, as are non-numbers.
  CHECK_THROWS_WITH(
      load_scene(replace_in_file(write_emissive_quad(tmp, "tc.gltf"), R"("texCoord": 1})",
                                 R"("texCoord": 1, "extensions": {"KHR_texture_transform": {"texCoord": 0}}})")),
      Catch::Contains("texCoord overrides are not supported"));
  CHECK_THROWS_WITH(
      load_scene(replace_in_file(write_emissive_quad(tmp, "nan.gltf"), R"("texCoord": 1})",
                                 R"("texCoord": 1, "extensions": {"KHR_texture_transform": {"offset": [1, "x"]}}})")),
      Catch::Contains("offset must be two numbers"));
}

TEST_CASE("quantized attributes (KHR_mesh_quantization) and normalized integer uvs are decoded", "[gltf]") {
  TempDir tmp;
  // The cube with SHORT normalized positions (±32767 → ±1) and UNSIGNED_BYTE normalized uvs.
  const int16_t p[8][4] = {{-32767, -32767, -32767, 0}, {32767, -32767, -32767, 0}, {32767, 32767, -32767, 0},
                           {-32767, 32767, -32767, 0},  {-32767, -32767, 32767, 0}, {32767, -32767, 32767, 0},
                           {32767, 32767, 32767, 0},    {-32767, 32767, 32767, 0}};
  const uint8_t uv[8][2] = {{0, 0}, {255, 0}, {255, 255}, {0, 255}, {0, 0}, {255, 0}, {255, 255}, {0, 255}};
  const uint16_t idx[36] = {0, 2, 1, 0, 3, 2, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4,
                            3, 7, 6, 3, 6, 2, 0, 4, 7, 0, 7, 3, 1, 2, 6, 1, 6, 5};
  std::ofstream bin(tmp("q.bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(p), sizeof p);      // 0..64 (stride 8)
  bin.write(reinterpret_cast<const char*>(uv), sizeof uv);    // 64..80
  bin.write(reinterpret_cast<const char*>(idx), sizeof idx);  // 80..152
  bin.close();
  std::ofstream(tmp("q.gltf")) << R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "extensionsUsed": ["KHR_mesh_quantization"], "extensionsRequired": ["KHR_mesh_quantization"],
  "nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}],
  "buffers": [{"uri": "q.bin", "byteLength": 152}],
  "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 64, "byteStride": 8},
                  {"buffer": 0, "byteOffset": 64, "byteLength": 16}, {"buffer": 0, "byteOffset": 80, "byteLength": 72}],
  "accessors": [{"bufferView": 0, "componentType": 5122, "normalized": true, "count": 8, "type": "VEC3",
                 "min": [-32767, -32767, -32767], "max": [32767, 32767, 32767]},
                {"bufferView": 1, "componentType": 5121, "normalized": true, "count": 8, "type": "VEC2"},
                {"bufferView": 2, "componentType": 5123, "count": 36, "type": "SCALAR"}]})";
  auto scene = load_scene(tmp("q.gltf"));
  const Mesh& m = scene->meshes[0];
  REQUIRE(m.vertex_count() == 8);
  CHECK(m.positions[6][0] == 1.f);
  CHECK(m.positions[0][2] == -1.f);
  REQUIRE(m.uvs.size() == 8);
  CHECK(m.uvs[2].x == 1.f);
  CHECK(m.uvs[1].y == 0.f);
}

TEST_CASE("metallicFactor strictly between 0 and 1 becomes the metallic-roughness blend", "[gltf][material]") {
  TempDir tmp;
  struct Case {
    const char* factor;
    BsdfType type;
    const char* colour;  // the base colour's parameter
  };
  for (const Case& c :
       {Case{"0", BsdfType::RoughPlastic, "grey.albedo"}, Case{"1", BsdfType::RoughConductor, "grey.specular"},
        Case{"0.4", BsdfType::MetallicRoughness, "grey.base_color"}}) {
    CAPTURE(c.factor);
    const std::string name = std::string("metallic_") + c.factor + ".gltf";
    auto scene = load_scene(replace_in_file(write_cube(tmp, name), R"("metallicFactor": 0,)",
                                            std::string(R"("metallicFactor": )") + c.factor + ","));
    REQUIRE(scene->materials.size() == 1);
    const Material& m = scene->materials[0];
    CHECK(m.type == c.type);
    const int colour = scene->params.find(c.colour);
    REQUIRE(colour >= 0);
    CHECK(scene->params[colour].value == std::vector<float>{0.5f, 0.5f, 0.5f});
    CHECK(scene->params.find("grey.roughness") >= 0);
    const int metallic = scene->params.find("grey.metallic");
    if (c.type == BsdfType::MetallicRoughness) {
      REQUIRE(metallic >= 0);
      CHECK(m.metallic.param == metallic);
      CHECK(scene->params[metallic].value == std::vector<float>{0.4f});
      CHECK(scene->params[metallic].lower == 0.f);
      CHECK(scene->params[metallic].upper == 1.f);
    } else {
      CHECK(metallic < 0);  // the pure lobes keep their parameters
    }
  }
}

namespace {
// A 2 × 2 quad facing +z with per-vertex colours: bottom-left red, bottom-right green, top-right
// blue, top-left red. `colours` is "float3" (VEC3 floats), "ubyte4" (VEC4 normalized unsigned
// bytes, alpha 255), "ubyte4_alpha" (the same with alpha 51 at the top-right vertex), "half" (VEC3
// floats, all 0.5), "byte_raw" (VEC4 unsigned bytes without
// `normalized`, which the specification forbids) or "" (no COLOR_0).
std::string write_coloured_quad(const TempDir& tmp, const std::string& name, const std::string& colours,
                                double metallic = 0.0) {
  using nlohmann::json;
  const float pos[4][3] = {{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
  const float rgb[4][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 0}};
  const float half[4][3] = {{0.5f, 0.5f, 0.5f}, {0.5f, 0.5f, 0.5f}, {0.5f, 0.5f, 0.5f}, {0.5f, 0.5f, 0.5f}};
  uint8_t rgba[4][4] = {{255, 0, 0, 255}, {0, 255, 0, 255}, {0, 0, 255, 255}, {255, 0, 0, 255}};
  if (colours == "ubyte4_alpha") rgba[2][3] = 51;
  const uint16_t idx[6] = {0, 1, 2, 0, 2, 3};
  const bool bytes = colours == "ubyte4" || colours == "ubyte4_alpha" || colours == "byte_raw";
  const size_t colour_bytes = colours.empty() ? 0 : bytes ? sizeof rgba : sizeof rgb;
  // Buffer: positions (0..48), colours (48..), indices.
  std::ofstream bin(tmp(name + ".bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(pos), sizeof pos);
  if (bytes)
    bin.write(reinterpret_cast<const char*>(rgba), sizeof rgba);
  else if (!colours.empty())
    bin.write(reinterpret_cast<const char*>(colours == "half" ? half : rgb), sizeof rgb);
  bin.write(reinterpret_cast<const char*>(idx), sizeof idx);
  bin.close();
  const size_t index_offset = 48 + colour_bytes;
  json views = {{{"buffer", 0}, {"byteOffset", 0}, {"byteLength", 48}},
                {{"buffer", 0}, {"byteOffset", index_offset}, {"byteLength", sizeof idx}}};
  json accessors = {{{"bufferView", 0},
                     {"componentType", 5126},
                     {"count", 4},
                     {"type", "VEC3"},
                     {"min", {-1, -1, 0}},
                     {"max", {1, 1, 0}}},
                    {{"bufferView", 1}, {"componentType", 5123}, {"count", 6}, {"type", "SCALAR"}}};
  json attributes = {{"POSITION", 0}};
  if (!colours.empty()) {
    views.push_back({{"buffer", 0}, {"byteOffset", 48}, {"byteLength", colour_bytes}});
    json colour = {
        {"bufferView", 2}, {"componentType", bytes ? 5121 : 5126}, {"count", 4}, {"type", bytes ? "VEC4" : "VEC3"}};
    if (colours == "ubyte4" || colours == "ubyte4_alpha") colour["normalized"] = true;
    accessors.push_back(colour);
    attributes["COLOR_0"] = 2;
  }
  const json gltf = {
      {"asset", {{"version", "2.0"}}},
      {"scene", 0},
      {"scenes", {{{"nodes", {0}}}}},
      {"nodes", {{{"mesh", 0}}}},
      {"meshes", {{{"name", "quad"}, {"primitives", {{{"attributes", attributes}, {"indices", 1}, {"material", 0}}}}}}},
      {"materials",
       {{{"name", "paint"},
         {"pbrMetallicRoughness",
          {{"baseColorFactor", {1, 1, 1, 1}}, {"metallicFactor", metallic}, {"roughnessFactor", 0.8}}}}}},
      {"buffers", {{{"uri", name + ".bin"}, {"byteLength", index_offset + sizeof idx}}}},
      {"bufferViews", views},
      {"accessors", accessors}};
  std::ofstream(tmp(name)) << gltf.dump();
  return tmp(name);
}

// The quad on a small film, zoomed in (the default camera frames its bounding sphere) so that every
// pixel sees the quad and none the sky.
std::unique_ptr<Scene> load_small(const std::string& path, int size = 32) {
  auto scene = load_scene(path);
  Camera& cam = scene->cameras[0];
  cam.width = size, cam.height = size;
  cam.fov_degrees = 20.f;
  cam.update();
  return scene;
}

const float* pixel(const Image& img, int x, int y) {
  return &img.data[(size_t(y) * size_t(img.width) + size_t(x)) * 3];
}
}  // namespace

TEST_CASE("COLOR_0 multiplies the base colour (float and normalized byte colours)", "[gltf][vertex_colors]") {
  TempDir tmp;
  // Pixels near the bottom-left, bottom-right and top-right corners of the 32 × 32 film.
  const int left = 2, right = 29, top = 2, bottom = 29;
  Image images[2];
  int k = 0;
  for (const char* colours : {"float3", "ubyte4"}) {
    CAPTURE(colours);
    auto scene = load_small(write_coloured_quad(tmp, std::string(colours) + ".gltf", colours));
    REQUIRE(scene->meshes[0].colors.size() == 4);
    const Image img = render(*scene, {0, 16, 1, false});
    const float *red = pixel(img, left, bottom), *green = pixel(img, right, bottom), *blue = pixel(img, right, top);
    INFO("red corner " << red[0] << " " << red[1] << " " << red[2] << ", green corner " << green[0] << " " << green[1]
                       << " " << green[2] << ", blue corner " << blue[0] << " " << blue[1] << " " << blue[2]);
    std::printf(
        "COLOR_0 %s: red corner (%.3f, %.3f, %.3f), green corner (%.3f, %.3f, %.3f), blue corner (%.3f, "
        "%.3f, %.3f)\n",
        colours, red[0], red[1], red[2], green[0], green[1], green[2], blue[0], blue[1], blue[2]);
    CHECK(red[0] > 3 * red[1]);
    CHECK(red[0] > 3 * red[2]);
    CHECK(green[1] > 3 * green[0]);
    CHECK(green[1] > 3 * green[2]);
    CHECK(blue[2] > 3 * blue[0]);
    CHECK(blue[2] > 3 * blue[1]);
    images[k++] = img;
  }
  // 255/255 and 0/255 decode to exactly 1 and 0: both files render the same image.
  CHECK(images[0].data == images[1].data);
  // Negative control: without COLOR_0 the same quad is grey.
  const Image plain = render(*load_small(write_coloured_quad(tmp, "plain.gltf", "")), {0, 16, 1, false});
  const float* p = pixel(plain, left, bottom);
  std::printf("no COLOR_0: bottom-left (%.3f, %.3f, %.3f)\n", p[0], p[1], p[2]);
  CHECK(p[0] == Approx(p[1]).epsilon(0.05));
  CHECK(p[0] == Approx(p[2]).epsilon(0.05));
  // COLOR_0 is a property of the file's materials: a JSON scene's `gltf` shape does not read it.
  CHECK(load_gltf_meshes(tmp("float3.gltf"), Transform())[0].colors.empty());
  // The specification allows floats and normalized unsigned integers only.
  CHECK_THROWS_WITH(load_scene(write_coloured_quad(tmp, "raw.gltf", "byte_raw")),
                    Catch::Contains("COLOR_0 (accessor 2): expected VEC3 or VEC4 of floats or normalized unsigned"));
}

TEST_CASE("a uniform COLOR_0 of 0.5 halves a diffuse, directly lit image", "[gltf][vertex_colors]") {
  TempDir tmp;
  auto render_diffuse = [&](const std::string& colours) {
    auto scene = load_small(write_coloured_quad(tmp, "d_" + colours + ".gltf", colours));
    // Diffuse only (glTF's dielectric has a white coat that no colour scales), lit by the sky
    // directly: the image is linear in the albedo.
    scene->materials[0].type = BsdfType::Diffuse;
    scene->settings.max_depth = 2;
    return render(*scene, {0, 8, 3, false});
  };
  const Image plain = render_diffuse(""), half = render_diffuse("half");
  double worst = 0.0;
  for (size_t i = 0; i < plain.data.size(); ++i) {
    REQUIRE(plain.data[i] > 0.f);  // every pixel sees the lit quad (a sky sample would not halve)
    worst = std::max(worst, std::abs(double(half.data[i]) - 0.5 * double(plain.data[i])) / (0.5 * plain.data[i]));
  }
  INFO("worst relative deviation from half " << worst);
  std::printf("uniform COLOR_0 0.5: worst relative deviation from half %.3g over %zu pixel channels\n", worst,
              plain.data.size());
  CHECK(worst <= 1e-6);
}

TEST_CASE("glTF vertex colours and the metallic blend: prb matches taped AD and same-seed differences",
          "[gltf][vertex_colors][gradient]") {
  TempDir tmp;
  auto scene = load_small(write_coloured_quad(tmp, "grad.gltf", "float3", 0.4), 16);
  REQUIRE(scene->materials[0].type == BsdfType::MetallicRoughness);
  scene->settings.rr_depth = 0;  // roulette reads the throughput, which the base colour changes
  // A linear functional of the image with varying weights; its gradient is the adjoint image.
  Image a(16, 16, 3);
  for (size_t i = 0; i < a.data.size(); ++i) a.data[i] = 1e-3f * float(1 + (i * 7919) % 13);
  GradientRequest rq;
  rq.adjoint_image = &a;
  rq.pass = {0, 8, 5, false};
  rq.adjoint_seed = 5;
  const std::vector<std::string> names{"paint.base_color", "paint.roughness", "paint.metallic"};
  scene->params.require_grad(names);
  rq.method = GradientMethod::Prb;
  compute_gradient(*scene, rq);
  std::vector<std::vector<float>> prb;
  for (const auto& n : names) prb.push_back(scene->params[scene->params.find(n)].grad);
  rq.method = GradientMethod::Taped;
  compute_gradient(*scene, rq);
  for (size_t i = 0; i < names.size(); ++i) {
    const std::vector<float>& taped = scene->params[scene->params.find(names[i])].grad;
    double diff = 0, norm = 0;
    for (size_t k = 0; k < taped.size(); ++k)
      diff += double(taped[k] - prb[i][k]) * (taped[k] - prb[i][k]), norm += double(prb[i][k]) * prb[i][k];
    INFO(names[i] << ": |prb| = " << std::sqrt(norm) << ", |taped - prb| = " << std::sqrt(diff));
    std::printf("glTF quad, %s: |prb| = %.6g, |taped - prb| / |prb| = %.3g\n", names[i].c_str(), std::sqrt(norm),
                std::sqrt(diff / norm));
    CHECK(norm > 0);
    CHECK(std::sqrt(diff) <= 1e-4 * std::sqrt(norm));
  }
  // The base colour does not move sampling: same-seed differences of the whole image.
  rq.method = GradientMethod::Prb;
  for (const auto& row : directional_check(*scene, "paint.base_color", rq, 3, 1e-2, 3)) {
    INFO("adjoint " << row.adjoint << " finite difference " << row.finite_difference);
    std::printf("glTF quad, paint.base_color: adjoint %.6g, finite difference %.6g, relative error %.2g\n", row.adjoint,
                row.finite_difference, row.relative_error);
    CHECK(row.relative_error < 1e-3);
    CHECK(std::abs(row.finite_difference) > 0);
  }
}

// metallicRoughnessTexture (linear; roughness in G, metallic in B, times the factors): one-channel
// bitmaps <material>.roughness (GGX α = roughness²) and <material>.metallic; the blend unless every
// metallic texel is 0 or 1. It shares the material's uv set like the other textures.
TEST_CASE("metallic-roughness textures become roughness and metallic bitmaps", "[gltf]") {
  TempDir tmp;
  auto quad_with = [&](const std::string& name, const std::string& mr_texture, double metallic_factor) {
    const std::string file = write_emissive_quad(tmp, name);
    // The quad's emissive material gets a metallic-roughness texture (image 1) instead.
    replace_in_file(file, R"("metallicFactor": 0)",
                    "\"metallicFactor\": " + std::to_string(metallic_factor) +
                        ", \"roughnessFactor\": 0.5, \"metallicRoughnessTexture\": " + mr_texture);
    replace_in_file(
        file, R"("textures": [{"source": 0}], "images": [{"uri": "emit.png"}])",
        R"("textures": [{"source": 0}, {"source": 1}], "images": [{"uri": "emit.png"}, {"uri": "mr.png"}])");
    return file;
  };
  Image mr(2, 1, 3);
  mr.at(0, 0, 1) = 1.f;  // left: roughness 1, metallic 0
  mr.at(1, 0, 2) = 1.f;  // right: roughness 0, metallic 1
  write_image(tmp("mr.png"), mr);
  {
    auto scene = load_scene(quad_with("mixed.gltf", R"({"index": 1, "texCoord": 1})", 1.0));
    const Material& m = scene->materials.at(0);
    CHECK(m.type == BsdfType::MetallicRoughness);
    const Param& rough = scene->params[m.roughness.param];
    const Param& metal = scene->params[m.metallic.param];
    CHECK(rough.name == "glow.roughness");
    CHECK(rough.shape == std::vector<int>{1, 2, 1});
    CHECK(rough.value == std::vector<float>{0.25f, 0.f});  // (1 · 0.5)², (0 · 0.5)²
    CHECK(metal.name == "glow.metallic");
    CHECK(metal.value == std::vector<float>{0.f, 1.f});
    CHECK(m.roughness.bitmap);
    CHECK(m.metallic.bitmap);
    CHECK(scene->params.find("glow.base_color") >= 0);
    Camera& cam = scene->cameras[0];
    cam.width = cam.height = 16;
    cam.update();
    const Image img = render(*scene, {0, 4, 3, false});
    for (float v : img.data) REQUIRE(std::isfinite(v));
  }
  {
    // The factor scales the texels: metallic 0 everywhere is the plain plastic (no metallic parameter).
    auto scene = load_scene(quad_with("plastic.gltf", R"({"index": 1, "texCoord": 1})", 0.0));
    CHECK(scene->materials.at(0).type == BsdfType::RoughPlastic);
    CHECK(scene->params.find("glow.metallic") < 0);
    CHECK(scene->params[scene->materials.at(0).roughness.param].shape == std::vector<int>{1, 2, 1});
  }
  // Bad input: a texture index past the file's textures is a one-line error, not a read past them.
  try {
    load_scene(quad_with("missing.gltf", R"({"index": 7, "texCoord": 1})", 1.0));
    FAIL("a missing metallic-roughness texture accepted");
  } catch (const InputError& e) {
    CHECK(std::string(e.what()).find("metallic-roughness texture references a missing texture") != std::string::npos);
    CHECK(std::string(e.what()).find('\n') == std::string::npos);
  }
  try {
    load_scene(quad_with("sets.gltf", R"({"index": 1, "texCoord": 0})", 1.0));
    FAIL("two uv sets accepted");
  } catch (const InputError& e) {
    CHECK(std::string(e.what()).find("emissive and metallic-roughness textures use different uv sets") !=
          std::string::npos);
  }
}

namespace {
// The message of the InputError loading `path` throws ("" when it loads).
std::string load_error(const std::string& path) {
  try {
    load_scene(path);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

// scenes/gltf/scene.gltf with `edit` applied to its JSON, written next to copies of its buffer and
// texture in `tmp`.
std::string bundled_variant(const TempDir& tmp, const std::string& name,
                            const std::function<void(nlohmann::json&)>& edit) {
  const fs::path dir = fs::path(BL_SOURCE_DIR) / "scenes" / "gltf";
  for (const char* f : {"scene.bin", "checker.png"}) fs::copy_file(dir / f, tmp(f), fs::copy_options::skip_existing);
  std::ifstream in(dir / "scene.gltf");
  nlohmann::json gltf = nlohmann::json::parse(in);
  edit(gltf);
  std::ofstream(tmp(name)) << gltf.dump();
  return tmp(name);
}

// What `f` writes to stderr (file descriptor 2) while it runs.
template <class F>
std::string stderr_of(const TempDir& tmp, F&& f) {
  std::fflush(stderr);
  const int saved = ::dup(2);
  std::FILE* capture = std::fopen(tmp("stderr.txt").c_str(), "w+");
  ::dup2(::fileno(capture), 2);
  auto restore = [&] {
    std::fflush(stderr);
    ::dup2(saved, 2);
    ::close(saved);
  };
  try {
    f();
  } catch (...) {
    restore();
    std::fclose(capture);
    throw;
  }
  restore();
  std::fclose(capture);
  std::ifstream text(tmp("stderr.txt"));
  return std::string((std::istreambuf_iterator<char>(text)), std::istreambuf_iterator<char>());
}
}  // namespace

TEST_CASE("glTF input the specification forbids is a one-line error naming the file", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  struct Case {
    const char* name;
    std::function<void(json&)> edit;
    const char* message;
  };
  const Case cases[] = {
      // Accessors inside their buffer views, with strides that hold an element.
      {"stride16", [](json& s) { s["bufferViews"][0]["byteStride"] = 16; },
       "accessor 0 reads past the end of its buffer view"},
      {"stride4", [](json& s) { s["bufferViews"][0]["byteStride"] = 4; },
       "byteStride 4 of buffer view 0 is less than the element size (12 bytes)"},
      {"offset", [](json& s) { s["accessors"][0]["byteOffset"] = 4; },
       "accessor 0 reads past the end of its buffer view"},
      // Node transforms.
      {"rot100",
       [](json& s) {
         s["nodes"][2]["rotation"] = {0, 100, 0, 0};
       },
       "node 2 ('gold_cube'): rotation is not a unit quaternion"},
      {"rot0",
       [](json& s) {
         s["nodes"][2]["rotation"] = {0, 0, 0, 0};
       },
       "rotation is not a unit quaternion"},
      {"matrix15",
       [](json& s) {
         s["nodes"][2].erase("rotation");
         s["nodes"][2].erase("translation");
         s["nodes"][2]["matrix"] = std::vector<double>(15, 1.0);
       },
       "node 2 ('gold_cube'): matrix needs 16 numbers, not 15"},
      {"rotation3",
       [](json& s) {
         s["nodes"][2]["rotation"] = {0, 0, 1};
       },
       "rotation needs 4 numbers, not 3"},
      {"translation2",
       [](json& s) {
         s["nodes"][2]["translation"] = {0, 1};
       },
       "translation needs 3 numbers, not 2"},
      {"scale4",
       [](json& s) {
         s["nodes"][3]["scale"] = {1, 1, 1, 1};
       },
       "scale needs 3 numbers, not 4"},
      {"projective",
       [](json& s) {
         s["nodes"][2].erase("rotation");
         s["nodes"][2].erase("translation");
         s["nodes"][2]["matrix"] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.5, 0, 0, 0, 1};  // column-major
       },
       "matrix is not affine"},
      {"matrix_and_trs",  // node 2 keeps its rotation and translation
       [](json& s) { s["nodes"][2]["matrix"] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1}; },
       "node 2 ('gold_cube'): has both a matrix and translation/rotation/scale"},
      // Materials, attributes, samplers.
      {"strength",
       [](json& s) { s["materials"][3]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] = -2; },
       "material 'lamp': KHR_materials_emissive_strength emissiveStrength must be a number"},
      {"strength_text",
       [](json& s) { s["materials"][3]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] = "x"; },
       "emissiveStrength must be a number"},
      {"position_ushort", [](json& s) { s["accessors"][0]["componentType"] = 5123; },
       "mesh 'ground': POSITION (accessor 0): component type UNSIGNED_SHORT needs the KHR_mesh_quantization "
       "extension"},
      {"normal_ubyte",
       [](json& s) {
         s["accessors"][1]["componentType"] = 5121;
         s["extensionsUsed"] = {"KHR_mesh_quantization"};
       },
       "NORMAL (accessor 1): component type UNSIGNED_BYTE is not allowed"},
      {"wrap", [](json& s) { s["samplers"][0]["wrapT"] = 12345; }, "sampler 0: wrap mode 12345 is not one of"},
      {"wrap_st", [](json& s) { s["samplers"][0]["wrapT"] = 33071; }, "sampler 0: wrapS 10497 and wrapT 33071 differ"},
      {"material", [](json& s) { s["meshes"][0]["primitives"][0]["material"] = 55; },
       "primitive references a missing material"},
      // Negative: caught in the JSON (tinygltf read -1 as no material, which rendered the default,
      // and -5 as an index the loader then found out of range).
      {"material_negative", [](json& s) { s["meshes"][0]["primitives"][0]["material"] = -1; },
       "mesh 0 ('ground') primitive 0: material must be a non-negative integer, not -1"},
      {"view_offset", [](json& s) { s["bufferViews"][1]["byteOffset"] = -48; },
       "buffer view 1: byteOffset must be a non-negative integer, not -48"},
      {"no_primitives", [](json& s) { s["meshes"][0]["primitives"] = json::array(); },
       "mesh 0 ('ground'): has no primitives"},
      {"texcoord", [](json& s) { s["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["texCoord"] = 1; },
       "mesh 'ground' primitive 0: its material's textures read TEXCOORD_1, which it does not have"},
      {"mode", [](json& s) { s["meshes"][0]["primitives"][0]["mode"] = 7; },
       "mesh 'ground' primitive 0: invalid mode 7 (expected 0 to 6)"},
      // Cameras.
      {"aspect0", [](json& s) { s["cameras"][0]["perspective"]["aspectRatio"] = 0; },
       "camera 0: aspectRatio must be a positive number"},
      {"znear0", [](json& s) { s["cameras"][0]["perspective"]["znear"] = 0; }, "camera 0: znear must be positive"},
      {"yfov", [](json& s) { s["cameras"][0]["perspective"]["yfov"] = 3.14; }, "at most 179.9°"},
  };
  for (const Case& c : cases) {
    CAPTURE(c.name);
    const std::string e = load_error(bundled_variant(tmp, std::string(c.name) + ".gltf", c.edit));
    CHECK_THAT(e, Catch::Contains(c.message) && Catch::Contains(std::string(c.name) + ".gltf: "));
    CHECK(e.find('\n') == std::string::npos);
  }
  // What the specification allows still loads: a stride of exactly one element, integer
  // positions with KHR_mesh_quantization, a rotation rounded to six digits (normalized, so it does
  // not scale the mesh).
  CHECK(load_error(bundled_variant(tmp, "stride12.gltf", [](json& s) {
          s["bufferViews"][0]["byteStride"] = 12;
        })).empty());
  // A camera named like a mesh gets a name of its own: both have pose parameters named after
  // them ("gold_cube.rotate"), and the camera's used to be dropped without a word.
  {
    auto scene =
        load_scene(bundled_variant(tmp, "camera_name.gltf", [](json& s) { s["cameras"][0]["name"] = "gold_cube"; }));
    REQUIRE(scene->cameras.size() == 1);
    CHECK(scene->cameras[0].name == "gold_cube_2");
    CHECK(scene->params.find("gold_cube.rotate") >= 0);
    CHECK(scene->params.find("gold_cube_2.rotate") >= 0);
    CHECK(scene->params.find("gold_cube_2.origin") >= 0);
  }
  // Mirrored repeat (33648) is read as such: it fell back to repeat.
  {
    auto scene = load_scene(bundled_variant(
        tmp, "mirror.gltf", [](json& s) { s["samplers"][0]["wrapS"] = s["samplers"][0]["wrapT"] = 33648; }));
    bool mirrored = false;
    for (const Material& m : scene->materials)
      mirrored = mirrored || (m.albedo.bitmap && m.albedo.wrap == Wrap::Mirror);
    CHECK(mirrored);
  }
  const auto gold_cube = [&](const std::string& name, double scale) {
    auto scene = load_scene(bundled_variant(tmp, name, [&](json& s) {
      for (auto& q : s["nodes"][2]["rotation"]) q = q.get<double>() * scale;
    }));
    REQUIRE(scene->meshes.size() >= 2);
    return scene->meshes[1].positions;
  };
  const std::vector<Vec3f> unit = gold_cube("unit.gltf", 1.0), drift = gold_cube("drift.gltf", 1.0005);
  REQUIRE(unit.size() == drift.size());
  for (size_t v = 0; v < unit.size(); ++v) CHECK(length(unit[v] - drift[v]) < 1e-5f);
}

namespace {
// A 2 × 2 quad facing +z drawn as one primitive of `mode` (4 TRIANGLES as two triangles, 5 a
// strip, 6 a fan), indexed or not, plus a LINES primitive when `lines`.
std::string write_mode_quad(const TempDir& tmp, const std::string& name, int mode, bool indexed, bool lines = false) {
  using nlohmann::json;
  // Corner order per mode: a strip zigzags, a fan goes round.
  const std::vector<std::vector<float>> corners =
      mode == 5 ? std::vector<std::vector<float>>{{-1, -1, 0}, {1, -1, 0}, {-1, 1, 0}, {1, 1, 0}}
                : std::vector<std::vector<float>>{{-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}};
  std::vector<float> pos;
  std::vector<uint16_t> idx;
  if (mode == 4 && !indexed) {
    for (int c : {0, 1, 2, 0, 2, 3}) pos.insert(pos.end(), corners[size_t(c)].begin(), corners[size_t(c)].end());
  } else {
    for (const auto& c : corners) pos.insert(pos.end(), c.begin(), c.end());
    idx = mode == 4 ? std::vector<uint16_t>{0, 1, 2, 0, 2, 3} : std::vector<uint16_t>{0, 1, 2, 3};
  }
  const size_t pos_bytes = pos.size() * 4, idx_bytes = idx.size() * 2;
  std::ofstream bin(tmp(name + ".bin"), std::ios::binary);
  bin.write(reinterpret_cast<const char*>(pos.data()), std::streamsize(pos_bytes));
  bin.write(reinterpret_cast<const char*>(idx.data()), std::streamsize(idx_bytes));
  bin.close();
  json prim = {{"attributes", {{"POSITION", 0}}}, {"mode", mode}};
  if (indexed) prim["indices"] = 1;
  // Arrays of one element spelled out: a one-element brace list is an array under GCC and the
  // element itself under clang (nlohmann's initializer-list rules).
  json prims = json::array({prim});
  if (lines) prims.push_back({{"attributes", {{"POSITION", 0}}}, {"mode", 1}});
  json scene = json::object(), node = json::object(), mesh = json::object(), buffer = json::object();
  scene["nodes"] = json::array({0});
  node["mesh"] = 0;
  mesh["name"] = "quad";
  mesh["primitives"] = prims;
  buffer["uri"] = name + ".bin";
  buffer["byteLength"] = pos_bytes + idx_bytes;
  const json gltf = {{"asset", {{"version", "2.0"}}},
                     {"scene", 0},
                     {"scenes", json::array({scene})},
                     {"nodes", json::array({node})},
                     {"meshes", json::array({mesh})},
                     {"buffers", json::array({buffer})},
                     {"bufferViews",
                      {{{"buffer", 0}, {"byteOffset", 0}, {"byteLength", pos_bytes}},
                       {{"buffer", 0}, {"byteOffset", pos_bytes}, {"byteLength", std::max<size_t>(idx_bytes, 2)}}}},
                     {"accessors",
                      {{{"bufferView", 0},
                        {"componentType", 5126},
                        {"count", pos.size() / 3},
                        {"type", "VEC3"},
                        {"min", {-1, -1, 0}},
                        {"max", {1, 1, 0}}},
                       {{"bufferView", 1}, {"componentType", 5123}, {"count", idx.size()}, {"type", "SCALAR"}}}}};
  std::ofstream(tmp(name)) << gltf.dump();
  return tmp(name);
}
}  // namespace

TEST_CASE("triangle strips and fans become triangles facing one way; points and lines are skipped with a warning",
          "[gltf]") {
  TempDir tmp;
  for (const int mode : {4, 5, 6})
    for (const bool indexed : {true, false}) {
      if (mode != 4 && !indexed) continue;  // unindexed strips and fans: below
      CAPTURE(mode, indexed);
      auto scene =
          load_scene(write_mode_quad(tmp, "m" + std::to_string(mode) + (indexed ? "i" : "") + ".gltf", mode, indexed));
      REQUIRE(scene->meshes.size() == 1);
      const Mesh& m = scene->meshes[0];
      REQUIRE(m.triangle_count() == 2);
      float area = 0.f;
      for (size_t t = 0; t < 2; ++t) {
        area += m.triangle_area(t);
        CHECK(m.face_normals[t].z == Approx(1.f));  // counter-clockwise seen from +z, as drawn
      }
      CHECK(area == Approx(4.f));
    }
  // Unindexed strips and fans read their vertices in order, like indices 0, 1, 2, ...
  for (const int mode : {5, 6}) {
    CAPTURE(mode);
    const std::string file = write_mode_quad(tmp, "u" + std::to_string(mode) + ".gltf", mode, true);
    std::ifstream in(file);
    nlohmann::json j = nlohmann::json::parse(in);
    j["meshes"][0]["primitives"][0].erase("indices");
    std::ofstream(file) << j.dump();
    auto scene = load_scene(file);
    REQUIRE(scene->meshes[0].triangle_count() == 2);
    for (size_t t = 0; t < 2; ++t) CHECK(scene->meshes[0].face_normals[t].z == Approx(1.f));
  }
  // A mesh with a line primitive: its triangles load, and one warning names the line primitive,
  // printed after the load (for a scene and for a JSON scene's glTF shape alike).
  const std::string mixed = write_mode_quad(tmp, "lines.gltf", 4, true, true);
  std::unique_ptr<Scene> scene;
  std::string warning = stderr_of(tmp, [&] { scene = load_scene(mixed); });
  CHECK(scene->meshes.size() == 1);
  CHECK(warning == "backlight: " + mixed + ": warning: mesh 'quad' primitive 1: points/lines are not rendered\n");
  const std::string json_scene = tmp("with_gltf.json");
  std::ofstream(json_scene) << R"({"cameras": [{"name": "c", "origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0],
    "fov": 40, "resolution": [8, 8]}], "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
    "shapes": [{"name": "q", "type": "gltf", "file": "lines.gltf", "material": "m"}],
    "environment": {"type": "constant", "radiance": [1, 1, 1]}})";
  warning = stderr_of(tmp, [&] { load_scene(json_scene); });
  CHECK(warning == "backlight: " + mixed + ": warning: mesh 'quad' primitive 1: points/lines are not rendered\n");
  // A scene that fails later keeps its one error line: no warning before it.
  std::ofstream(json_scene) << R"({"cameras": [{"name": "c", "origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0],
    "fov": 40, "resolution": [8, 8]}], "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
    "shapes": [{"name": "q", "type": "gltf", "file": "lines.gltf", "material": "m"},
               {"name": "r", "type": "rectangle", "material": "nope"}],
    "environment": {"type": "constant", "radiance": [1, 1, 1]}})";
  warning = stderr_of(tmp, [&] { CHECK_THROWS_WITH(load_scene(json_scene), Catch::Contains("unknown material")); });
  CHECK(warning.empty());
}

TEST_CASE("a JSON transform matrix must be affine", "[gltf][errors]") {
  TempDir tmp;
  write_cube(tmp, "cube.gltf");
  auto scene_with = [&](const std::string& last_row) {
    std::ofstream(tmp("m.json")) << R"({"cameras": [{"name": "c", "origin": [0, 0, 5], "target": [0, 0, 0],
      "up": [0, 1, 0], "fov": 40, "resolution": [8, 8]}], "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
      "shapes": [{"name": "s", "type": "gltf", "file": "cube.gltf", "material": "m",
                  "transform": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], )" +
                                        last_row + R"(]}}],
      "environment": {"type": "constant", "radiance": [1, 1, 1]}})";
    return load_error(tmp("m.json"));
  };
  CHECK(scene_with("[0, 0, 0, 1]").empty());
  for (const char* row : {"[0, 0, 0, 2]", "[0, 0.5, 0, 1]"}) {
    CAPTURE(row);
    CHECK_THAT(scene_with(row), Catch::Contains("m.json") && Catch::Contains("/shapes/0/transform/matrix") &&
                                    Catch::Contains("the last row must be [0, 0, 0, 1]"));
  }
}

TEST_CASE("a binary glTF of a version other than 2 is refused", "[gltf][errors]") {
  TempDir tmp;
  // The cube's JSON as the JSON chunk of a GLB (its buffer stays the external cube.bin).
  std::ifstream in(write_cube(tmp, "cube.gltf"));
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  while (text.size() % 4) text += ' ';
  auto write_glb = [&](const std::string& name, uint32_t version) {
    const uint32_t header[5] = {0x46546C67u /* glTF */, version, uint32_t(20 + text.size()), uint32_t(text.size()),
                                0x4E4F534Au /* JSON */};
    std::ofstream glb(tmp(name), std::ios::binary);
    glb.write(reinterpret_cast<const char*>(header), sizeof header);
    glb << text;
    return tmp(name);
  };
  CHECK(load_error(write_glb("v2.glb", 2)).empty());
  const std::string e = load_error(write_glb("v1.glb", 1));
  CHECK_THAT(e, Catch::Contains("v1.glb: invalid glTF: binary glTF version 1 (expected 2)"));
}

namespace {
// A glTF variant that must be refused: `message` is part of its one-line error.
struct RefusedVariant {
  const char* name;
  std::function<void(nlohmann::json&)> edit;
  const char* message;
};
void check_refused(const TempDir& tmp, const std::vector<RefusedVariant>& cases) {
  for (const RefusedVariant& c : cases) {
    CAPTURE(c.name);
    const std::string e = load_error(bundled_variant(tmp, std::string(c.name) + ".gltf", c.edit));
    CHECK_THAT(e, Catch::Contains(c.message) && Catch::Contains(std::string(c.name) + ".gltf: "));
    CHECK(e.find('\n') == std::string::npos);
  }
}
// The error of a bundled variant ("" when it loads).
std::string variant_error(const TempDir& tmp, const std::string& name,
                          const std::function<void(nlohmann::json&)>& edit) {
  return load_error(bundled_variant(tmp, name, edit));
}

// A PNG of `width` × `height` pixels of `channels` samples (3: RGB, 4: RGBA) of `bits` bits (8 or
// 16), row by row, its pixel data in one stored (uncompressed) deflate block: the 16-bit and alpha
// images write_image does not make.
std::string png_bytes(int width, int height, int channels, int bits, const std::vector<uint16_t>& samples) {
  auto crc32 = [](const std::string& bytes) {
    uint32_t c = 0xFFFFFFFFu;
    for (const unsigned char b : bytes) {
      c ^= b;
      for (int k = 0; k < 8; ++k) c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
    }
    return c ^ 0xFFFFFFFFu;
  };
  auto be32 = [](uint32_t v) { return std::string{char(v >> 24), char(v >> 16), char(v >> 8), char(v)}; };
  auto chunk = [&](const std::string& type, const std::string& data) {
    return be32(uint32_t(data.size())) + type + data + be32(crc32(type + data));
  };
  std::string raw;  // per row: filter type 0, then the samples, big-endian
  size_t k = 0;
  for (int y = 0; y < height; ++y) {
    raw += '\0';
    for (int x = 0; x < width * channels; ++x, ++k) {
      if (bits == 16) raw += char(samples[k] >> 8);
      raw += char(samples[k] & 0xFF);
    }
  }
  uint32_t a = 1, b = 0;  // Adler-32
  for (const unsigned char c : raw) a = (a + c) % 65521, b = (b + a) % 65521;
  const uint16_t n = uint16_t(raw.size()), not_n = uint16_t(~n);
  const std::string zlib = std::string("\x78\x01\x01", 3) + char(n & 0xFF) + char(n >> 8) + char(not_n & 0xFF) +
                           char(not_n >> 8) + raw + be32((b << 16) | a);
  const std::string header =
      be32(uint32_t(width)) + be32(uint32_t(height)) + char(bits) + char(channels == 4 ? 6 : 2) + std::string(3, '\0');
  return std::string("\x89PNG\r\n\x1a\n", 8) + chunk("IHDR", header) + chunk("IDAT", zlib) + chunk("IEND", "");
}
void write_file(const std::string& path, const std::string& bytes) { std::ofstream(path, std::ios::binary) << bytes; }
}  // namespace

TEST_CASE("glTF morph targets are refused unless their weights are all 0", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  // The gold cube's normals (accessor 5, 24 VEC3 floats) as a position target.
  const auto with_target = [](json& s) { s["meshes"][1]["primitives"][0]["targets"] = {{{"POSITION", 5}}}; };
  check_refused(tmp, {{"mesh_weight",
                       [&](json& s) {
                         with_target(s);
                         s["meshes"][1]["weights"] = {0.5};
                       },
                       "mesh 'gold_cube' primitive 0: morph targets with weights other than 0 (mesh weights) are not "
                       "supported"},
                      {"node_weight",
                       [&](json& s) {
                         with_target(s);
                         s["meshes"][1]["weights"] = {0.0};
                         s["nodes"][2]["weights"] = {1.0};
                       },
                       "morph targets with weights other than 0 (node 2 ('gold_cube') weights)"},
                      {"weight_count",
                       [&](json& s) {
                         with_target(s);
                         s["meshes"][1]["weights"] = {0.0, 0.0};
                       },
                       "mesh 'gold_cube' primitive 0: 2 mesh weights for 1 morph targets"}});
  // Weights of 0 (given or by default) move nothing: such a file loads, the node's weights
  // overriding the mesh's.
  CHECK(variant_error(tmp, "no_weights.gltf", with_target).empty());
  CHECK(variant_error(tmp, "zero_node_weights.gltf", [&](json& s) {
          with_target(s);
          s["meshes"][1]["weights"] = {1.0};
          s["nodes"][2]["weights"] = {0.0};
        }).empty());
}

TEST_CASE("a glTF node with a skin is refused", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(tmp, {{"skin",
                       [](json& s) {
                         // tinygltf requires inverseBindMatrices (the specification does not):
                         // one MAT4 of zeros (an accessor without a buffer view).
                         s["accessors"].push_back({{"componentType", 5126}, {"count", 1}, {"type", "MAT4"}});
                         s["skins"] = {{{"joints", {2}}, {"inverseBindMatrices", 16}}};
                         s["nodes"][2]["skin"] = 0;
                       },
                       "node 2 ('gold_cube'): skins (skeletal animation) are not supported"}});
}

TEST_CASE("glTF alphaMode MASK and BLEND are refused unless every alpha keeps the surface opaque",
          "[gltf][errors][material]") {
  TempDir tmp;
  using nlohmann::json;
  const auto gold = [](const char* mode, double alpha) {
    return [=](json& s) {
      s["materials"][1]["alphaMode"] = mode;
      s["materials"][1]["pbrMetallicRoughness"]["baseColorFactor"][3] = alpha;
    };
  };
  check_refused(
      tmp, {{"blend", gold("BLEND", 0.5),
             "mesh 'gold_cube' primitive 0: material 'gold': alphaMode BLEND blends where alpha < 1, and alpha here "
             "goes down to 0.5 (baseColorFactor alpha 0.5): backlight's surfaces are opaque"},
            {"mask", gold("MASK", 0.4),
             "material 'gold': alphaMode MASK cuts out where alpha < alphaCutoff 0.5, and alpha here goes down to 0.4"},
            {"mask_cutoff",
             [&](json& s) {
               gold("MASK", 0.6)(s);
               s["materials"][1]["alphaCutoff"] = 0.7;
             },
             "alphaMode MASK cuts out where alpha < alphaCutoff 0.7"}});
  // Alphas that change nothing load; OPAQUE ignores alpha, as glTF says.
  CHECK(variant_error(tmp, "blend1.gltf", gold("BLEND", 1.0)).empty());
  CHECK(variant_error(tmp, "mask06.gltf", gold("MASK", 0.6)).empty());
  CHECK(variant_error(tmp, "opaque0.gltf", gold("OPAQUE", 0.0)).empty());
  // The base-colour texture's alpha channel (8- and 16-bit), over every texel.
  for (const int bits : {8, 16}) {
    CAPTURE(bits);
    const uint16_t opaque = bits == 8 ? 255 : 65535;
    const std::string suffix = std::to_string(bits) + ".png";
    write_file(tmp("transparent" + suffix), png_bytes(2, 1, 4, bits, {200, 100, 50, opaque, 10, 20, 30, 0}));
    write_file(tmp("opaque" + suffix), png_bytes(2, 1, 4, bits, {200, 100, 50, opaque, 10, 20, 30, opaque}));
    const auto ground = [&](const std::string& image) {
      return [=](json& s) {
        s["images"][0]["uri"] = image;
        s["materials"][0]["alphaMode"] = "BLEND";
      };
    };
    CHECK_THAT(variant_error(tmp, "tex_alpha.gltf", ground("transparent" + suffix)),
               Catch::Contains("material 'ground': alphaMode BLEND blends where alpha < 1, and alpha here goes down "
                               "to 0 (base colour texture alpha down to 0)"));
    CHECK(variant_error(tmp, "tex_opaque.gltf", ground("opaque" + suffix)).empty());
  }
  // COLOR_0's alpha (a VEC4 with alpha 0.2 at one vertex).
  const std::string quad = write_coloured_quad(tmp, "alpha.gltf", "ubyte4_alpha");
  for (const char* mode : {"OPAQUE", "MASK", "BLEND"}) {
    CAPTURE(mode);
    std::ifstream in(quad);
    json gltf = json::parse(in);
    gltf["materials"][0]["alphaMode"] = mode;
    std::ofstream(tmp("alpha_mode.gltf")) << gltf.dump();
    const std::string e = load_error(tmp("alpha_mode.gltf"));
    if (std::string(mode) == "OPAQUE")
      CHECK(e.empty());
    else
      CHECK_THAT(e, Catch::Contains("and alpha here goes down to 0.2 (COLOR_0 alpha down to 0.2)"));
  }
}

TEST_CASE("glTF normal and occlusion textures are ignored with one warning per file", "[gltf]") {
  TempDir tmp;
  using nlohmann::json;
  std::string file = bundled_variant(tmp, "maps.gltf", [](json& s) {
    s["materials"][0]["normalTexture"] = {{"index", 0}};
    s["materials"][2]["occlusionTexture"] = {{"index", 0}, {"strength", 0.5}};
    s["materials"][3]["normalTexture"] = {{"index", 0}};
    s["materials"][3]["occlusionTexture"] = {{"index", 0}};
  });
  std::unique_ptr<Scene> scene;
  CHECK(stderr_of(tmp, [&] { scene = load_scene(file); }) ==
        "backlight: " + file +
            ": warning: material 'ground': normalTexture (shading uses the mesh's normals) is ignored (so are those "
            "of 2 more materials)\n");
  REQUIRE(scene);
  CHECK(scene->meshes.size() == 4);
  file = bundled_variant(tmp, "both.gltf", [](json& s) {
    s["materials"][2]["normalTexture"] = {{"index", 0}};
    s["materials"][2]["occlusionTexture"] = {{"index", 0}};
  });
  CHECK(stderr_of(tmp, [&] { load_scene(file); }) ==
        "backlight: " + file +
            ": warning: material 'blue_plastic': normalTexture (shading uses the mesh's normals) and occlusionTexture "
            "(path tracing computes occlusion itself) are ignored\n");
  // The bundled scene has neither: no warning.
  const std::string plain = bundled_variant(tmp, "plain.gltf", [](json&) {});
  CHECK(stderr_of(tmp, [&] { load_scene(plain); }).empty());
}

TEST_CASE("glTF cameras backlight cannot reproduce are refused: orthographic, mirrored, scaled to 0",
          "[gltf][errors][camera]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(
      tmp,
      {{"ortho",
        [](json& s) {
          s["cameras"][0] = {{"type", "orthographic"},
                             {"orthographic", {{"xmag", 1}, {"ymag", 1}, {"znear", 0.1}, {"zfar", 100}}}};
        },
        "camera 0: orthographic cameras are not supported (perspective ones are)"},
       {"mirror",
        [](json& s) {
          s["nodes"][5]["scale"] = {-1, 1, 1};
        },
        "camera 0: its node's world transform mirrors (determinant < 0)"},
       {"flat",
        [](json& s) {
          s["nodes"][5]["scale"] = {1, 0, 1};
        },
        "camera 0: its node's world transform scales to 0"},
       // tinygltf's own message spoke of an orthographic camera.
       {"yfov", [](json& s) { s["cameras"][0]["perspective"].erase("yfov"); }, "camera 0: perspective.yfov is missing"},
       {"znear", [](json& s) { s["cameras"][0]["perspective"].erase("znear"); },
        "camera 0: perspective.znear is missing"},
       {"perspective", [](json& s) { s["cameras"][0].erase("perspective"); },
        "camera 0: a perspective camera needs a perspective object"}});
  // An orthographic camera no node of the default scene uses is never rendered: it loads.
  CHECK(variant_error(tmp, "unused_ortho.gltf", [](json& s) {
          s["cameras"].push_back(
              {{"type", "orthographic"}, {"orthographic", {{"xmag", 1}, {"ymag", 1}, {"znear", 0.1}, {"zfar", 100}}}});
        }).empty());
}

TEST_CASE("a glTF zfar that clips the scene is refused; one beyond it is ignored", "[gltf][errors][camera]") {
  TempDir tmp;
  using nlohmann::json;
  const auto zfar = [](double z, double scale = 1) {
    return [=](json& s) {
      s["cameras"][0]["perspective"]["zfar"] = z;
      if (scale != 1) s["nodes"][5]["scale"] = {scale, scale, scale};
    };
  };
  // The ground's far corners lie at depth 9.88 from the camera.
  check_refused(tmp, {{"zfar5", zfar(5), "camera 0: zfar 5 clips shape 'ground' (at depth 9.87"},
                      {"zfar6", zfar(6), "camera 0: zfar 6 clips shape 'ground'"},
                      {"zfar_near", zfar(0.01), "camera 0: zfar must exceed znear"},
                      {"zfar0", zfar(0), "camera 0: zfar must be a positive number"}});
  CHECK(variant_error(tmp, "zfar20.gltf", zfar(20)).empty());
  // Depth is measured in the camera's view space: a camera node scaled by 2 sees the ground at
  // depth 4.94.
  CHECK(variant_error(tmp, "zfar6_scaled.gltf", zfar(6, 2)).empty());
}

TEST_CASE("glTF NEAREST magnification is refused", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(tmp, {{"nearest", [](json& s) { s["samplers"][0]["magFilter"] = 9728; },
                       "sampler 0: magFilter 9728 (NEAREST) is not supported (bitmap textures are bilinear)"}});
}

TEST_CASE("glTF files of another major version, or needing a newer reader, are refused", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(tmp, {{"v1", [](json& s) { s["asset"]["version"] = "1.0"; },
                       "asset.version 1.0: backlight reads glTF 2.x files only"},
                      {"v3", [](json& s) { s["asset"]["version"] = "3.0"; }, "asset.version 3.0"},
                      {"min21", [](json& s) { s["asset"]["minVersion"] = "2.1"; },
                       "asset.minVersion 2.1: the file needs a glTF reader of that version (backlight reads glTF 2.0)"},
                      {"text", [](json& s) { s["asset"]["version"] = "two"; },
                       "asset.version \"two\" is not of the form major.minor"}});
  // A newer minor version only adds what a 2.0 reader may ignore.
  CHECK(variant_error(tmp, "v21.gltf", [](json& s) { s["asset"]["version"] = "2.1"; }).empty());
  CHECK(variant_error(tmp, "min20.gltf", [](json& s) { s["asset"]["minVersion"] = "2.0"; }).empty());
}

TEST_CASE("a glTF image file that is missing is named as missing", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(tmp, {{"missing", [](json& s) { s["images"][0]["uri"] = "nope.png"; },
                       "base colour texture: image 0 'nope.png': file not found or unreadable"}});
}

TEST_CASE("16-bit PNG textures in glTF are read at full precision", "[gltf]") {
  TempDir tmp;
  using nlohmann::json;
  const std::vector<uint16_t> samples = {65535, 32768, 0, 1000, 50000, 65535};
  write_file(tmp("deep.png"), png_bytes(2, 1, 3, 16, samples));
  auto scene = load_scene(bundled_variant(tmp, "deep.gltf", [](json& s) { s["images"][0]["uri"] = "deep.png"; }));
  const int albedo = scene->params.find("ground.albedo");
  REQUIRE(albedo >= 0);
  REQUIRE(scene->params[albedo].shape == std::vector<int>{1, 2, 3});
  // sRGB decoded from value / 65535, as 8-bit textures are from value / 255.
  for (size_t k = 0; k < samples.size(); ++k) {
    CAPTURE(k);
    CHECK(scene->params[albedo].value[k] == srgb_to_linear(float(samples[k]) / 65535.f));
  }
  // An 8-bit image of the same shape reads value / 255, as before.
  write_file(tmp("shallow.png"), png_bytes(2, 1, 3, 8, {255, 128, 0, 4, 195, 255}));
  scene = load_scene(bundled_variant(tmp, "shallow.gltf", [](json& s) { s["images"][0]["uri"] = "shallow.png"; }));
  CHECK(scene->params[scene->params.find("ground.albedo")].value[1] == srgb_to_linear(128.f / 255.f));
}

TEST_CASE("broken glTF index accessors are named", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(
      tmp, {{"count5", [](json& s) { s["accessors"][3]["count"] = 5; },
             "mesh 'ground' primitive 0: indices (accessor 3): count 5 is not a multiple of 3 (mode TRIANGLES)"},
            {"vec3",
             [](json& s) {
               s["accessors"][3]["type"] = "VEC3";
               s["accessors"][3]["count"] = 2;
             },
             "mesh 'ground' primitive 0: indices (accessor 3): type VEC3 (expected SCALAR)"},
            {"float", [](json& s) { s["accessors"][3]["componentType"] = 5126; },
             "indices (accessor 3): component type FLOAT (expected UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT)"},
            {"unindexed", [](json& s) { s["meshes"][0]["primitives"][0].erase("indices"); },
             "mesh 'ground' primitive 0: POSITION (accessor 0) without indices: count 4 is not a multiple of 3"}});
}

TEST_CASE("a glTF accessor without a buffer view reads as zeros", "[gltf]") {
  TempDir tmp;
  using nlohmann::json;
  auto scene =
      load_scene(bundled_variant(tmp, "zero_uvs.gltf", [](json& s) { s["accessors"][2].erase("bufferView"); }));
  const Mesh& ground = scene->meshes[0];
  REQUIRE(ground.uvs.size() == 4);
  for (const Vec2f& uv : ground.uvs) CHECK((uv.x == 0.f && uv.y == 0.f));
}

TEST_CASE("glTF nodes scaled to 0 are skipped with one warning per file", "[gltf]") {
  TempDir tmp;
  using nlohmann::json;
  // The plastic box alone, then the parent of both cubes, then the light (an emitter).
  std::string file = bundled_variant(tmp, "box0.gltf", [](json& s) { s["nodes"][3]["scale"] = {0, 0, 0}; });
  std::unique_ptr<Scene> scene;
  CHECK(stderr_of(tmp, [&] { scene = load_scene(file); }) ==
        "backlight: " + file +
            ": warning: node 3 ('plastic_box'): its world transform scales to 0 (determinant 0), so its mesh "
            "'plastic_box' is not rendered\n");
  REQUIRE(scene);
  std::vector<std::string> names;
  for (const Mesh& m : scene->meshes) names.push_back(m.name);
  CHECK(names == std::vector<std::string>{"ground", "gold_cube", "light"});
  file = bundled_variant(tmp, "objects0.gltf", [](json& s) { s["nodes"][1]["scale"] = {0, 0, 0}; });
  scene.reset();
  CHECK(stderr_of(tmp, [&] { scene = load_scene(file); }) ==
        "backlight: " + file +
            ": warning: node 2 ('gold_cube'): its world transform scales to 0 (determinant 0), so its mesh "
            "'gold_cube' is not rendered (nor are the meshes of 1 more such nodes)\n");
  REQUIRE(scene);
  CHECK(scene->meshes.size() == 2);
  file = bundled_variant(tmp, "light0.gltf", [](json& s) { s["nodes"][4]["scale"] = {0, 0, 0}; });
  scene.reset();
  CHECK_THAT(stderr_of(tmp, [&] { scene = load_scene(file); }), Catch::Contains("so its mesh 'light' is not rendered"));
  REQUIRE(scene);
  CHECK(scene->area_emitters.empty());
}

TEST_CASE("malformed optional glTF properties are refused, not defaulted", "[gltf][errors]") {
  TempDir tmp;
  using nlohmann::json;
  check_refused(
      tmp,
      {{"byte_offset", [](json& s) { s["accessors"][0]["byteOffset"] = -4; },
        "accessor 0: byteOffset must be a non-negative integer, not -4"},
       {"rotation", [](json& s) { s["nodes"][2]["rotation"] = "abc"; },
        "node 2 ('gold_cube'): rotation must be an array of numbers, not \"abc\""},
       {"scale_text",
        [](json& s) {
          s["nodes"][3]["scale"] = {1, "x", 1};
        },
        "node 3 ('plastic_box'): scale must be"},
       {"scene", [](json& s) { s["scene"] = -1; }, "scene must be a non-negative integer, not -1"},
       {"texture", [](json& s) { s["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"] = -2; },
        "material 0 ('ground'): baseColorTexture: index must be a non-negative integer, not -2"},
       {"camera", [](json& s) { s["nodes"][5]["camera"] = -1; },
        "node 5 ('camera'): camera must be a non-negative integer, not -1"},
       {"mesh", [](json& s) { s["nodes"][0]["mesh"] = -7; }, "node 0 ('ground'): mesh must be"},
       {"indices", [](json& s) { s["meshes"][0]["primitives"][0]["indices"] = -1; },
        "mesh 0 ('ground') primitive 0: indices must be a non-negative integer, not -1"},
       {"emissive",  // the lamp went dark without a word
        [](json& s) {
          s["materials"][3]["emissiveFactor"] = {-1, 0, 0};
        },
        "material 3 ('lamp'): emissiveFactor values must be ≥ 0, not [-1,0,0]"},
       {"base_factor",  // with a texture (without one, the parameter's range refused it already)
        [](json& s) {
          s["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] = {2, 1, 1, 1};
        },
        "material 0 ('ground'): baseColorFactor values must be in [0, 1], not [2,1,1,1]"},
       {"alpha_mode", [](json& s) { s["materials"][1]["alphaMode"] = "CUTOUT"; },
        "material 1 ('gold'): alphaMode \"CUTOUT\" is not OPAQUE, MASK or BLEND"},
       {"alpha_cutoff", [](json& s) { s["materials"][1]["alphaCutoff"] = -1; },
        "material 1 ('gold'): alphaCutoff must be a number ≥ 0, not -1"},
       // Factors of another JSON type: tinygltf used its default in their place, without a word
       // (a roughness "0.2" rendered as 1, a metallic "0" as a metal, emission "1 1 1" as none).
       {"roughness_text", [](json& s) { s["materials"][0]["pbrMetallicRoughness"]["roughnessFactor"] = "0.2"; },
        "material 0 ('ground'): roughnessFactor must be a number in [0, 1], not \"0.2\""},
       {"metallic_text", [](json& s) { s["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] = "0"; },
        "material 0 ('ground'): metallicFactor must be a number in [0, 1], not \"0\""},
       {"base_text", [](json& s) { s["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] = "0.2 0.3 0.4 1"; },
        "material 0 ('ground'): baseColorFactor must be an array of 4 numbers"},
       {"emissive_text", [](json& s) { s["materials"][3]["emissiveFactor"] = "1 1 1"; },
        "material 3 ('lamp'): emissiveFactor must be an array of 3 numbers"}});
}
