// libFuzzer harness: bytes → an optimization config file → check_optimize_config (JSON, keys,
// values; the config's scene is not loaded and nothing runs).
#include "engine/core/errors.h"
#include "engine/optimize/optimizer.h"
#include "tests/fuzz/fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input("optimize.json", data, size);
  try {
    bl::check_optimize_config(path);
  } catch (const bl::InputError&) {
  }
  return 0;
}
