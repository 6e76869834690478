#include "engine/io/image_io.h"

#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfInputFile.h>
#include <ImfOutputFile.h>
#include <fcntl.h>
#include <png.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>
#include <set>
#include <utility>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/plugins/plugin.h"

namespace bl {

namespace fs = std::filesystem;

void check_encoded_image(const std::string& where, const unsigned char* b, size_t size) {
  auto be16 = [&](size_t i) { return uint64_t(b[i]) << 8 | b[i + 1]; };
  auto be32 = [&](size_t i) { return be16(i) << 16 | be16(i + 2); };
  static const unsigned char kPng[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (size >= 29 && std::memcmp(b, kPng, 8) == 0 && std::memcmp(b + 12, "IHDR", 4) == 0) {
    const uint64_t w = be32(16), h = be32(20), depth = b[24], color = b[25];
    if (w == 0 || h == 0)
      throw file_error(where, "corrupt image (PNG of " + std::to_string(w) + " x " + std::to_string(h) + " pixels)");
    limits::check_image_size(where, w, h);
    const uint64_t samples = color == 2 ? 3 : color == 4 ? 2 : color == 6 ? 4 : 1;        // RGB, grey+alpha, RGBA
    const uint64_t raw = h * (1 + (w * samples * std::max<uint64_t>(depth, 1) + 7) / 8);  // filter byte per row
    if (raw / 1100 > size)
      throw file_error(where, "corrupt image (" + std::to_string(size) + " bytes cannot hold a PNG of " +
                                  std::to_string(w) + " x " + std::to_string(h) + " pixels)");
  } else if (size >= 4 && b[0] == 0xFF && b[1] == 0xD8) {
    // JPEG: the first start-of-frame segment holds the size.
    for (size_t pos = 2; pos + 9 <= size;) {
      if (b[pos] != 0xFF) return;  // not a marker: leave it to the decoder
      const unsigned m = b[pos + 1];
      if (m == 0xFF) {
        ++pos;  // fill byte
        continue;
      }
      if (m == 0x01 || (m >= 0xD0 && m <= 0xD8)) {
        pos += 2;
        continue;
      }
      const bool sof = m >= 0xC0 && m <= 0xCF && m != 0xC4 && m != 0xC8 && m != 0xCC;
      if (sof) {
        limits::check_image_size(where, be16(pos + 7), be16(pos + 5));
        return;
      }
      pos += 2 + be16(pos + 2);
    }
  }
}

namespace {
// Swaps the C stdio stream `stderr` for /dev/null while alive. The codecs inside OpenImageIO
// (libjpeg) print their own warnings and errors through stdio; our one-line error says what went wrong. File
// descriptor 2 is left alone, so sanitizer and libFuzzer reports (written to the descriptor, or
// through their own saved stream) still reach the terminal. Loaders run on the main thread,
// before any progress output.
class StdioStderrSilencer {
 public:
  StdioStderrSilencer() : null_(std::fopen("/dev/null", "w")) {
    if (null_) {
      std::fflush(stderr);
      saved_ = stderr;
      stderr = null_;
    }
  }
  ~StdioStderrSilencer() {
    if (null_) {
      stderr = saved_;
      std::fclose(null_);
    }
  }
  StdioStderrSilencer(const StdioStderrSilencer&) = delete;
  StdioStderrSilencer& operator=(const StdioStderrSilencer&) = delete;

 private:
  FILE* null_ = nullptr;
  FILE* saved_ = nullptr;
};

// Reads a file's structure without loading it: bytes at an offset, bounds-checked by the caller
// against the file size.
class FileProbe {
 public:
  explicit FileProbe(const std::string& path) : f_(path, std::ios::binary) {
    std::error_code ec;
    size_ = std::filesystem::file_size(path, ec);
    if (ec) size_ = 0;
  }
  uint64_t size() const { return size_; }
  std::string read(uint64_t at, size_t n) {
    std::string out(n, '\0');
    f_.clear();
    f_.seekg(std::streamoff(at));
    f_.read(out.data(), std::streamsize(n));
    out.resize(size_t(f_.gcount()));
    return out;
  }

 private:
  std::ifstream f_;
  uint64_t size_ = 0;
};

// OpenEXR allocates each header attribute at the size the file claims before it notices the file
// is shorter (a 1 KB file can claim a 1.7 GB string). Walk the header(s) first and check that
// every attribute fits in the file. Layout: magic, version/flags, then per part a list of
// (name\0, type\0, int32 size, value) ended by an empty name; multi-part files end the list of
// headers with one more empty name.
void check_exr_header(const std::string& path) {
  FileProbe file(path);
  const std::string head = file.read(0, 8);
  if (head.size() < 8 || static_cast<unsigned char>(head[0]) != 0x76 || head[1] != 0x2f || head[2] != 0x31 ||
      head[3] != 0x01)
    return;                                                                  // not OpenEXR
  const bool multipart = (static_cast<unsigned char>(head[5]) & 0x10) != 0;  // flag bit 12
  // Names are at most 31 bytes unless the long-names flag (bit 10) allows 255. OpenEXR reads a
  // longer name only up to its limit and takes the rest as type and size, so a walk that
  // accepted it would check other sizes than the ones OpenEXR allocates (found by fuzz_image).
  const size_t max_name = (static_cast<unsigned char>(head[5]) & 0x04) != 0 ? 255 : 31;
  uint64_t pos = 8;
  auto read_string = [&]() {
    const std::string chunk = file.read(pos, max_name + 1);
    const size_t end = chunk.find('\0');
    if (end == std::string::npos)
      throw file_error(path, "corrupt image (truncated OpenEXR header, or a name longer than " +
                                 std::to_string(max_name) + " bytes)");
    pos += end + 1;
    return chunk.substr(0, end);
  };
  for (int part = 0;; ++part) {
    int attributes = 0;
    for (;; ++attributes) {
      const std::string name = read_string();
      if (name.empty()) break;
      const std::string type = read_string();
      const std::string size_bytes = file.read(pos, 4);
      if (size_bytes.size() < 4) throw file_error(path, "corrupt image (truncated OpenEXR header)");
      int32_t size = 0;
      std::memcpy(&size, size_bytes.data(), 4);
      pos += 4;
      if (size < 0 || uint64_t(size) > file.size() - std::min(pos, file.size()))
        throw file_error(path, "corrupt image (OpenEXR attribute '" + name.substr(0, 64) + "' claims " +
                                   std::to_string(size) + " bytes; the file has " + std::to_string(file.size()) + ")");
      // Two value types are read by their own structure rather than by the declared size: a
      // channel list up to its empty name, a preview by its width × height. Both must fill the
      // declared size exactly, or OpenEXR's position would leave this walk's (found by fuzz_image:
      // a channel list ending early made OpenEXR read a 1.7 GB "attribute" from inside it).
      const std::string value = type == "chlist" || type == "preview" ? file.read(pos, size_t(size)) : std::string();
      auto corrupt_value = [&] {
        return file_error(path, "corrupt image (OpenEXR attribute '" + name.substr(0, 64) + "' of type " + type +
                                    " does not fill its " + std::to_string(size) + " bytes)");
      };
      if (type == "chlist") {
        size_t at = 0;
        for (;;) {
          const size_t end = value.find('\0', at);
          if (end == std::string::npos || end - at > max_name) throw corrupt_value();
          if (end == at) {
            at = end + 1;
            break;
          }
          at = end + 1 + 16;  // pixel type, pLinear + 3 reserved, x and y sampling
          if (at > value.size()) throw corrupt_value();
        }
        if (at != value.size()) throw corrupt_value();
      } else if (type == "preview") {
        if (value.size() < 8) throw corrupt_value();
        uint32_t wh[2];
        std::memcpy(wh, value.data(), 8);
        if (uint64_t(wh[0]) * wh[1] * 4 + 8 != value.size()) throw corrupt_value();
      }
      pos += uint64_t(size);
    }
    if (!multipart || attributes == 0) return;
    if (part > 1024) throw file_error(path, "corrupt image (too many OpenEXR parts)");
  }
}

// The whole file, for the readers below that decode from memory.
std::vector<unsigned char> read_whole_file(const std::string& path) {
  std::error_code ec;
  const uint64_t size = fs::file_size(path, ec);
  if (ec) throw file_error(path, "cannot read");
  limits::require_at_most(path, "file size", size, limits::kFileBytes);
  std::vector<unsigned char> bytes(size);
  std::ifstream f(path, std::ios::binary);
  if (!f.read(reinterpret_cast<char*>(bytes.data()), std::streamsize(size)) || uint64_t(f.gcount()) != size)
    throw file_error(path, "cannot read");
  return bytes;
}

uint32_t be32(const unsigned char* b) {
  return uint32_t(b[0]) << 24 | uint32_t(b[1]) << 16 | uint32_t(b[2]) << 8 | uint32_t(b[3]);
}

// PNG, walked chunk by chunk (headers only) before libpng sees it. libpng allocates a chunk at the
// length the file declares (up to 2 GB) inside ImageInput::open, before we see the image's size:
// every chunk must fit in the file, and the IHDR's width and height must be within the limits.
// The copy handed to libpng keeps the critical chunks and the ancillary ones that can affect
// decoded pixels (tRNS, gAMA, sRGB, cHRM, sBIT) and drops the rest (text, XMP, Exif, ICC
// profiles, times): metadata backlight never uses.
std::vector<unsigned char> png_without_metadata(const std::string& path, const std::vector<unsigned char>& in) {
  if (in.size() < 8) throw file_error(path, "corrupt image (truncated PNG signature)");
  std::vector<unsigned char> out(in.begin(), in.begin() + 8);  // signature (checked by image_format)
  const uint64_t n = in.size();
  uint64_t pos = 8;
  bool ended = false;
  while (n >= pos + 12) {
    const uint32_t length = be32(&in[pos]);
    const std::string type(reinterpret_cast<const char*>(&in[pos + 4]), 4);
    if (uint64_t(length) > n - pos - 12)
      throw file_error(path, "corrupt image (PNG chunk '" + type + "' claims " + std::to_string(length) +
                                 " bytes; the file has " + std::to_string(n) + ")");
    if (type == "IHDR" && length >= 8) limits::check_image_size(path, be32(&in[pos + 8]), be32(&in[pos + 12]));
    const bool critical = (in[pos + 4] & 0x20) == 0;
    const bool keep =
        critical || type == "tRNS" || type == "gAMA" || type == "sRGB" || type == "cHRM" || type == "sBIT";
    const uint64_t end = pos + 12 + uint64_t(length);
    if (keep) out.insert(out.end(), in.begin() + std::ptrdiff_t(pos), in.begin() + std::ptrdiff_t(end));
    pos = end;
    if (type == "IEND") {
      ended = true;
      break;
    }
  }
  // A truncated file keeps its partial tail: libpng reports the truncation.
  if (!ended) out.insert(out.end(), in.begin() + std::ptrdiff_t(pos), in.end());
  return out;
}

// JPEG, walked marker by marker the way libjpeg finds markers (bytes other than 0xFF skipped,
// 0xFF fill bytes, FF 00 and restart markers inside entropy-coded data). The copy handed to
// OpenImageIO drops APP1..APP13, APP15 and COM segments: OpenImageIO 2.4 decodes Exif, XMP, IPTC
// and ICC data from them with lengths taken from the data itself (fuzz_image found a heap overread
// in its IPTC decoder: an APP13 record claiming more bytes than its segment holds). APP0 (JFIF)
// and APP14 (Adobe colour transform) stay: libjpeg needs them to decode the pixels.
std::vector<unsigned char> jpeg_without_metadata(const std::string& path, const std::vector<unsigned char>& in) {
  const size_t n = in.size();
  if (n < 2) throw file_error(path, "corrupt image (truncated JPEG)");
  std::vector<unsigned char> out(in.begin(), in.begin() + 2);  // SOI (checked by image_format)
  size_t pos = 2;
  while (pos < n) {
    // Data between markers (entropy-coded scans, or stray bytes libjpeg skips) is copied as is.
    size_t next = pos;
    for (;;) {
      while (next < n && in[next] != 0xFF) ++next;
      if (next + 1 >= n) break;
      size_t m = next + 1;
      while (m < n && in[m] == 0xFF) ++m;  // fill bytes
      if (m >= n) {
        next = n;
        break;
      }
      const unsigned char code = in[m];
      if (code == 0x00 || (code >= 0xD0 && code <= 0xD7) || code == 0x01) {
        next = m + 1;  // stuffed zero, restart or TEM marker: part of the data stream
        continue;
      }
      break;
    }
    out.insert(out.end(), in.begin() + std::ptrdiff_t(pos), in.begin() + std::ptrdiff_t(std::min(next, n)));
    if (next + 1 >= n) break;
    size_t m = next + 1;
    while (m < n && in[m] == 0xFF) ++m;
    const unsigned char code = in[m];
    if (code == 0xD8 || code == 0xD9) {  // SOI (libjpeg refuses a second one) or EOI
      out.push_back(0xFF);
      out.push_back(code);
      pos = m + 1;
      if (code == 0xD9) break;
      continue;
    }
    if (m + 2 >= n) {  // truncated: libjpeg reports it
      out.insert(out.end(), in.begin() + std::ptrdiff_t(next), in.end());
      break;
    }
    const size_t length = size_t(in[m + 1]) << 8 | size_t(in[m + 2]);
    if (length < 2)
      throw file_error(path, "corrupt image (JPEG segment at byte " + std::to_string(next) + " has length " +
                                 std::to_string(length) + ")");
    const size_t end = std::min(n, m + 1 + length);
    const bool metadata = (code >= 0xE1 && code <= 0xEF && code != 0xEE) || code == 0xFE;
    if (!metadata) {
      out.push_back(0xFF);
      out.insert(out.end(), in.begin() + std::ptrdiff_t(m), in.begin() + std::ptrdiff_t(end));
    }
    pos = end;
  }
  return out;
}

// The format of a file, chosen by its first bytes; the extension is not trusted. Only these
// formats are read: given a file it cannot place, OpenImageIO would try every plugin it has
// (video through FFmpeg, DICOM, FITS, ...), code that was never meant to see untrusted textures
// (fuzz_set and fuzz_image found leaks and huge allocations there). JPEG and Radiance HDR go
// through OpenImageIO (the oiio plugin, opened on first use; these names are its readers'); EXR,
// PNG and PFM are decoded here with OpenEXR, libpng and a few lines.
std::string image_format(const std::string& path) {
  FileProbe file(path);
  const std::string head = file.read(0, 16);
  auto starts = [&](const char* magic, size_t n) { return head.size() >= n && head.compare(0, n, magic, n) == 0; };
  if (starts("\x89PNG\r\n\x1a\n", 8)) return "png";
  if (starts("\x76\x2f\x31\x01", 4)) return "openexr";
  if (starts("\xff\xd8\xff", 3)) return "jpeg";
  if (starts("#?", 2)) return "hdr";  // Radiance: "#?RADIANCE" or "#?RGBE"
  if (starts("PF", 2) || starts("Pf", 2)) return "pfm";
  throw file_error(path, "unsupported image format (expected PNG, OpenEXR, JPEG, Radiance HDR or PFM)");
}

std::string first_line(std::string s) {
  if (auto nl = s.find('\n'); nl != std::string::npos) s.resize(nl);
  return s;
}

// OpenEXR: the data window, channels R, G, B when the file has them, else Y, else one layer's
// <layer>.R/.G/.B or <layer>.Y (the only layer that has them), else a file's only channel;
// alpha and other layers are not read. Anything else is refused: the first three channels in
// the file's alphabetical order were taken before, so diffuse.B/G/R loaded as blue, green, red
// and a file of R and G as (G, R, R). Every pixel type is returned as float. check_exr_header
// has walked the header already.
Image read_exr(const std::string& path) {
  try {
    Imf::InputFile file(path.c_str());
    const Imf::Header& header = file.header();
    const Imath::Box2i dw = header.dataWindow();
    const int64_t w = int64_t(dw.max.x) - dw.min.x + 1, h = int64_t(dw.max.y) - dw.min.y + 1;
    if (w <= 0 || h <= 0) throw file_error(path, "image has no pixels");
    limits::check_image_size(path, uint64_t(w), uint64_t(h));
    const Imf::ChannelList& list = header.channels();
    std::vector<std::string> names;
    auto colour_in = [&](const std::string& prefix) -> std::vector<std::string> {
      if (list.findChannel(prefix + "R") && list.findChannel(prefix + "G") && list.findChannel(prefix + "B"))
        return {prefix + "R", prefix + "G", prefix + "B"};
      if (list.findChannel(prefix + "Y")) return {prefix + "Y"};
      return {};
    };
    names = colour_in("");
    std::string all;  // the channel names, for the message
    size_t count = 0;
    for (auto it = list.begin(); it != list.end(); ++it, ++count)
      if (count < 12) all += std::string(all.empty() ? "" : ", ") + std::string(it.name()).substr(0, 64);
    if (count > 12) all += ", ...";
    if (names.empty()) {
      std::vector<std::string> layers;  // layers with colour channels
      std::set<std::string> prefixes;
      for (auto it = list.begin(); it != list.end(); ++it) {
        const std::string n = it.name();
        if (const size_t dot = n.rfind('.'); dot != std::string::npos) prefixes.insert(n.substr(0, dot + 1));
      }
      for (const auto& prefix : prefixes)
        if (!colour_in(prefix).empty()) layers.push_back(prefix);
      if (layers.size() == 1)
        names = colour_in(layers[0]);
      else if (layers.size() > 1)
        throw file_error(
            path, "OpenEXR image with several colour layers (channels " + all + "): which one to read is ambiguous");
      else if (count == 1)
        names = {list.begin().name()};
    }
    if (count == 0) throw file_error(path, "image has no channels");
    if (names.empty())
      throw file_error(path, "OpenEXR image without R, G, B or Y channels (channels " + all +
                                 "): which channel is which colour is unknown");
    for (const auto& n : names)
      if (const Imf::Channel* c = list.findChannel(n); c->xSampling != 1 || c->ySampling != 1)
        throw file_error(path, "unsupported OpenEXR image (channel '" + n.substr(0, 64) + "' is subsampled)");
    Image img(int(w), int(h), int(names.size()));
    img.from_float_file = true;
    const size_t xstride = sizeof(float) * names.size(), ystride = xstride * size_t(w);
    Imf::FrameBuffer frame;
    for (size_t c = 0; c < names.size(); ++c)
      frame.insert(names[c], Imf::Slice::Make(Imf::FLOAT, img.data.data() + c, dw, xstride, ystride));
    file.setFrameBuffer(frame);
    file.readPixels(dw.min.y, dw.max.y);
    return img;
  } catch (const InputError&) {
    throw;
  } catch (const std::exception& e) {
    throw file_error(path, "corrupt image (" + first_line(e.what()) + ")");
  }
}

// PNG through libpng, from the copy png_without_metadata made. Palette and low bit depths are
// expanded; 16-bit samples keep their precision; alpha (and tRNS) is ignored: the colour is
// returned as stored, not composited. libpng reports errors by longjmp, so the two steps that
// call it hold no objects with destructors; PngRead owns everything.
struct PngRead {
  const std::vector<unsigned char>* bytes = nullptr;
  size_t pos = 0;
  png_structp png = nullptr;
  png_infop info = nullptr;
  char error[256] = "";
  ~PngRead() {
    if (png) png_destroy_read_struct(&png, info ? &info : nullptr, nullptr);
  }
};

void png_on_error(png_structp png, png_const_charp message) {
  auto* r = static_cast<PngRead*>(png_get_error_ptr(png));
  std::snprintf(r->error, sizeof(r->error), "%s", message);
  png_longjmp(png, 1);
}
void png_on_warning(png_structp, png_const_charp) {}
void png_on_read(png_structp png, png_bytep out, size_t n) {
  auto* r = static_cast<PngRead*>(png_get_io_ptr(png));
  if (n > r->bytes->size() - r->pos) png_error(png, "file truncated");
  std::memcpy(out, r->bytes->data() + r->pos, n);
  r->pos += n;
}

bool png_read_header(PngRead* r, int* width, int* height, int* channels, int* depth) {
  if (setjmp(png_jmpbuf(r->png))) return false;
  png_set_read_fn(r->png, r, png_on_read);
  png_read_info(r->png, r->info);
  const int color = png_get_color_type(r->png, r->info), bits = png_get_bit_depth(r->png, r->info);
  if (color == PNG_COLOR_TYPE_PALETTE) png_set_palette_to_rgb(r->png);
  if (color == PNG_COLOR_TYPE_GRAY && bits < 8) png_set_expand_gray_1_2_4_to_8(r->png);
  if (color & PNG_COLOR_MASK_ALPHA) png_set_strip_alpha(r->png);
  if (bits == 16) png_set_swap(r->png);  // native (little-endian) 16-bit samples
  png_set_interlace_handling(r->png);
  png_read_update_info(r->png, r->info);
  *width = int(png_get_image_width(r->png, r->info));
  *height = int(png_get_image_height(r->png, r->info));
  *channels = png_get_channels(r->png, r->info);
  *depth = png_get_bit_depth(r->png, r->info);
  return true;
}
bool png_read_rows(PngRead* r, png_bytep* rows) {
  if (setjmp(png_jmpbuf(r->png))) return false;
  png_read_image(r->png, rows);
  return true;
}

Image read_png(const std::string& path, const std::vector<unsigned char>& bytes) {
  check_encoded_image(path, bytes.data(), bytes.size());
  PngRead r;
  r.bytes = &bytes;
  r.png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &r, png_on_error, png_on_warning);
  if (r.png) r.info = png_create_info_struct(r.png);
  if (!r.png || !r.info) throw std::bad_alloc();
  int w = 0, h = 0, channels = 0, depth = 0;
  if (!png_read_header(&r, &w, &h, &channels, &depth))
    throw file_error(path, std::string("corrupt image (") + r.error + ")");
  if (w <= 0 || h <= 0 || (channels != 1 && channels != 3) || (depth != 8 && depth != 16))
    throw file_error(path, "unsupported PNG layout");
  limits::check_image_size(path, uint64_t(w), uint64_t(h));
  const size_t row_bytes = size_t(w) * size_t(channels) * size_t(depth / 8);
  std::vector<unsigned char> pixels(row_bytes * size_t(h));
  std::vector<png_bytep> rows(static_cast<size_t>(h));
  for (size_t y = 0; y < rows.size(); ++y) rows[y] = pixels.data() + y * row_bytes;
  if (!png_read_rows(&r, rows.data())) throw file_error(path, std::string("corrupt image (") + r.error + ")");
  Image img(w, h, channels);
  if (depth == 8) {
    for (size_t i = 0; i < img.data.size(); ++i) img.data[i] = float(pixels[i]) / 255.f;
  } else {
    for (size_t i = 0; i < img.data.size(); ++i) {
      uint16_t v;
      std::memcpy(&v, &pixels[2 * i], 2);
      img.data[i] = float(v) / 65535.f;
    }
  }
  return img;
}

// Portable float map: "PF" (RGB) or "Pf" (grey), width, height and scale as text, each followed
// by one white-space character after the last, then rows of floats from the bottom up; a negative
// scale means little-endian. Sizes are checked against the file before allocating.
Image read_pfm(const std::string& path) {
  FileProbe file(path);
  const std::string head = file.read(0, 128);
  if (head.size() < 3 || !std::isspace(static_cast<unsigned char>(head[2])))
    throw file_error(path, "corrupt image (PFM magic is PF or Pf followed by white space)");
  size_t pos = 2;
  auto token = [&]() {
    while (pos < head.size() && std::isspace(static_cast<unsigned char>(head[pos]))) ++pos;
    const size_t start = pos;
    while (pos < head.size() && !std::isspace(static_cast<unsigned char>(head[pos]))) ++pos;
    if (pos == start || pos >= head.size()) throw file_error(path, "corrupt image (truncated PFM header)");
    return head.substr(start, pos - start);
  };
  const std::string ws = token(), hs = token(), ss = token();
  ++pos;  // the one white-space character before the data
  auto number = [&](const std::string& t) {
    char* end = nullptr;
    const double v = std::strtod(t.c_str(), &end);
    if (*end != '\0' || !std::isfinite(v)) throw file_error(path, "corrupt image (PFM header value '" + t + "')");
    return v;
  };
  const double w = number(ws), h = number(hs), scale = number(ss);
  if (w < 1 || h < 1 || w != std::floor(w) || h != std::floor(h) || scale == 0)
    throw file_error(path, "corrupt image (PFM header: " + ws + " x " + hs + ", scale " + ss + ")");
  limits::check_image_size(path, uint64_t(std::min(w, 1e12)), uint64_t(std::min(h, 1e12)));
  const int channels = head[1] == 'F' ? 3 : 1;
  const size_t row = size_t(w) * size_t(channels);
  // Checked before allocating: a 30-byte header may claim gigabytes.
  if (file.size() < pos || (file.size() - pos) / sizeof(float) < row * size_t(h))
    throw file_error(path, "corrupt image (PFM file shorter than its " + ws + " x " + hs + " pixels)");
  if ((file.size() - pos) != row * size_t(h) * sizeof(float))
    throw file_error(path, "corrupt image (PFM file longer than its " + ws + " x " + hs + " pixels)");
  Image img(int(w), int(h), channels);
  const bool swap = (scale < 0) != (std::endian::native == std::endian::little);
  for (int y = 0; y < img.height; ++y) {
    const std::string bytes = file.read(pos + uint64_t(y) * row * sizeof(float), row * sizeof(float));
    if (bytes.size() != row * sizeof(float)) throw file_error(path, "cannot read");
    float* dst = img.data.data() + size_t(img.height - 1 - y) * row;
    for (size_t i = 0; i < row; ++i) {
      uint32_t u;
      std::memcpy(&u, bytes.data() + 4 * i, 4);
      if (swap) u = __builtin_bswap32(u);
      std::memcpy(dst + i, &u, 4);
    }
  }
  img.from_float_file = true;
  return img;
}

// JPEG and Radiance HDR through OpenImageIO (the oiio plugin).
Image read_with_plugin(const std::string& path, const std::string& format, const std::vector<unsigned char>& bytes) {
  const auto& oiio = plugin::oiio(path, format == "jpeg" ? "reading JPEG" : "reading Radiance HDR");
  StdioStderrSilencer quiet;
  plugin::ImageHeader spec;
  std::string error;
  void* reader = oiio.open(path, format, bytes, int(limits::kImagePixels * 12 >> 20), &spec, &error);
  if (!reader) throw file_error(path, error);
  struct Close {
    const plugin::OiioApi& api;
    void* reader;
    ~Close() { api.close(reader); }
  } close{oiio, reader};
  if (spec.width <= 0 || spec.height <= 0 || spec.channels <= 0) throw file_error(path, "image has no pixels");
  // The header's size, checked before anything is allocated (a 69-byte file can claim 10^10 pixels).
  limits::check_image_size(path, uint64_t(spec.width), uint64_t(spec.height));
  limits::require_at_most(path, "channel count", uint64_t(spec.channels), 64);
  // Only the channels kept are read: a header may claim 64 channels of a 2^28-pixel image.
  Image img(spec.width, spec.height, spec.channels >= 3 ? 3 : 1);
  img.from_float_file = spec.is_float;
  if (!oiio.read(reader, img.channels, img.data.data(), &error)) throw file_error(path, error);
  return img;
}
}  // namespace

Image box_downsample(const Image& image, int k) {
  if (k < 1 || image.width % k != 0 || image.height % k != 0)
    throw std::invalid_argument("box_downsample: " + std::to_string(k) + " does not divide " +
                                std::to_string(image.width) + "x" + std::to_string(image.height));
  Image out(image.width / k, image.height / k, image.channels);
  const double scale = 1.0 / (double(k) * k);
  for (int y = 0; y < out.height; ++y)
    for (int x = 0; x < out.width; ++x)
      for (int c = 0; c < image.channels; ++c) {
        double sum = 0;
        for (int dy = 0; dy < k; ++dy)
          for (int dx = 0; dx < k; ++dx) sum += image.at(x * k + dx, y * k + dy, c);
        out.at(x, y, c) = float(sum * scale);
      }
  return out;
}

float srgb_to_linear(float v) { return v <= 0.04045f ? v / 12.92f : std::pow((v + 0.055f) / 1.055f, 2.4f); }
float linear_to_srgb(float v) {
  v = std::clamp(v, 0.f, 1.f);
  return v <= 0.0031308f ? 12.92f * v : 1.055f * std::pow(v, 1.f / 2.4f) - 0.055f;
}

Image read_image(const std::string& path, bool decode_srgb) {
  return with_path_errors([&] { return read_image_unguarded(path, decode_srgb); });
}

Image read_image_unguarded(const std::string& path, bool decode_srgb) {
  require_input_file(path);
  check_exr_header(path);
  const std::string format = image_format(path);
  Image img;
  if (format == "openexr") {
    img = read_exr(path);
  } else if (format == "png") {
    img = read_png(path, png_without_metadata(path, read_whole_file(path)));
  } else if (format == "pfm") {
    img = read_pfm(path);
  } else {
    // JPEG is decoded from a copy in memory without its metadata (see above).
    img = read_with_plugin(
        path, format,
        format == "jpeg" ? jpeg_without_metadata(path, read_whole_file(path)) : std::vector<unsigned char>());
  }
  const bool srgb = decode_srgb && !img.from_float_file;
  const size_t channels = size_t(img.channels);
  // 8-bit files hold 256 distinct values: their decoding comes from a table of srgb_to_linear at
  // exactly those values (the same floats; a 1024² RGB texture took 3 M powf calls).
  static const std::array<float, 256> srgb_table = [] {
    std::array<float, 256> t;
    for (int b = 0; b < 256; ++b) t[size_t(b)] = srgb_to_linear(float(b) / 255.f);
    return t;
  }();
  for (size_t i = 0; i < img.data.size(); ++i) {
    float& v = img.data[i];
    if (!std::isfinite(v))
      throw file_error(path, "pixel (" + std::to_string(i / channels % size_t(img.width)) + ", " +
                                 std::to_string(i / channels / size_t(img.width)) + ") is not a finite number");
    if (!srgb) continue;
    const float code = std::round(v * 255.f);
    if (code >= 0.f && code <= 255.f && float(int(code)) / 255.f == v)
      v = srgb_table[size_t(code)];
    else
      v = srgb_to_linear(v);  // 16-bit PNG and other values
  }
  return img;
}

namespace {
std::string temp_name(const std::string& path) {
  fs::path p(path);
  // Keep the extension last: OpenImageIO (JPEG, HDR) picks the format from it.
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

// Flushes and closes `f`, the temporary `tmp` of `path` written with stdio (`written`: every write
// succeeded); on any failure removes `tmp` and throws "write failed (<cause>)", the errno of the
// failed write, flush or close (close reports what a delayed write found: NFS, a quota). An
// ofstream's failbit said only "write failed".
void finish_stdio_write(std::FILE* f, bool written, const std::string& tmp, const std::string& path) {
  int cause = written ? 0 : errno;
  bool ok = written && std::fflush(f) == 0;
  if (written && !ok) cause = errno;
  if (std::fclose(f) != 0 && ok) {
    ok = false;
    cause = errno;
  }
  if (ok) return;
  std::error_code ec;
  fs::remove(tmp, ec);
  throw file_error(path, "write failed" + (cause ? std::string(" (") + std::strerror(cause) + ")" : std::string()));
}

// Portable float map: "PF" (RGB) or "Pf" (grey), width and height, a negative scale for
// little-endian data, then rows from the bottom up.
// Written with stdio, whose failing call leaves errno: the cause is named ("write failed (No space
// left on device)"), as the EXR and PNG writers do.
void write_pfm(const std::string& tmp, const std::string& path, const Image& image) {
  const bool grey = image.channels == 1;
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (!f) throw file_error(path, std::string("cannot open for writing (") + std::strerror(errno) + ")");
  const std::string header = std::string(grey ? "Pf" : "PF") + "\n" + std::to_string(image.width) + " " +
                             std::to_string(image.height) + "\n-1.0\n";
  static_assert(std::endian::native == std::endian::little, "PFM is written as little-endian floats");
  std::vector<float> row(size_t(image.width) * (grey ? 1 : 3));
  bool ok = std::fwrite(header.data(), 1, header.size(), f) == header.size();
  for (int y = image.height - 1; ok && y >= 0; --y) {
    for (int x = 0; x < image.width; ++x)
      for (int c = 0; c < (grey ? 1 : 3); ++c)
        row[size_t(x) * (grey ? 1 : 3) + size_t(c)] = image.at(x, y, std::min(c, image.channels - 1));
    ok = std::fwrite(row.data(), sizeof(float), row.size(), f) == row.size();
  }
  finish_stdio_write(f, ok, tmp, path);
}

// OpenEXR, 32-bit float channels (Y, Y A, R G B or R G B A), zip compression.
void write_exr(const std::string& tmp, const std::string& path, const Image& image) {
  static const std::vector<std::vector<const char*>> names = {{"Y"}, {"Y", "A"}, {"R", "G", "B"}, {"R", "G", "B", "A"}};
  if (image.channels < 1 || image.channels > 4)
    throw file_error(path, "OpenEXR images are written with 1 to 4 channels");
  try {
    Imf::Header header(image.width, image.height);
    header.compression() = Imf::ZIP_COMPRESSION;
    const auto& channel_names = names[size_t(image.channels - 1)];
    for (const char* n : channel_names) header.channels().insert(n, Imf::Channel(Imf::FLOAT));
    Imf::OutputFile out(tmp.c_str(), header);
    const size_t xstride = sizeof(float) * size_t(image.channels), ystride = xstride * size_t(image.width);
    Imf::FrameBuffer frame;
    for (size_t c = 0; c < channel_names.size(); ++c)
      frame.insert(
          channel_names[c],
          Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(const_cast<float*>(image.data.data() + c)), xstride, ystride));
    out.setFrameBuffer(frame);
    out.writePixels(image.height);
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw file_error(path, "write failed (" + first_line(e.what()) + ")");
  }
}

// PNG, 8-bit sRGB, through libpng (errors by longjmp: png_write_rows holds no destructors).
struct PngWrite {
  FILE* file = nullptr;
  png_structp png = nullptr;
  png_infop info = nullptr;
  char error[256] = "";
  int error_errno = 0;  // errno when libpng failed: its fwrite's ("Write Error") names no cause
  ~PngWrite() {
    if (png) png_destroy_write_struct(&png, info ? &info : nullptr);
    if (file) std::fclose(file);
  }
};
void png_on_write_error(png_structp png, png_const_charp message) {
  auto* w = static_cast<PngWrite*>(png_get_error_ptr(png));
  w->error_errno = errno;
  std::snprintf(w->error, sizeof(w->error), "%s", message);
  png_longjmp(png, 1);
}
bool png_write_rows(PngWrite* w, int width, int height, int channels, png_bytep* rows) {
  if (setjmp(png_jmpbuf(w->png))) return false;
  static const int types[] = {PNG_COLOR_TYPE_GRAY, PNG_COLOR_TYPE_GRAY_ALPHA, PNG_COLOR_TYPE_RGB,
                              PNG_COLOR_TYPE_RGB_ALPHA};
  png_init_io(w->png, w->file);
  png_set_IHDR(w->png, w->info, png_uint_32(width), png_uint_32(height), 8, types[channels - 1], PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(w->png, w->info);
  png_write_image(w->png, rows);
  png_write_end(w->png, nullptr);
  return true;
}

void write_png(const std::string& tmp, const std::string& path, const Image& image,
               const std::vector<unsigned char>& bytes) {
  if (image.channels < 1 || image.channels > 4) throw file_error(path, "PNG images are written with 1 to 4 channels");
  std::vector<png_bytep> rows(size_t(image.height));
  const size_t row_bytes = size_t(image.width) * size_t(image.channels);
  for (size_t y = 0; y < rows.size(); ++y) rows[y] = const_cast<unsigned char*>(bytes.data() + y * row_bytes);
  bool ok = false;
  std::string error;
  {
    PngWrite w;
    w.file = std::fopen(tmp.c_str(), "wb");
    if (!w.file) throw file_error(path, "cannot open for writing");
    w.png = png_create_write_struct(PNG_LIBPNG_VER_STRING, &w, png_on_write_error, png_on_warning);
    if (w.png) w.info = png_create_info_struct(w.png);
    ok = w.png && w.info && png_write_rows(&w, image.width, image.height, image.channels, rows.data());
    error = w.error;
    // The cause of a failed write (a full disk: "No space left on device"): errno of libpng's
    // failed fwrite, or of the flush and close of what stdio still held.
    int cause = std::ferror(w.file) ? w.error_errno : 0;
    if (std::fflush(w.file) != 0 && !cause) cause = errno;
    ok = ok && !std::ferror(w.file);
    if (std::fclose(std::exchange(w.file, nullptr)) != 0) {
      ok = false;
      if (!cause) cause = errno;
    }
    if (!ok && cause) error += (error.empty() ? "" : ": ") + std::string(std::strerror(cause));
  }
  if (!ok) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw file_error(path, "write failed" + (error.empty() ? std::string() : " (" + error + ")"));
  }
}
}  // namespace

void check_output_format(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  if (ext != ".exr" && ext != ".hdr" && ext != ".pfm" && ext != ".png" && ext != ".jpg" && ext != ".jpeg")
    throw file_error(path, "unsupported output format '" + ext + "' (use .exr, .png, .pfm, .hdr or .jpg)");
  fs::path dir = fs::path(path).parent_path();
  std::error_code ec;
  if (!dir.empty() && !fs::is_directory(dir, ec)) {
    if (ec && ec != std::errc::no_such_file_or_directory) throw file_error(path, "output folder: " + ec.message());
    throw file_error(path,
                     fs::exists(dir, ec) ? "'" + dir.string() + "' is not a folder" : "output folder does not exist");
  }
  // Found now, not by the rename after the whole render.
  if (fs::is_directory(path, ec)) throw file_error(path, "is a folder (name an image file)");
  // JPEG and HDR are written by the oiio plugin: a missing plugin fails now, not after the work.
  if (ext == ".hdr" || ext == ".jpg" || ext == ".jpeg")
    (void)plugin::oiio(path, ext == ".hdr" ? "writing Radiance HDR" : "writing JPEG");
}

void check_output_creatable(const std::string& path) {
  check_output_format(path);
  // A folder we may not create files in (the write goes to a temporary file beside the output,
  // then renamed): a read-only mount or /proc failed only after the work, naming the temporary
  // file. A probe of that file's name, created and removed at once (before the work only:
  // write_image finds a failing write by itself).
  const std::string probe = temp_name(path);
  const int fd = ::open(probe.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
  if (fd < 0 && errno != EEXIST)
    throw file_error(path, std::string("cannot create files in its folder (") + std::strerror(errno) + ")");
  if (fd >= 0) {
    ::close(fd);
    ::unlink(probe.c_str());
  }
}

void write_image(const std::string& path, const Image& image, bool encode_srgb) {
  check_output_format(path);
  std::string ext = fs::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  const bool is_float = ext == ".exr" || ext == ".hdr" || ext == ".pfm";
  const std::string tmp = temp_name(path);
  if (ext == ".pfm") {
    write_pfm(tmp, path, image);
  } else if (ext == ".exr") {
    write_exr(tmp, path, image);
  } else {
    std::vector<unsigned char> bytes;
    if (!is_float) {
      bytes.resize(image.data.size());
      for (size_t i = 0; i < bytes.size(); ++i)
        bytes[i] = (unsigned char)std::lround(
            (encode_srgb ? linear_to_srgb(image.data[i]) : std::clamp(image.data[i], 0.f, 1.f)) * 255.f);
    }
    if (ext == ".png") {
      write_png(tmp, path, image, bytes);
    } else {  // .hdr, .jpg: OpenImageIO
      const auto& oiio = plugin::oiio(path, ext == ".hdr" ? "writing Radiance HDR" : "writing JPEG");
      std::string error;
      if (!oiio.write(tmp, image.width, image.height, image.channels, is_float ? image.data.data() : nullptr,
                      is_float ? nullptr : bytes.data(), &error)) {
        std::error_code ec;
        fs::remove(tmp, ec);
        throw file_error(path, error);
      }
    }
  }
  commit(tmp, path);
}

void write_text_atomic(const std::string& path, const std::string& text) {
  write_bytes_atomic(path, text.data(), text.size());
}

// With stdio, as write_pfm: a failed write names its cause (an ofstream said only "write failed").
void write_bytes_atomic(const std::string& path, const void* data, size_t size) {
  const std::string tmp = temp_name(path);
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (!f) throw file_error(path, std::string("cannot open for writing (") + std::strerror(errno) + ")");
  finish_stdio_write(f, std::fwrite(data, 1, size, f) == size, tmp, path);
  commit(tmp, path);
}

void sync_path(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw file_error(path, std::string("cannot open to flush it to disk (") + std::strerror(errno) + ")");
  const int failed = ::fsync(fd) != 0 ? errno : 0;
  ::close(fd);
  // EINVAL: a file system that cannot sync this kind of file (some do not sync folders); nothing
  // more can be done there, and the write itself has succeeded.
  if (failed && failed != EINVAL)
    throw file_error(path, std::string("cannot flush to disk (") + std::strerror(failed) + ")");
}

void sync_folder(const std::string& dir) {
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec))
    if (it->is_regular_file(ec)) sync_path(it->path().string());
  if (ec) throw file_error(dir, "cannot list it to flush it to disk (" + ec.message() + ")");
  sync_path(dir);
}

bool process_gone(const std::string& digits) {
  if (digits.empty() || digits.find_first_not_of("0123456789") != std::string::npos) return false;
  if (digits.size() > 9) return true;  // beyond any pid
  const pid_t pid = pid_t(std::stol(digits));
  if (pid <= 0) return false;
  if (kill(pid, 0) != 0) return errno == ESRCH;
  // A zombie writes nothing more: a plot child killed with its parent (PR_SET_PDEATHSIG) stays
  // one until someone reaps it, for ever under a container's init that does not (its
  // temporary was left behind: test_optimize_crash failed now and then).
  std::ifstream stat("/proc/" + digits + "/stat");
  std::string line;
  if (!std::getline(stat, line)) return false;
  const size_t close = line.rfind(')');  // "pid (comm) state ...": comm may hold spaces
  return close != std::string::npos && close + 2 < line.size() && (line[close + 2] == 'Z' || line[close + 2] == 'X');
}

std::string regex_escaped(const std::string& text) {
  std::string out;
  for (char ch : text) {
    if (std::strchr(R"(\^$.|?*+()[]{})", ch)) out += '\\';
    out += ch;
  }
  return out;
}

int remove_stale_temporaries(const std::string& dir, bool recursive, const std::string& stem) {
  // temp_name's pattern: "." stem ".tmp" PID extension. Only files of processes that no longer
  // run go: this one, or another writing into the same folder, may be writing its own.
  const std::regex pattern("^\\.(?:" + stem + ")\\.tmp([0-9]+)(\\.[A-Za-z0-9]+)?$");
  const auto dead = process_gone;
  int removed = 0;
  std::error_code ec;
  auto consider = [&](const fs::directory_entry& entry) {
    std::error_code e;
    if (!entry.is_regular_file(e)) return;
    std::smatch m;
    const std::string name = entry.path().filename().string();
    if (!std::regex_match(name, m, pattern) || !dead(m[1].str())) return;
    if (fs::remove(entry.path(), e)) ++removed;
  };
  if (recursive) {
    for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) consider(*it);
  } else {
    for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) consider(*it);
  }
  return removed;
}

}  // namespace bl
