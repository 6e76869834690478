#include "engine/image_io.h"

#include <OpenImageIO/imageio.h>
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "engine/errors.h"

namespace bl {

namespace fs = std::filesystem;
using namespace OIIO;

namespace {
// Redirects file descriptor 2 to /dev/null while alive (loaders run on the main thread, before
// any progress output).
class StderrSilencer {
 public:
  StderrSilencer() {
    std::fflush(stderr);
    saved_ = dup(STDERR_FILENO);
    int null_fd = open("/dev/null", O_WRONLY);
    if (saved_ >= 0 && null_fd >= 0) dup2(null_fd, STDERR_FILENO);
    if (null_fd >= 0) close(null_fd);
  }
  ~StderrSilencer() {
    std::fflush(stderr);
    if (saved_ >= 0) {
      dup2(saved_, STDERR_FILENO);
      close(saved_);
    }
  }
  StderrSilencer(const StderrSilencer&) = delete;
  StderrSilencer& operator=(const StderrSilencer&) = delete;

 private:
  int saved_ = -1;
};
}  // namespace

float srgb_to_linear(float v) { return v <= 0.04045f ? v / 12.92f : std::pow((v + 0.055f) / 1.055f, 2.4f); }
float linear_to_srgb(float v) {
  v = std::clamp(v, 0.f, 1.f);
  return v <= 0.0031308f ? 12.92f * v : 1.055f * std::pow(v, 1.f / 2.4f) - 0.055f;
}

Image read_image(const std::string& path, bool decode_srgb) {
  if (!fs::exists(path)) throw file_error(path, "file not found");
  if (!fs::is_regular_file(path)) throw file_error(path, "not a regular file");
  // Some format libraries (libpng) print their own messages to stderr; our one-line error says
  // what went wrong, so theirs are silenced for the duration of the read.
  StderrSilencer quiet;
  auto in = ImageInput::open(path);
  if (!in) {
    std::string err = geterror();
    if (auto nl = err.find('\n'); nl != std::string::npos) err.resize(nl);
    throw file_error(path, "cannot read image" + (err.empty() ? std::string() : " (" + err + ")"));
  }
  const ImageSpec& spec = in->spec();
  if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0) throw file_error(path, "image has no pixels");
  Image img(spec.width, spec.height, std::min(spec.nchannels, 3));
  img.from_float_file = spec.format.is_floating_point();
  std::vector<float> all(size_t(spec.width) * size_t(spec.height) * size_t(spec.nchannels));
  if (!in->read_image(0, 0, 0, spec.nchannels, TypeDesc::FLOAT, all.data())) {
    std::string err = in->geterror();
    if (auto nl = err.find('\n'); nl != std::string::npos) err.resize(nl);
    throw file_error(path, "corrupt image (" + err + ")");
  }
  in->close();
  const bool srgb = decode_srgb && !img.from_float_file;
  for (size_t p = 0; p < img.pixel_count(); ++p)
    for (int c = 0; c < img.channels; ++c) {
      float v = all[p * size_t(spec.nchannels) + size_t(c)];
      if (!std::isfinite(v))
        throw file_error(path, "pixel (" + std::to_string(p % size_t(spec.width)) + ", " +
                                   std::to_string(p / size_t(spec.width)) + ") is not a finite number");
      img.data[p * size_t(img.channels) + size_t(c)] = srgb ? srgb_to_linear(v) : v;
    }
  return img;
}

namespace {
std::string temp_name(const std::string& path) {
  fs::path p(path);
  // Keep the extension last: OpenImageIO picks the format from it.
  return (p.parent_path() / ("." + p.stem().string() + ".tmp" + std::to_string(getpid()) + p.extension().string()))
      .string();
}
void commit(const std::string& tmp, const std::string& path) {
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw file_error(path, "cannot write (rename failed)");
  }
}
}  // namespace

void check_output_format(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  if (ext != ".exr" && ext != ".hdr" && ext != ".pfm" && ext != ".png" && ext != ".jpg" && ext != ".jpeg")
    throw file_error(path, "unsupported output format '" + ext + "' (use .exr or .png)");
  fs::path dir = fs::path(path).parent_path();
  if (!dir.empty() && !fs::is_directory(dir)) throw file_error(path, "output folder does not exist");
}

void write_image(const std::string& path, const Image& image) {
  check_output_format(path);
  std::string ext = fs::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  const bool is_float = ext == ".exr" || ext == ".hdr" || ext == ".pfm";
  const std::string tmp = temp_name(path);
  auto out = ImageOutput::create(tmp);
  if (!out) throw file_error(path, "cannot create image writer");
  ImageSpec spec(image.width, image.height, image.channels, is_float ? TypeDesc::FLOAT : TypeDesc::UINT8);
  if (is_float) spec.attribute("compression", "zip");
  if (!out->open(tmp, spec)) throw file_error(path, "cannot open for writing (" + out->geterror() + ")");
  bool ok;
  if (is_float) {
    ok = out->write_image(TypeDesc::FLOAT, image.data.data());
  } else {
    std::vector<unsigned char> bytes(image.data.size());
    for (size_t i = 0; i < bytes.size(); ++i)
      bytes[i] = (unsigned char)std::lround(linear_to_srgb(image.data[i]) * 255.f);
    ok = out->write_image(TypeDesc::UINT8, bytes.data());
  }
  ok = out->close() && ok;
  if (!ok) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw file_error(path, "write failed");
  }
  commit(tmp, path);
}

void write_text_atomic(const std::string& path, const std::string& text) {
  const std::string tmp = temp_name(path);
  {
    std::ofstream f(tmp, std::ios::binary);
    if (!f) throw file_error(path, "cannot open for writing");
    f << text;
    f.flush();
    if (!f) throw file_error(path, "write failed");
  }
  commit(tmp, path);
}

}  // namespace bl
