#include "engine/scene/volume_io.h"

#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include "engine/core/errors.h"
#include "engine/core/limits.h"

namespace bl {

namespace {
constexpr size_t kHeaderBytes = 48;  // magic 3, version 1, encoding 4, dims 12, channels 4, bbox 24

int32_t read_i32(const std::string& bytes, size_t at) {
  int32_t v;
  std::memcpy(&v, bytes.data() + at, 4);
  return v;
}
float read_f32(const std::string& bytes, size_t at) {
  float v;
  std::memcpy(&v, bytes.data() + at, 4);
  return v;
}
}  // namespace

VolumeGrid read_vol(const std::string& path) {
  return with_path_errors([&] {
    namespace fs = std::filesystem;
    require_input_file(path);
    const uint64_t file_bytes = fs::file_size(path);
    limits::require_at_most(path, "file size", file_bytes, limits::kFileBytes);
    std::ifstream f(path, std::ios::binary);
    std::string bytes(kHeaderBytes, '\0');
    if (!f.read(bytes.data(), std::streamsize(kHeaderBytes))) throw file_error(path, "truncated .vol header");
    if (bytes.compare(0, 3, "VOL") != 0) throw file_error(path, "not a .vol file (expected the magic 'VOL')");
    if (uint8_t(bytes[3]) != 3)
      throw file_error(path, "unsupported .vol version " + std::to_string(uint8_t(bytes[3])) + " (expected 3)");
    if (read_i32(bytes, 4) != 1)
      throw file_error(path,
                       "unsupported .vol encoding " + std::to_string(read_i32(bytes, 4)) + " (expected 1, float32)");
    VolumeGrid g;
    g.x = read_i32(bytes, 8), g.y = read_i32(bytes, 12), g.z = read_i32(bytes, 16), g.channels = read_i32(bytes, 20);
    if (g.x < 1 || g.y < 1 || g.z < 1 || g.channels < 1)
      throw file_error(path, "grid dimensions must be positive (got " + std::to_string(g.x) + "×" +
                                 std::to_string(g.y) + "×" + std::to_string(g.z) + ", " + std::to_string(g.channels) +
                                 " channels)");
    if (g.channels != 1 && g.channels != 3)
      throw file_error(path, std::to_string(g.channels) + " channels (expected 1 or 3)");
    const uint64_t voxels = limits::checked_product(path, "voxel count", {uint64_t(g.x), uint64_t(g.y), uint64_t(g.z)},
                                                    limits::kGridVoxels);
    const uint64_t values = voxels * uint64_t(g.channels);
    if (file_bytes != kHeaderBytes + values * 4)
      throw file_error(path, "file has " + std::to_string(file_bytes) + " bytes; a " + std::to_string(g.x) + "×" +
                                 std::to_string(g.y) + "×" + std::to_string(g.z) + "×" + std::to_string(g.channels) +
                                 " grid needs " + std::to_string(kHeaderBytes + values * 4));
    for (int a = 0; a < 3; ++a) g.bbox_min[a] = read_f32(bytes, 24 + 4 * size_t(a));
    for (int a = 0; a < 3; ++a) g.bbox_max[a] = read_f32(bytes, 36 + 4 * size_t(a));
    g.data.resize(size_t(values));
    if (!f.read(reinterpret_cast<char*>(g.data.data()), std::streamsize(values * 4)))
      throw file_error(path, "truncated .vol data");
    for (size_t i = 0; i < g.data.size(); ++i)
      if (!std::isfinite(g.data[i])) {
        const size_t voxel = i / size_t(g.channels);
        throw file_error(path, "voxel (" + std::to_string(voxel % size_t(g.x)) + ", " +
                                   std::to_string(voxel / size_t(g.x) % size_t(g.y)) + ", " +
                                   std::to_string(voxel / (size_t(g.x) * size_t(g.y))) + ") is not a finite number");
      }
    return g;
  });
}

void write_vol(const std::string& path, const VolumeGrid& g) { write_vol(path, g, g.data); }

void write_vol(const std::string& path, const VolumeGrid& g, const std::vector<float>& data) {
  if (data.size() != g.voxels_checked()) throw InputError(path + ": grid data size does not match its dimensions");
  char header[kHeaderBytes] = {'V', 'O', 'L', char(3)};
  const int32_t ints[5] = {1, g.x, g.y, g.z, g.channels};
  std::memcpy(header + 4, ints, sizeof ints);
  const float bbox[6] = {g.bbox_min.x, g.bbox_min.y, g.bbox_min.z, g.bbox_max.x, g.bbox_max.y, g.bbox_max.z};
  std::memcpy(header + 24, bbox, sizeof bbox);
  // Streamed into a temporary next to the target (no copy of the grid), then renamed: a killed
  // run never leaves a truncated file, and remove_stale_temporaries recognises the name.
  const std::filesystem::path p(path);
  const std::string tmp =
      (p.parent_path() / ("." + p.stem().string() + ".tmp" + std::to_string(::getpid()) + p.extension().string()))
          .string();
  {
    std::ofstream f(tmp, std::ios::binary);
    if (!f) throw file_error(path, "cannot open for writing");
    f.write(header, kHeaderBytes);
    f.write(reinterpret_cast<const char*>(data.data()), std::streamsize(data.size() * sizeof(float)));
    f.flush();
    if (!f) {
      f.close();
      std::error_code ec;
      std::filesystem::remove(tmp, ec);
      throw file_error(path, "write failed");
    }
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    throw file_error(path, "cannot write (rename failed)");
  }
}

}  // namespace bl
