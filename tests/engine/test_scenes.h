#pragma once
// Small scenes generated at test time (into a temporary folder), so gradient tests exercise every
// kernel kind: bitmap and constant textures, diffuse/conductor/plastic BSDFs (and, optionally,
// their metallic-roughness blend), an area light and an importance-sampled environment map, with
// NEE, MIS and Russian roulette all active.
#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "engine/core/math.h"
#include "engine/io/image_io.h"

namespace bl::test {

// A scratch folder for this test process, removed when the process exits normally (a failing
// test's folder is removed too; the failure message carries what is needed to reproduce it).
inline std::string temp_dir(const std::string& name) {
  struct Cleanup {
    std::vector<std::filesystem::path> dirs;
    ~Cleanup() {
      std::error_code ec;
      for (const auto& d : dirs) std::filesystem::remove_all(d, ec);
    }
  };
  static Cleanup cleanup;
  auto dir = std::filesystem::temp_directory_path() / ("backlight-test-" + name + "-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  cleanup.dirs.push_back(dir);
  return dir.string();
}

struct OpenSceneOptions {
  int resolution = 32;
  int max_depth = 5;
  int rr_depth = 2;
  bool environment = true;
  bool area_light = true;
  // A fourth object in front: a cube of glTF's metallic-roughness blend ("alloy", metallic 0.4).
  bool alloy = false;
};

// A textured floor with a plastic and a conductor cube under a small area light and a sky map.
inline std::string write_open_scene(const std::string& dir, const OpenSceneOptions& o = {}) {
  // 16x16 floor texture with structure, 16x8 sky with a bright "sun" texel block.
  Image floor(16, 16, 3);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) {
      floor.at(x, y, 0) = 0.2f + 0.6f * float(x) / 15.f;
      floor.at(x, y, 1) = ((x / 4 + y / 4) % 2) ? 0.7f : 0.25f;
      floor.at(x, y, 2) = 0.3f + 0.3f * std::sin(float(y));
    }
  write_image(dir + "/floor.exr", floor);
  Image sky(16, 8, 3);
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 16; ++x)
      for (int c = 0; c < 3; ++c) sky.at(x, y, c) = 0.3f + 0.1f * float(c) + ((x == 5 && y == 2) ? 20.f : 0.f);
  write_image(dir + "/sky.exr", sky);
  std::string r = std::to_string(o.resolution);
  std::string json = R"({
  "integrator": {"spp": 4, "max_depth": )" +
                     std::to_string(o.max_depth) + R"(, "rr_depth": )" + std::to_string(o.rr_depth) + R"(, "seed": 3},
  "cameras": [{"origin": [0, 1.6, 4], "target": [0, 0, 0], "fov": 50, "resolution": [)" +
                     r + "," + r + R"(]}],
  "materials": {
    "floor": {"type": "diffuse", "albedo": {"type": "bitmap", "file": "floor.exr", "wrap": "repeat"}},
    "plastic": {"type": "roughplastic", "albedo": [0.2, 0.4, 0.7], "roughness": 0.3},
    "metal": {"type": "roughconductor", "specular": [0.9, 0.7, 0.4], "roughness": 0.25},
    "white": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]})" +
                     (o.alloy ? R"(,
    "alloy": {"type": "metallic_roughness", "base_color": [0.9, 0.6, 0.3], "roughness": 0.3, "metallic": 0.4})"
                              : "") +
                     R"(
  },
  "shapes": [
    {"name": "floor", "type": "rectangle", "material": "floor",
     "transform": {"scale": 2, "rotate": {"axis": [1, 0, 0], "angle": -90}}},
    {"name": "box", "type": "cube", "material": "plastic",
     "transform": {"scale": 0.4, "rotate": {"axis": [0, 1, 0], "angle": 30}, "translate": [-0.6, 0.4, 0]}},
    {"name": "ball", "type": "cube", "material": "metal",
     "transform": {"scale": 0.35, "rotate": {"axis": [1, 1, 0], "angle": 40}, "translate": [0.7, 0.45, 0.3]}})" +
                     (o.alloy ? R"(,
    {"name": "alloy_box", "type": "cube", "material": "alloy",
     "transform": {"scale": 0.3, "rotate": {"axis": [0, 1, 0], "angle": -25}, "translate": [0.05, 0.3, 1.0]}})"
                              : "") +
                     (o.area_light ? R"(,
    {"name": "light", "type": "rectangle", "material": "white", "emitter": {"radiance": [6, 5, 4]},
     "transform": {"scale": 0.4, "rotate": {"axis": [1, 0, 0], "angle": 90}, "translate": [0, 2.2, 0]}})"
                                   : "") +
                     R"(
  ])" +
                     (o.environment ? R"(,
  "environment": {"type": "envmap", "file": "sky.exr", "scale": 1})"
                                    : "") +
                     "\n}\n";
  std::ofstream(dir + "/scene.json") << json;
  return dir + "/scene.json";
}

// A smooth-shaded dome as a JSON mesh shape named "dome": a 12×12 grid over [−1.5, 1.5]² at
// z = −0.2 (x² + y²) with analytic vertex normals, or with `area_weighted` the grid's
// area-weighted ones.
inline nlohmann::json dome_shape(const std::string& material, bool area_weighted = false) {
  nlohmann::json positions = nlohmann::json::array(), normals = nlohmann::json::array(),
                 indices = nlohmann::json::array();
  const int n = 12;
  for (int i = 0; i <= n; ++i)
    for (int k = 0; k <= n; ++k) {
      const double x = -1.5 + 3.0 * i / n, y = -1.5 + 3.0 * k / n;
      positions.push_back({x, y, -0.2 * (x * x + y * y)});
      const Vec3d normal = normalize(Vec3d(0.4 * x, 0.4 * y, 1));
      normals.push_back({normal.x, normal.y, normal.z});
    }
  for (int i = 0; i < n; ++i)
    for (int k = 0; k < n; ++k) {
      const int a = i * (n + 1) + k, b = a + n + 1;
      indices.push_back({a, b, b + 1});
      indices.push_back({a, b + 1, a + 1});
    }
  if (area_weighted) {
    std::vector<Vec3d> sum(positions.size(), Vec3d(0.0));
    auto at = [&](int i) { return Vec3d(positions[size_t(i)][0], positions[size_t(i)][1], positions[size_t(i)][2]); };
    for (const auto& t : indices) {
      const int a = t[0], b = t[1], c = t[2];
      const Vec3d cr = cross(at(b) - at(a), at(c) - at(a));
      for (int i : {a, b, c}) sum[size_t(i)] += cr;
    }
    for (size_t v = 0; v < sum.size(); ++v) {
      const Vec3d nv = normalize(sum[v]);
      normals[v] = {nv.x, nv.y, nv.z};
    }
  }
  return {{"name", "dome"},         {"type", "mesh"},     {"material", material},
          {"positions", positions}, {"normals", normals}, {"indices", indices}};
}

}  // namespace bl::test
