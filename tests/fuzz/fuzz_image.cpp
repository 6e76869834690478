// libFuzzer harness: bytes → an image file → read_image. The extension follows the format's
// magic number when there is one (.png, .exr, .hdr, .jpg), otherwise the first byte picks one of
// them, so files whose name and content disagree are read too (OpenImageIO then tries every
// format). The last bit of the size picks sRGB decoding. OpenImageIO and the codecs are not
// instrumented: this finds crashes, hangs and huge allocations in them, and bugs in read_image.
#include <cstring>

#include "engine/core/errors.h"
#include "engine/io/image_io.h"
#include "tests/fuzz/fuzz_common.h"

namespace {
const char* extension(const uint8_t* d, size_t n) {
  static const char* const any[] = {"png", "exr", "hdr", "jpg"};
  if (n >= 4 && std::memcmp(d, "\x89PNG", 4) == 0) return "png";
  if (n >= 4 && std::memcmp(d, "\x76\x2f\x31\x01", 4) == 0) return "exr";
  if (n >= 2 && std::memcmp(d, "#?", 2) == 0) return "hdr";
  if (n >= 2 && d[0] == 0xff && d[1] == 0xd8) return "jpg";
  return n ? any[d[0] % 4] : "png";
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = bl::fuzz::write_input(std::string("image.") + extension(data, size), data, size);
  try {
    bl::Image img = bl::read_image(path, size % 2 == 0);
  } catch (const bl::InputError&) {
  }
  return 0;
}
