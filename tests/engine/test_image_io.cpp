// Image files: every format write_image produces reads back; the reader is chosen from the file's
// bytes, never its name; names with a NUL byte and bytes no supported format claims are refused
// with a one-line InputError before any OpenImageIO plugin sees them.
#include <OpenImageIO/imageio.h>
#include <unistd.h>
#include <catch2/catch.hpp>

#include <cmath>
#include <filesystem>
#include <fstream>

#include "engine/core/errors.h"
#include "engine/io/image_io.h"

using namespace bl;
namespace fs = std::filesystem;

namespace {
struct TempDir {
  fs::path dir = fs::temp_directory_path() / ("backlight-test-image-" + std::to_string(::getpid()));
  TempDir() { fs::create_directories(dir); }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
  std::string operator()(const std::string& name) const { return (dir / name).string(); }
};

Image gradient_image() {
  Image img(7, 5, 3);
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x)
      for (int c = 0; c < 3; ++c) img.at(x, y, c) = 0.05f + 0.9f * float(x + 2 * y + 3 * c) / 30.f;
  return img;
}

std::string error_of(const std::string& path) {
  try {
    read_image(path, false);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("every written format reads back", "[image][io]") {
  TempDir tmp;
  const Image img = gradient_image();
  // Float formats keep values to their precision (EXR half, Radiance's shared exponent); 8-bit
  // formats store sRGB rounded to 1/255, at most 0.5/255 × 2.27 (the slope of the sRGB curve at
  // 1) in linear units (JPEG adds its compression error).
  const struct {
    const char* name;
    float tolerance;
    bool is_float;
  } formats[] = {{"a.exr", 1e-3f, true},
                 {"a.pfm", 0.f, true},
                 {"a.hdr", 0.01f, true},
                 {"a.png", 0.5f / 255.f * 2.27f, false},
                 {"a.jpg", 0.08f, false}};
  for (const auto& f : formats) {
    CAPTURE(f.name);
    write_image(tmp(f.name), img);
    const Image back = read_image(tmp(f.name), !f.is_float);
    REQUIRE(back.width == img.width);
    REQUIRE(back.height == img.height);
    REQUIRE(back.channels == 3);
    CHECK(back.from_float_file == f.is_float);
    float worst = 0.f;
    for (size_t i = 0; i < img.data.size(); ++i) worst = std::max(worst, std::abs(back.data[i] - img.data[i]));
    CHECK(worst <= f.tolerance);
  }
}

TEST_CASE("the reader follows the file's bytes, not its name", "[image][io]") {
  TempDir tmp;
  const Image img = gradient_image();
  write_image(tmp("real.exr"), img);
  fs::rename(tmp("real.exr"), tmp("named.png"));
  const Image back = read_image(tmp("named.png"), true);  // sRGB decoding applies to 8-bit files only
  REQUIRE(back.width == 7);
  CHECK(back.from_float_file);
  CHECK(std::abs(back.at(3, 2, 1) - img.at(3, 2, 1)) < 1e-3f);
}

TEST_CASE("unsupported bytes and NUL names are one-line input errors", "[image][io]") {
  TempDir tmp;
  std::ofstream(tmp("fits.png")) << "SIMPLE  =                    T / FITS";
  const std::string fits = error_of(tmp("fits.png"));
  CHECK(fits.find("fits.png: unsupported image format") != std::string::npos);
  std::ofstream(tmp("empty.exr")).flush();
  CHECK(error_of(tmp("empty.exr")).find("unsupported image format") != std::string::npos);

  const Image img = gradient_image();
  write_image(tmp("tex.png"), img);
  const std::string nul = error_of(tmp("tex.png") + std::string(1, '\0') + ".qt");
  CHECK(nul.find("NUL byte") != std::string::npos);
  CHECK(nul.find('\0') == std::string::npos);
  CHECK(nul.find('\n') == std::string::npos);
  // Negative control: the same file without the NUL reads.
  CHECK(error_of(tmp("tex.png")).empty());
}
