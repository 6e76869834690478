// libFuzzer harness: bytes → a Mitsuba .vol file → read_vol (engine/scene/volume_io.h). Header
// fields, sizes against the file length and the voxel limit, and non-finite values.
#include "engine/core/errors.h"
#include "engine/scene/volume_io.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input("grid.vol", data, size);
  try {
    bl::VolumeGrid grid = bl::read_vol(path);
  } catch (const bl::InputError&) {
  }
  return 0;
}
