// Image files: every format write_image produces reads back; the reader is chosen from the file's
// bytes, never its name; names with a NUL byte and bytes no supported format claims are refused
// with a one-line InputError before any OpenImageIO plugin sees them.
#include <OpenImageIO/imageio.h>
#include <sys/wait.h>
#include <unistd.h>
#include <zlib.h>
#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
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

TEST_CASE("8-bit sRGB decoding gives srgb_to_linear of every code, bit for bit", "[image][io]") {
  // The reader decodes 8-bit files through a table; it must give what the formula gives.
  TempDir tmp;
  Image img(256, 1, 3);
  for (int b = 0; b < 256; ++b)
    for (int c = 0; c < 3; ++c) img.at(b, 0, c) = srgb_to_linear(float(b) / 255.f);
  write_image(tmp("codes.png"), img);
  const Image raw = read_image(tmp("codes.png"), false), decoded = read_image(tmp("codes.png"), true);
  REQUIRE(raw.width == 256);
  REQUIRE(decoded.width == 256);
  for (int b = 0; b < 256; ++b)
    for (int c = 0; c < 3; ++c) {
      CAPTURE(b, c);
      REQUIRE(raw.at(b, 0, c) == float(b) / 255.f);  // the file holds every code once
      const float expected = srgb_to_linear(float(b) / 255.f), got = decoded.at(b, 0, c);
      CHECK(std::memcmp(&expected, &got, sizeof(float)) == 0);
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

// EXR and PNG are decoded by OpenEXR and libpng directly (no OpenImageIO); the layouts real files
// use, written here by OpenImageIO (a different writer than ours) or by hand.
TEST_CASE("OpenEXR layouts: data window, Y, half, extra layers, subsampling", "[image][io]") {
  TempDir tmp;
  auto write = [&](const std::string& name, OIIO::ImageSpec spec, const std::vector<float>& px) {
    auto out = OIIO::ImageOutput::create(tmp(name));
    REQUIRE(out);
    REQUIRE(out->open(tmp(name), spec));
    REQUIRE(out->write_image(OIIO::TypeDesc::FLOAT, px.data()));
    out->close();
  };
  SECTION("a data window away from the origin, half floats, alpha and another layer") {
    OIIO::ImageSpec spec(5, 4, 5, OIIO::TypeDesc::HALF);
    spec.x = 7, spec.y = -3, spec.full_width = 20, spec.full_height = 20;
    spec.channelnames = {"R", "G", "B", "A", "depth.Z"};
    spec.alpha_channel = 3;
    std::vector<float> px(5 * 4 * 5);
    for (size_t i = 0; i < px.size(); ++i) px[i] = float(i % 97) * 0.25f;
    write("window.exr", spec, px);
    const Image back = read_image(tmp("window.exr"), true);  // float files are never sRGB-decoded
    REQUIRE(back.width == 5);
    REQUIRE(back.height == 4);
    REQUIRE(back.channels == 3);
    CHECK(back.from_float_file);
    for (int y = 0; y < 4; ++y)
      for (int x = 0; x < 5; ++x)
        for (int c = 0; c < 3; ++c) CHECK(back.at(x, y, c) == px[(size_t(y) * 5 + size_t(x)) * 5 + size_t(c)]);
  }
  SECTION("one channel Y") {
    OIIO::ImageSpec spec(3, 2, 1, OIIO::TypeDesc::FLOAT);
    spec.channelnames = {"Y"};
    write("y.exr", spec, {1, 2, 3, 4, 5, 6.5f});
    const Image back = read_image(tmp("y.exr"), false);
    REQUIRE(back.channels == 1);
    CHECK(back.data == std::vector<float>{1, 2, 3, 4, 5, 6.5f});
  }
  SECTION("one layer's colour channels; two-channel and ambiguous files refused") {
    // diffuse.B, diffuse.G, diffuse.R sort blue first: they were read as (B, G, R), and a file of
    // R and G as (G, R, R), without a word.
    OIIO::ImageSpec spec(2, 1, 4, OIIO::TypeDesc::FLOAT);
    spec.channelnames = {"diffuse.R", "diffuse.G", "diffuse.B", "depth.Z"};
    write("layer.exr", spec, {0.9f, 0.5f, 0.1f, 7.f, 0.8f, 0.4f, 0.2f, 8.f});
    const Image back = read_image(tmp("layer.exr"), false);
    REQUIRE(back.channels == 3);
    CHECK(back.data == std::vector<float>{0.9f, 0.5f, 0.1f, 0.8f, 0.4f, 0.2f});
    OIIO::ImageSpec rg(2, 1, 2, OIIO::TypeDesc::FLOAT);
    rg.channelnames = {"R", "G"};
    write("rg.exr", rg, {0.9f, 0.5f, 0.8f, 0.4f});
    CHECK(error_of(tmp("rg.exr")).find("without R, G, B or Y channels (channels G, R)") != std::string::npos);
    OIIO::ImageSpec two(1, 1, 6, OIIO::TypeDesc::FLOAT);
    two.channelnames = {"a.R", "a.G", "a.B", "b.R", "b.G", "b.B"};
    write("two.exr", two, {1, 2, 3, 4, 5, 6});
    CHECK(error_of(tmp("two.exr")).find("several colour layers") != std::string::npos);
    OIIO::ImageSpec one(2, 1, 1, OIIO::TypeDesc::FLOAT);
    one.channelnames = {"Z"};
    write("z.exr", one, {3.f, 4.f});
    CHECK(read_image(tmp("z.exr"), false).data == std::vector<float>{3.f, 4.f});
  }
  SECTION("NaN is refused with the pixel") {
    OIIO::ImageSpec spec(2, 2, 3, OIIO::TypeDesc::FLOAT);
    std::vector<float> px(12, 0.5f);
    px[3 * 3 + 1] = std::nanf("");
    write("nan.exr", spec, px);
    CHECK(error_of(tmp("nan.exr")).find("nan.exr: pixel (1, 1) is not a finite number") != std::string::npos);
  }
  SECTION("a truncated file is a one-line error") {
    write_image(tmp("full.exr"), gradient_image());
    std::vector<unsigned char> bytes = file_bytes(tmp("full.exr"));
    bytes.resize(bytes.size() - 40);
    put_file(tmp("cut.exr"), bytes);
    const std::string e = error_of(tmp("cut.exr"));
    CHECK(e.find("cut.exr: corrupt image") != std::string::npos);
    CHECK(e.find('\n') == std::string::npos);
  }
}

TEST_CASE("PNG layouts: 16-bit, grey, alpha, palette (by hand), interlaced", "[image][io]") {
  TempDir tmp;
  auto write = [&](const std::string& name, OIIO::ImageSpec spec, OIIO::TypeDesc type, const void* px) {
    auto out = OIIO::ImageOutput::create(tmp(name));
    REQUIRE(out);
    REQUIRE(out->open(tmp(name), spec));
    REQUIRE(out->write_image(type, px));
    out->close();
  };
  SECTION("16-bit RGB keeps its precision") {
    std::vector<uint16_t> px(4 * 3 * 3);
    for (size_t i = 0; i < px.size(); ++i) px[i] = uint16_t(i * 1811 + 7);
    write("16.png", OIIO::ImageSpec(4, 3, 3, OIIO::TypeDesc::UINT16), OIIO::TypeDesc::UINT16, px.data());
    const Image back = read_image(tmp("16.png"), false);
    REQUIRE(back.channels == 3);
    CHECK_FALSE(back.from_float_file);
    for (size_t i = 0; i < px.size(); ++i) CHECK(back.data[i] == float(px[i]) / 65535.f);
    const Image srgb = read_image(tmp("16.png"), true);
    CHECK(srgb.data[5] == srgb_to_linear(float(px[5]) / 65535.f));
  }
  SECTION("grey is one channel; alpha is not read (the colour as stored)") {
    const std::vector<unsigned char> grey = {0, 51, 102, 255};
    write("grey.png", OIIO::ImageSpec(2, 2, 1, OIIO::TypeDesc::UINT8), OIIO::TypeDesc::UINT8, grey.data());
    const Image g = read_image(tmp("grey.png"), false);
    REQUIRE(g.channels == 1);
    CHECK(g.data == std::vector<float>{0.f, 0.2f, 0.4f, 1.f});
    const std::vector<unsigned char> rgba = {255, 128, 0, 0, 10, 20, 30, 255};
    OIIO::ImageSpec spec(2, 1, 4, OIIO::TypeDesc::UINT8);
    spec.attribute("oiio:UnassociatedAlpha", 1);
    write("rgba.png", spec, OIIO::TypeDesc::UINT8, rgba.data());
    const Image c = read_image(tmp("rgba.png"), false);
    REQUIRE(c.channels == 3);
    CHECK(c.data == std::vector<float>{1.f, 128 / 255.f, 0.f, 10 / 255.f, 20 / 255.f, 30 / 255.f});
  }
  SECTION("a palette image with 2-bit indices, interlaced (Adam7), built by hand") {
    // 3×2 pixels, palette {red, green, blue, white}; each row: filter byte 0, then 2-bit indices.
    const unsigned char rows[] = {0, 0b00011000, 0, 0b11100000};  // row 0: 0 1 2; row 1: 3 2 0
    std::string idat;
    {
      uLongf n = compressBound(sizeof(rows));
      std::vector<unsigned char> z(n);
      REQUIRE(compress(z.data(), &n, rows, sizeof(rows)) == Z_OK);
      idat.assign(reinterpret_cast<const char*>(z.data()), n);
    }
    auto chunk = [](const std::string& type, const std::string& data) {
      std::string c(4, '\0');
      const uint32_t len = uint32_t(data.size());
      for (int i = 0; i < 4; ++i) c[size_t(i)] = char(len >> (24 - 8 * i));
      const std::string body = type + data;
      uint32_t crc = uint32_t(crc32(0, reinterpret_cast<const Bytef*>(body.data()), uInt(body.size())));
      c += body;
      for (int i = 0; i < 4; ++i) c += char(crc >> (24 - 8 * i));
      return c;
    };
    const std::string ihdr = std::string("\0\0\0\3\0\0\0\2\2\3\0\0\0", 13);  // 3×2, depth 2, palette
    const std::string plte = std::string("\xff\0\0\0\xff\0\0\0\xff\xff\xff\xff", 12);
    const std::string png = std::string("\x89PNG\r\n\x1a\n", 8) + chunk("IHDR", ihdr) + chunk("PLTE", plte) +
                            chunk("IDAT", idat) + chunk("IEND", "");
    std::ofstream(tmp("palette.png"), std::ios::binary) << png;
    const Image p = read_image(tmp("palette.png"), false);
    REQUIRE(p.width == 3);
    REQUIRE(p.height == 2);
    REQUIRE(p.channels == 3);
    CHECK(p.data == std::vector<float>{1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1, 0, 0, 1, 1, 0, 0});
    // The same image interlaced, written by OpenImageIO (libpng): identical pixels.
    OIIO::ImageSpec spec(3, 2, 3, OIIO::TypeDesc::UINT8);
    spec.attribute("png:interlace", 1);
    std::vector<unsigned char> px(18);
    for (size_t i = 0; i < 18; ++i) px[i] = (unsigned char)std::lround(p.data[i] * 255.f);
    write("adam7.png", spec, OIIO::TypeDesc::UINT8, px.data());
    CHECK(read_image(tmp("adam7.png"), false).data == p.data);
  }
  SECTION("a truncated file is a one-line error") {
    write_image(tmp("full.png"), gradient_image());
    std::vector<unsigned char> bytes = file_bytes(tmp("full.png"));
    bytes.resize(bytes.size() / 2);
    put_file(tmp("cut.png"), bytes);
    const std::string e = error_of(tmp("cut.png"));
    CHECK(e.find("cut.png: corrupt image") != std::string::npos);
    CHECK(e.find('\n') == std::string::npos);
  }
}

TEST_CASE("PFM: both byte orders, grey, bottom-up rows, short files", "[image][io]") {
  TempDir tmp;
  auto pfm = [&](const std::string& name, const std::string& header, std::vector<float> values, bool big) {
    std::string body(reinterpret_cast<const char*>(values.data()), values.size() * 4);
    if (big)
      for (size_t i = 0; i < body.size(); i += 4) std::swap(body[i], body[i + 3]), std::swap(body[i + 1], body[i + 2]);
    std::ofstream(tmp(name), std::ios::binary) << header << body;
  };
  // Stored bottom row first: the file's first row is the image's last.
  pfm("be.pfm", "Pf\n2 2\n1.0\n", {1, 2, 3, 4}, true);
  pfm("le.pfm", "Pf 2 2 -1\n", {1, 2, 3, 4}, false);
  for (const char* name : {"be.pfm", "le.pfm"}) {
    CAPTURE(name);
    const Image g = read_image(tmp(name), true);
    REQUIRE(g.channels == 1);
    CHECK(g.from_float_file);
    CHECK(g.data == std::vector<float>{3, 4, 1, 2});
  }
  pfm("short.pfm", "PF\n4 4\n-1.0\n", {1, 2, 3}, false);
  CHECK(error_of(tmp("short.pfm")).find("short.pfm: corrupt image (PFM file shorter") != std::string::npos);
  pfm("huge.pfm", "PF\n1000000000 1000000000\n-1.0\n", {1, 2, 3}, false);
  CHECK(error_of(tmp("huge.pfm")).find("huge.pfm:") != std::string::npos);
  pfm("zero.pfm", "PF\n0 4\n-1.0\n", {1, 2, 3}, false);
  CHECK(error_of(tmp("zero.pfm")).find("zero.pfm: corrupt image (PFM header") != std::string::npos);
}

// Temporaries of processes that no longer write are removed; a zombie (a killed plot child that
// nobody reaped: kill(pid, 0) still succeeds) counts as gone, a running process does not, nor do
// names outside the pattern.
TEST_CASE("stale temporaries: dead and zombie writers' files go, live writers' stay", "[image][io]") {
  TempDir t;
  const pid_t zombie = ::fork();
  REQUIRE(zombie >= 0);
  if (zombie == 0) ::_exit(0);
  // Wait until the child has exited (a zombie: its /proc stat says Z), without reaping it.
  for (int i = 0; i < 1000; ++i) {
    std::ifstream stat("/proc/" + std::to_string(zombie) + "/stat");
    std::string line;
    std::getline(stat, line);
    if (line.find(") Z") != std::string::npos) break;
    ::usleep(1000);
  }
  const std::string mine = t(".a.tmp" + std::to_string(::getpid()) + ".png");
  const std::string of_zombie = t(".b.tmp" + std::to_string(zombie) + ".png");
  const std::string of_nobody = t(".c.tmp999999999.csv");
  const std::string other = t("d.tmp1.png");
  for (const auto& f : {mine, of_zombie, of_nobody, other}) std::ofstream(f) << "x";
  CHECK(remove_stale_temporaries(t.dir.string()) == 2);
  CHECK(fs::exists(mine));
  CHECK(!fs::exists(of_zombie));
  CHECK(!fs::exists(of_nobody));
  CHECK(fs::exists(other));
  int status = 0;
  ::waitpid(zombie, &status, 0);
}
