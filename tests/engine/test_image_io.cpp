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

namespace {
std::vector<unsigned char> file_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}
void put_file(const std::string& path, const std::vector<unsigned char>& bytes) {
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), std::streamsize(bytes.size()));
}
std::vector<unsigned char> segment(unsigned char marker, const std::string& payload) {
  const size_t length = payload.size() + 2;
  std::vector<unsigned char> s = {0xFF, marker, (unsigned char)(length >> 8), (unsigned char)(length & 0xFF)};
  s.insert(s.end(), payload.begin(), payload.end());
  return s;
}
std::vector<unsigned char> png_chunk(const std::string& type, const std::string& data) {
  const uint32_t n = uint32_t(data.size());
  std::vector<unsigned char> c = {(unsigned char)(n >> 24), (unsigned char)(n >> 16), (unsigned char)(n >> 8),
                                  (unsigned char)n};
  c.insert(c.end(), type.begin(), type.end());
  c.insert(c.end(), data.begin(), data.end());
  c.insert(c.end(), {0xDE, 0xAD, 0xBE, 0xEF});  // wrong CRC: these chunks never reach libpng
  return c;
}
}  // namespace

// OpenImageIO 2.4 decodes Exif, XMP, IPTC and ICC metadata with lengths taken from the data
// (fuzz_image found a heap overread in its JPEG IPTC decoder). read_image hands it copies without
// those segments and chunks. The hostile segments below overread OpenImageIO's buffers if they
// reach it; the ASan+UBSan build of this test (tools/check --sanitize) is what catches that.
TEST_CASE("image metadata is never parsed: hostile Exif, IPTC, XMP and ICC segments read as the plain image",
          "[image][io]") {
  TempDir tmp;
  const Image img = gradient_image();
  const std::string bytes(1, '\0');
  // An IPTC record claiming 65535 bytes in a 30-byte segment, and an APP13 that is exactly
  // "Photoshop 3.0" with no NUL (OpenImageIO compares it with strcmp).
  std::string iptc = std::string("Photoshop 3.0") + bytes + "8BIM" + "\x04\x04" + std::string(4, '\0') + "\x7f\xff";
  iptc += std::string("\x1c\x02\x78\xff\xff", 5) + "caption";
  const std::vector<std::vector<unsigned char>> jpeg_metadata = {
      segment(0xE1, std::string("Exif") + bytes + bytes + "MM" + bytes + "*" + "\x7f\xff\xff\xf0"),
      segment(0xE1, "http://ns.adobe.com/xap/1.0/"),
      segment(0xED, iptc),
      segment(0xED, "Photoshop 3.0"),
      segment(0xE2, std::string("ICC_PROFILE") + bytes + "\x01\x01" + "\xff\xff\xff\xff"),
      segment(0xFE, "comment"),
  };
  SECTION("JPEG, baseline and progressive") {
    for (const bool progressive : {false, true}) {
      CAPTURE(progressive);
      const std::string plain = tmp(progressive ? "p.jpg" : "b.jpg");
      {
        auto out = OIIO::ImageOutput::create(plain);
        REQUIRE(out);
        OIIO::ImageSpec spec(img.width, img.height, 3, OIIO::TypeDesc::UINT8);
        if (progressive) spec.attribute("jpeg:progressive", 1);
        std::vector<unsigned char> px(img.data.size());
        for (size_t i = 0; i < px.size(); ++i) px[i] = (unsigned char)std::lround(img.data[i] * 255.f);
        REQUIRE(out->open(plain, spec));
        REQUIRE(out->write_image(OIIO::TypeDesc::UINT8, px.data()));
        out->close();
      }
      std::vector<unsigned char> hostile = file_bytes(plain);
      REQUIRE(hostile.size() > 4);
      // After SOI, and once more just before EOI (after the entropy-coded scans).
      std::vector<unsigned char> all;
      for (const auto& s : jpeg_metadata) all.insert(all.end(), s.begin(), s.end());
      hostile.insert(hostile.end() - 2, all.begin(), all.end());
      hostile.insert(hostile.begin() + 2, all.begin(), all.end());
      put_file(tmp("hostile.jpg"), hostile);
      const Image a = read_image(plain, false);  // stored as linear 8-bit values above
      const Image b = read_image(tmp("hostile.jpg"), false);
      REQUIRE(b.width == a.width);
      REQUIRE(b.height == a.height);
      CHECK(b.data == a.data);  // same entropy-coded data, same decoder: identical pixels
      float worst = 0.f;
      for (size_t i = 0; i < img.data.size(); ++i) worst = std::max(worst, std::abs(b.data[i] - img.data[i]));
      CHECK(worst < 0.08f);
    }
  }
  SECTION("PNG") {
    write_image(tmp("plain.png"), img);
    std::vector<unsigned char> hostile = file_bytes(tmp("plain.png"));
    const std::vector<std::vector<unsigned char>> chunks = {
        png_chunk("eXIf", std::string("MM") + bytes + "*" + "\x7f\xff\xff\xf0"),
        png_chunk("iTXt", std::string("XML:com.adobe.xmp") + bytes + bytes + bytes + bytes + bytes + "<x:xmpmeta"),
        png_chunk("iCCP", std::string("icc") + bytes + bytes + "\x78\x9c\xff\xff"),
        png_chunk("tEXt", std::string("Comment") + bytes + "text"),
    };
    size_t at = 8 + 12 + 13;  // after the signature and IHDR
    for (const auto& c : chunks) {
      hostile.insert(hostile.begin() + std::ptrdiff_t(at), c.begin(), c.end());
      at += c.size();
    }
    put_file(tmp("hostile.png"), hostile);
    const Image a = read_image(tmp("plain.png"), true);
    const Image b = read_image(tmp("hostile.png"), true);
    REQUIRE(b.width == a.width);
    CHECK(b.data == a.data);
  }
  SECTION("a truncated JPEG or PNG is still a one-line error") {
    write_image(tmp("t.jpg"), img);
    std::vector<unsigned char> jpg = file_bytes(tmp("t.jpg"));
    jpg.resize(jpg.size() / 3);
    put_file(tmp("cut.jpg"), jpg);
    const std::string jerr = error_of(tmp("cut.jpg"));
    CHECK(jerr.find("cut.jpg") != std::string::npos);
    write_image(tmp("t.png"), img);
    std::vector<unsigned char> png = file_bytes(tmp("t.png"));
    png.resize(png.size() - 20);
    put_file(tmp("cut.png"), png);
    const std::string perr = error_of(tmp("cut.png"));
    CHECK(perr.find("cut.png") != std::string::npos);
    CHECK(perr.find('\n') == std::string::npos);
  }
}
