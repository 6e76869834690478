#include "engine/io/image_io.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>

#include "engine/core/errors.h"
#include "engine/core/limits.h"

namespace bl {

namespace fs = std::filesystem;
using namespace OIIO;

namespace {
// Swaps the C stdio stream `stderr` for /dev/null while alive. libpng (inside OpenImageIO) prints
// its own warnings and errors through stdio; our one-line error says what went wrong. File
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
// The copy handed to OpenImageIO keeps the critical chunks and the ancillary ones that affect
// decoded pixels (tRNS; gAMA, sRGB, cHRM and sBIT, which OpenImageIO's alpha handling reads) and
// drops the rest (text, XMP, Exif, ICC profiles, times): metadata backlight never uses, parsed by
// code of OpenImageIO that was not written for hostile files.
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

// The OpenImageIO reader for a file, chosen by its first bytes. Only these formats are read:
// given a file it cannot place, OpenImageIO would try every plugin it has (video through
// FFmpeg, DICOM, FITS, ...), code that was never meant to see untrusted textures (fuzz_set and
// fuzz_image found leaks and huge allocations there). The extension is not trusted either.
const char* image_format(const std::string& path) {
  FileProbe file(path);
  const std::string head = file.read(0, 16);
  auto starts = [&](const char* magic, size_t n) { return head.size() >= n && head.compare(0, n, magic, n) == 0; };
  if (starts("\x89PNG\r\n\x1a\n", 8)) return "png";
  if (starts("\x76\x2f\x31\x01", 4)) return "openexr";
  if (starts("\xff\xd8\xff", 3)) return "jpeg";
  if (starts("#?", 2)) return "hdr";                     // Radiance: "#?RADIANCE" or "#?RGBE"
  if (starts("PF", 2) || starts("Pf", 2)) return "pnm";  // PFM (OpenImageIO's PNM reader)
  throw file_error(path, "unsupported image format (expected PNG, OpenEXR, JPEG, Radiance HDR or PFM)");
}
}  // namespace

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
  // Readers that honour it refuse images beyond this size before allocating (OpenImageIO 2.4).
  static const bool oiio_limits = OIIO::attribute("limits:imagesize_MB", int(limits::kImagePixels * 12 >> 20));
  (void)oiio_limits;
  const std::string format = image_format(path);
  // PNG and JPEG are decoded from a copy in memory without their metadata (see above).
  std::vector<unsigned char> bytes;
  if (format == "png") bytes = png_without_metadata(path, read_whole_file(path));
  if (format == "jpeg") bytes = jpeg_without_metadata(path, read_whole_file(path));
  Filesystem::IOMemReader memory(bytes.data(), bytes.size());
  StdioStderrSilencer quiet;
  auto in = ImageInput::create(format);
  if (in && !bytes.empty() && !in->set_ioproxy(&memory))
    throw file_error(path, "cannot read image (no in-memory reader for " + format + ")");
  if (in) {
    ImageSpec opened;
    if (!in->open(path, opened)) {
      std::string err = in->geterror();
      if (auto nl = err.find('\n'); nl != std::string::npos) err.resize(nl);
      throw file_error(path, "cannot read image" + (err.empty() ? std::string() : " (" + err + ")"));
    }
  }
  if (!in) {
    std::string err = geterror();
    if (auto nl = err.find('\n'); nl != std::string::npos) err.resize(nl);
    throw file_error(path, "cannot read image" + (err.empty() ? std::string() : " (" + err + ")"));
  }
  const ImageSpec& spec = in->spec();
  if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0) throw file_error(path, "image has no pixels");
  // The header's size, checked before anything is allocated (a 69-byte PNG can claim 10^10 pixels).
  limits::check_image_size(path, uint64_t(spec.width), uint64_t(spec.height));
  limits::require_at_most(path, "channel count", uint64_t(spec.nchannels), 64);
  Image img(spec.width, spec.height, std::min(spec.nchannels, 3));
  img.from_float_file = spec.format.is_floating_point();
  // Only the channels kept are read: a header may claim 64 channels of a 2^28-pixel image.
  const int nread = img.channels;
  std::vector<float> all(size_t(spec.width) * size_t(spec.height) * size_t(nread));
  if (!in->read_image(0, 0, 0, nread, TypeDesc::FLOAT, all.data())) {
    std::string err = in->geterror();
    if (auto nl = err.find('\n'); nl != std::string::npos) err.resize(nl);
    throw file_error(path, "corrupt image (" + err + ")");
  }
  in->close();
  const bool srgb = decode_srgb && !img.from_float_file;
  for (size_t p = 0; p < img.pixel_count(); ++p)
    for (int c = 0; c < img.channels; ++c) {
      float v = all[p * size_t(nread) + size_t(c)];
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

// Portable float map: "PF" (RGB) or "Pf" (grey), width and height, a negative scale for
// little-endian data, then rows from the bottom up.
void write_pfm(const std::string& tmp, const std::string& path, const Image& image) {
  const bool grey = image.channels == 1;
  std::ofstream f(tmp, std::ios::binary);
  if (!f) throw file_error(path, "cannot open for writing");
  f << (grey ? "Pf" : "PF") << "\n" << image.width << " " << image.height << "\n-1.0\n";
  static_assert(std::endian::native == std::endian::little, "PFM is written as little-endian floats");
  std::vector<float> row(size_t(image.width) * (grey ? 1 : 3));
  for (int y = image.height - 1; y >= 0; --y) {
    for (int x = 0; x < image.width; ++x)
      for (int c = 0; c < (grey ? 1 : 3); ++c)
        row[size_t(x) * (grey ? 1 : 3) + size_t(c)] = image.at(x, y, std::min(c, image.channels - 1));
    f.write(reinterpret_cast<const char*>(row.data()), std::streamsize(row.size() * sizeof(float)));
  }
  f.flush();
  if (!f) {
    f.close();
    std::error_code ec;
    fs::remove(tmp, ec);
    throw file_error(path, "write failed");
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
  if (ext == ".pfm") {  // OpenImageIO 2.4 reads PFM but writes only 8-bit PNM
    write_pfm(tmp, path, image);
    commit(tmp, path);
    return;
  }
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
  write_bytes_atomic(path, text.data(), text.size());
}

void write_bytes_atomic(const std::string& path, const void* data, size_t size) {
  const std::string tmp = temp_name(path);
  {
    std::ofstream f(tmp, std::ios::binary);
    if (!f) throw file_error(path, "cannot open for writing");
    f.write(static_cast<const char*>(data), std::streamsize(size));
    f.flush();
    if (!f) {
      f.close();
      std::error_code ec;
      fs::remove(tmp, ec);
      throw file_error(path, "write failed");
    }
  }
  commit(tmp, path);
}

int remove_stale_temporaries(const std::string& dir) {
  // temp_name's pattern: "." stem ".tmp" PID extension. Only other processes' files go: this
  // process may be writing its own.
  static const std::regex pattern(R"(^\..*\.tmp([0-9]+)(\.[A-Za-z0-9]+)?$)");
  const std::string own = std::to_string(getpid());
  int removed = 0;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::smatch m;
    const std::string name = it->path().filename().string();
    if (!std::regex_match(name, m, pattern) || m[1].str() == own) continue;
    std::error_code rm;
    if (fs::remove(it->path(), rm)) ++removed;
  }
  return removed;
}

}  // namespace bl
