// libbacklight_oiio.so: JPEG and Radiance HDR through OpenImageIO (plugin_api.h). Opened by
// image_io.cpp on the first such file, so runs that use only EXR, PNG and PFM never load
// OpenImageIO's libraries. The caller has already checked and sanitized the bytes (format from
// the magic number, metadata segments removed); this file only drives OpenImageIO.
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <memory>
#include <vector>

#include "engine/plugins/plugin_api.h"

namespace {

using namespace OIIO;

std::string first_line(std::string s) {
  if (auto nl = s.find('\n'); nl != std::string::npos) s.resize(nl);
  return s;
}

struct Reader {
  std::unique_ptr<Filesystem::IOMemReader> memory;
  std::unique_ptr<ImageInput> in;
};

void* open_image(const std::string& path, const std::string& format, const std::vector<unsigned char>& bytes,
                 int image_limit_mb, bl::plugin::ImageHeader* header, std::string* error) {
  try {
    // Readers that honour it refuse images beyond this size before allocating (OpenImageIO 2.4).
    OIIO::attribute("limits:imagesize_MB", image_limit_mb);
    auto r = std::make_unique<Reader>();
    r->in = ImageInput::create(format);
    if (!r->in) {
      *error = "cannot read image (" + first_line(geterror()) + ")";
      return nullptr;
    }
    if (!bytes.empty()) {
      r->memory = std::make_unique<Filesystem::IOMemReader>(const_cast<unsigned char*>(bytes.data()), bytes.size());
      if (!r->in->set_ioproxy(r->memory.get())) {
        *error = "cannot read image (no in-memory reader for " + format + ")";
        return nullptr;
      }
    }
    ImageSpec opened;
    if (!r->in->open(path, opened)) {
      const std::string e = first_line(r->in->geterror());
      *error = "cannot read image" + (e.empty() ? std::string() : " (" + e + ")");
      return nullptr;
    }
    const ImageSpec& spec = r->in->spec();
    *header = {spec.width, spec.height, spec.nchannels, spec.format.is_floating_point()};
    return r.release();
  } catch (const std::exception& e) {
    *error = std::string("cannot read image (") + e.what() + ")";
    return nullptr;
  }
}

bool read_image(void* reader, int channels, float* out, std::string* error) {
  auto* r = static_cast<Reader*>(reader);
  try {
    if (r->in->read_image(0, 0, 0, channels, TypeDesc::FLOAT, out)) return true;
    *error = "corrupt image (" + first_line(r->in->geterror()) + ")";
  } catch (const std::exception& e) {
    *error = std::string("corrupt image (") + e.what() + ")";
  }
  return false;
}

void close_image(void* reader) {
  auto* r = static_cast<Reader*>(reader);
  if (r->in) r->in->close();
  delete r;
}

// Encoded in memory, then written here: OpenImageIO's HDR writer let a failed write of its last
// buffer pass (a full disk left a cut .hdr and exit 0), and libjpeg's exit()ed the process
// ("Output file write error --- out of disk space?", exit 1, its temporary file left).
bool write_image(const std::string& path, int width, int height, int channels, const float* floats,
                 const unsigned char* bytes, std::string* error) {
  std::vector<unsigned char> encoded;
  try {
    auto out = ImageOutput::create(path);
    if (!out) {
      *error = "cannot create image writer";
      return false;
    }
    Filesystem::IOVecOutput memory(encoded);
    if (!out->set_ioproxy(&memory)) {
      *error = "cannot encode in memory (" + first_line(out->geterror()) + ")";
      return false;
    }
    ImageSpec spec(width, height, channels, floats ? TypeDesc::FLOAT : TypeDesc::UINT8);
    if (!out->open(path, spec)) {
      *error = "cannot open for writing (" + first_line(out->geterror()) + ")";
      return false;
    }
    bool ok = floats ? out->write_image(TypeDesc::FLOAT, floats) : out->write_image(TypeDesc::UINT8, bytes);
    ok = out->close() && ok;
    if (!ok) {
      *error = "write failed (" + first_line(out->geterror()) + ")";
      return false;
    }
  } catch (const std::exception& e) {
    *error = std::string("write failed (") + e.what() + ")";
    return false;
  }
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) {
    *error = std::string("cannot open for writing (") + std::strerror(errno) + ")";
    return false;
  }
  bool ok = std::fwrite(encoded.data(), 1, encoded.size(), f) == encoded.size() && std::fflush(f) == 0;
  int cause = ok ? 0 : errno;
  if (std::fclose(f) != 0 && ok) {
    ok = false;
    cause = errno;
  }
  if (!ok) *error = std::string("write failed (") + std::strerror(cause) + ")";
  return ok;
}

const bl::plugin::OiioApi api = {bl::plugin::kPluginAbi, open_image, read_image, close_image, write_image};

}  // namespace

extern "C" __attribute__((visibility("default"))) const bl::plugin::OiioApi* backlight_oiio_plugin() { return &api; }
