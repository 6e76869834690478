#pragma once
// Images in and out: OpenEXR and PNG through OpenEXR and libpng, PFM directly, JPEG and Radiance
// HDR through OpenImageIO in a plugin opened on first use (engine/plugins/). Pixel data is row-major, row 0 on top (the
// first scanline), interleaved channels, linear float. Files are written atomically: to a temporary name in the same
// folder, then renamed, so a killed run never leaves a truncated file.
#include <string>
#include <vector>

namespace bl {

struct Image {
  int width = 0, height = 0, channels = 3;
  std::vector<float> data;
  bool from_float_file = false;  // the file stored floats (EXR, HDR, PFM)

  Image() = default;
  Image(int w, int h, int c = 3) : width(w), height(h), channels(c), data(size_t(w) * size_t(h) * size_t(c), 0.f) {}
  float& at(int x, int y, int c) {
    return data[(size_t(y) * size_t(width) + size_t(x)) * size_t(channels) + size_t(c)];
  }
  float at(int x, int y, int c) const {
    return data[(size_t(y) * size_t(width) + size_t(x)) * size_t(channels) + size_t(c)];
  }
  size_t pixel_count() const { return size_t(width) * size_t(height); }
};

// The mean of every k×k block (width and height must be multiples of k): the image a film of
// 1/k the resolution records, pixels being box-filtered.
Image box_downsample(const Image& image, int k);

// Reads PNG, OpenEXR, JPEG, Radiance HDR and PFM, chosen by the file's first bytes (not its
// name). 8/16-bit files are decoded from sRGB to linear when `decode_srgb`; float files are
// returned as stored. One channel (grey; EXR: Y) or three (RGB; EXR: R, G, B); alpha is not read. Errors (missing,
// corrupt, NaN/inf) throw InputError naming the file.
Image read_image(const std::string& path, bool decode_srgb);
Image read_image_unguarded(const std::string& path, bool decode_srgb);  // read_image without path-error mapping
// Before decoding an encoded PNG or JPEG held in memory: its header's pixel size is within the
// image limits and, for PNG, its bytes can hold that many pixels (deflate expands at most ~1032-
// fold): a few hundred bytes claiming 16000 × 16000 pixels must not allocate 768 MB first. Errors
// name `where`; other formats pass unchecked.
void check_encoded_image(const std::string& where, const unsigned char* bytes, size_t size);
// Throws InputError unless the extension is one write_image supports (check before long work).
void check_output_format(const std::string& path);
// check_output_format, and that the output's folder takes new files (before long work).
void check_output_creatable(const std::string& path);
// Writes by extension: .exr/.pfm/.hdr as float, .png/.jpg as 8-bit clamped to [0, 1], sRGB-encoded
// when `encode_srgb` (a linear texture's own values otherwise, so that reading the file back in
// its colour space gives them again). Atomic.
void write_image(const std::string& path, const Image& image, bool encode_srgb = true);
// Writes `text` to `path` atomically (temp file + rename).
void write_text_atomic(const std::string& path, const std::string& text);
// The same for raw bytes, written straight from `data` (no copy).
void write_bytes_atomic(const std::string& path, const void* data, size_t size);
// Flushes the regular files directly in `dir`, then `dir` itself, to the disk (fsync): the atomic
// writes above survive a kill (old file or new, never a cut one), but after a power cut a file
// renamed into place may come back empty unless its data reached the disk before the rename.
// An optimize checkpoint calls it before its directory swap. One line naming `dir` on failure.
void sync_folder(const std::string& dir);
// fsync of one file or folder (`path`), one line naming it on failure.
void sync_path(const std::string& path);
// Deletes, under `dir` (recursively, or only in `dir` itself), the temporaries that
// write_image/write_text_atomic of another process left behind when it was killed before its
// rename: names ".<stem>.tmp<pid>.<ext>" whose stem matches `stem` (a regular expression) and
// whose process no longer runs. Returns how many.
int remove_stale_temporaries(const std::string& dir, bool recursive = true, const std::string& stem = ".*");
// Whether process `pid` (decimal digits) is gone: no such process, or a zombie that will write
// nothing more. Used to remove what killed processes left behind.
bool process_gone(const std::string& pid_digits);
// `text` as a regular expression matching exactly it (a file name's stem for the above).
std::string regex_escaped(const std::string& text);

float srgb_to_linear(float v);
float linear_to_srgb(float v);

}  // namespace bl
