// libFuzzer harness: bytes → an OpenVDB file → read_vdb (engine/scene/openvdb_io.h). OpenVDB
// parses in the backlight-vdb-read helper process, so libFuzzer sees the coverage of this side
// only: what is fuzzed is the isolation — every input, whatever OpenVDB does with it (invalid
// bools, allocations sized by the file, endless loops: all found in OpenVDB within seconds),
// must come back as an InputError within the time limit, never a crash or a hang here. The
// limits are tighter than the defaults so a run stays within libFuzzer's -timeout and RSS limit.
#include "engine/core/errors.h"
#include "engine/scene/openvdb_io.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input("grid.vdb", data, size);
  try {
    bl::VolumeGrid grid = bl::read_vdb(path, size % 2 ? "density" : "", {768, 5});
  } catch (const bl::InputError&) {
  }
  return 0;
}
