// libFuzzer harness: bytes → a glTF file → load_scene. Inputs that start with the binary magic
// "glTF" are written as .glb, everything else as .gltf (JSON). Relative buffer and image URIs
// resolve in the scratch folder, so "../assets/scene.bin" reaches the shared assets.
#include <cstring>

#include "engine/core/errors.h"
#include "engine/scene/scene_load.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const bool binary = size >= 4 && std::memcmp(data, "glTF", 4) == 0;
  const std::string path = bl::fuzz::write_input(binary ? "input.glb" : "input.gltf", data, size);
  try {
    auto scene = bl::load_scene(path);
  } catch (const bl::InputError&) {
  }
  return 0;
}
