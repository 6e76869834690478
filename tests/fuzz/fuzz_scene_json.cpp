// libFuzzer harness: bytes → a .json scene file → load_scene (parse, validate, build the scene).
#include "engine/core/errors.h"
#include "engine/scene/scene_load.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input("scene.json", data, size);
  try {
    auto scene = bl::load_scene(path);
  } catch (const bl::InputError&) {
  }
  return 0;
}
