// libFuzzer harness: bytes → a mesh file → read_obj / read_ply. Inputs that start with "ply" are
// written as .ply, everything else as .obj (tinyobjloader, then backlight's own checks).
#include <cstring>

#include "engine/core/errors.h"
#include "engine/scene/mesh_io.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const bool ply = size >= 3 && std::memcmp(data, "ply", 3) == 0;
  const std::string path = bl::fuzz::write_input(ply ? "input.ply" : "input.obj", data, size);
  try {
    bl::Mesh m = ply ? bl::read_ply(path) : bl::read_obj(path, true);
    for (uint32_t i : m.indices)
      if (i >= m.positions.size()) __builtin_trap();  // the readers promise valid indices
  } catch (const bl::InputError&) {
  }
  return 0;
}
