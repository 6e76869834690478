#pragma once
// The interface between backlight and its plugins: shared libraries opened on first use
// (engine/plugins/plugin.h), so that the libraries they link are loaded only by the runs that
// need them. OpenImageIO links ~260 shared libraries (GDAL, Poppler, FFmpeg, OpenCV, ...) and
// OpenVDB another dozen; loading them cost every `backlight` start ~0.2 s of CPU and ~100 MB of
// RSS. EXR, PNG and PFM are read and written without them (engine/io/image_io.cpp).
//
// Plugins are built with backlight by the same compiler against the same standard library, so
// the interface is C++ (strings, the engine's plain structs); each plugin exports one extern "C"
// function returning a table whose `abi` must equal kPluginAbi. Plugin functions never throw: a
// failure returns false / null with a message in *error.
#include <cstddef>
#include <string>
#include <vector>

#include "engine/scene/volume_io.h"

namespace bl::plugin {

inline constexpr int kPluginAbi = 1;

struct ImageHeader {
  int width = 0, height = 0, channels = 0;
  bool is_float = false;  // the file stores floats (Radiance HDR)
};

// libbacklight_oiio.so: the image formats backlight reads and writes through OpenImageIO (JPEG
// and Radiance HDR; see image_io.cpp for which formats go where).
struct OiioApi {
  int abi;
  // Opens an image of `format` (an OpenImageIO plugin name) from `bytes`, or from the file at
  // `path` when `bytes` is empty; `bytes` must outlive the reader. Returns null and *error on
  // failure. Nothing is decoded yet: the caller checks the header's size first.
  void* (*open)(const std::string& path, const std::string& format, const std::vector<unsigned char>& bytes,
                int image_limit_mb, ImageHeader* header, std::string* error);
  // Decodes the first `channels` channels as floats into out[width × height × channels].
  bool (*read)(void* reader, int channels, float* out, std::string* error);
  void (*close)(void* reader);
  // Writes a width × height × channels image to `path` (format from its extension): `floats`
  // stored as floats, or `bytes` (already sRGB-encoded) as 8-bit; exactly one is non-null.
  bool (*write)(const std::string& path, int width, int height, int channels, const float* floats,
                const unsigned char* bytes, std::string* error);
};

// libbacklight_openvdb.so: writing .vdb files. (Reading runs OpenVDB in a separate process,
// backlight-vdb-read: its reader is not safe on hostile files; see openvdb_io.h.)
struct OpenVdbApi {
  int abi;
  // Writes `grid` as one float (1 channel) or vec3s (3 channels) grid named `name` to `path`
  // (not atomically: the caller writes to a temporary name and renames).
  bool (*write)(const std::string& path, const VolumeGrid& grid, const std::string& name, std::string* error);
};

}  // namespace bl::plugin

extern "C" {
const bl::plugin::OiioApi* backlight_oiio_plugin();
const bl::plugin::OpenVdbApi* backlight_openvdb_plugin();
}
