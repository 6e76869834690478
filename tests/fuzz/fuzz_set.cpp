// libFuzzer harness: bytes → one `--set NAME=FILE|v1,v2,...` assignment applied to a small scene
// that is loaded once (every parameter kind: bitmap texture, constants, roughness, emitter
// radiance, environment map). Parameter values are restored after each run, so runs are
// independent. Image files: /tmp/backlight-fuzz/assets/{tex.png,tex.exr,env.exr,checker.png}.
#include <fstream>
#include <memory>
#include <vector>

#include "engine/core/errors.h"
#include "engine/scene/scene_load.h"
#include "tests/fuzz/fuzz_common.h"

namespace {

const char* kScene = R"({
  "integrator": {"spp": 1, "max_depth": 3},
  "cameras": [{"name": "main", "origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0],
               "fov": 40, "resolution": [8, 8]}],
  "materials": {
    "wall": {"type": "diffuse", "albedo": {"type": "bitmap", "file": "../assets/tex.png", "wrap": "repeat"}},
    "white": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]},
    "metal": {"type": "roughconductor", "specular": [0.9, 0.7, 0.4], "roughness": 0.2},
    "plastic": {"type": "roughplastic", "albedo": 0.5, "roughness": 0.1, "ior": 1.5}
  },
  "shapes": [
    {"name": "back", "type": "rectangle", "material": "wall", "transform": {"translate": [0, 0, -1]}},
    {"name": "box", "type": "cube", "material": "metal", "transform": {"scale": 0.3}},
    {"name": "floor", "type": "rectangle", "material": "plastic",
     "transform": {"rotate": {"axis": [1, 0, 0], "angle": -90}, "translate": [0, -1, 0]}},
    {"name": "light", "type": "rectangle", "material": "white", "emitter": {"radiance": [5, 5, 5]},
     "transform": {"scale": 0.2, "rotate": {"axis": [1, 0, 0], "angle": 90}, "translate": [0, 0.99, 0]}}
  ],
  "environment": {"type": "envmap", "file": "../assets/env.exr", "scale": 1}
})";

struct Fixture {
  std::unique_ptr<bl::Scene> scene;
  std::vector<std::vector<float>> values;  // every parameter's loaded value
};

Fixture& fixture() {
  static Fixture f = [] {
    Fixture x;
    const std::string path = bl::fuzz::scratch_dir() + "/set_scene.json";
    std::ofstream(path) << kScene;
    x.scene = bl::load_scene(path);
    for (const auto& p : x.scene->params.all()) x.values.push_back(p.value);
    return x;
  }();
  return f;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  Fixture& f = fixture();
  const std::string assignment(reinterpret_cast<const char*>(data), size);
  try {
    bl::apply_override(*f.scene, assignment);
  } catch (const bl::InputError&) {
  }
  bool changed = false;
  auto& params = f.scene->params.all();
  for (size_t i = 0; i < params.size(); ++i)
    if (params[i].value != f.values[i]) params[i].value = f.values[i], changed = true;
  if (changed) f.scene->prepare_sampling();
  return 0;
}
