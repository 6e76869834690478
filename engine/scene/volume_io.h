#pragma once
// Volume grids in and out: Mitsuba's binary .vol format (the interchange format of the Mitsuba 3
// references in ../shared/reference/mitsuba3-volume/).
// Layout, little endian: 'V' 'O' 'L', version 3 (uint8), encoding 1 = float32 (int32), nx, ny, nz,
// channels (int32 each), bbox xmin, ymin, zmin, xmax, ymax, zmax (float32), then nx·ny·nz·channels
// float32 values, x fastest, channels interleaved: value (ix, iy, iz, c) is number
// ((iz·ny + iy)·nx + ix)·channels + c — the [Z, Y, X, C] layout of backlight's grid parameters.
#include <string>
#include <vector>

#include "engine/core/math.h"

namespace bl {

struct VolumeGrid {
  int x = 0, y = 0, z = 0, channels = 1;
  Vec3f bbox_min{0.f, 0.f, 0.f}, bbox_max{1.f, 1.f, 1.f};
  std::vector<float> data;
  std::vector<int> shape() const { return {z, y, x, channels}; }  // a grid parameter's shape
  size_t voxels_checked() const { return size_t(x) * size_t(y) * size_t(z) * size_t(channels); }
};

// Reads and validates a .vol file (sizes checked against the file length and the limits before
// allocating; every value finite). Errors are InputError "<file>: <problem>".
VolumeGrid read_vol(const std::string& path);
// Writes atomically (temporary file + rename).
void write_vol(const std::string& path, const VolumeGrid& grid);
// The same with the values given apart (grid.data is ignored): no copy of a large grid.
void write_vol(const std::string& path, const VolumeGrid& grid, const std::vector<float>& data);

}  // namespace bl
