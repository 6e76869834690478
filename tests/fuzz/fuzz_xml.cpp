// libFuzzer harness: bytes → a Mitsuba 3 XML scene → load_scene. Meshes and textures named
// "../assets/…" resolve to the shared assets (quad.obj, quad.ply, tex.png).
#include "engine/core/errors.h"
#include "engine/scene/scene_load.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input("input.xml", data, size);
  try {
    auto scene = bl::load_scene(path);
  } catch (const bl::InputError&) {
  }
  return 0;
}
