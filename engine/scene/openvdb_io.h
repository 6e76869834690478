#pragma once
// Volume grids in and out of OpenVDB (.vdb) files, for interop with Houdini, Blender, Mitsuba 3
// and the OpenVDB tools.
//
// Mapping. OpenVDB stores voxels at integer index coordinates (i, j, k); a voxel's value is a
// point sample at index (i, j, k), i.e. the index coordinate of a voxel *centre* is an integer,
// and the grid's transform maps index space to world space. Reading densifies the active-voxel
// bounding box [min, max] (inclusive) into backlight's layout: voxel (ix, iy, iz) of the
// [Z, Y, X, C] parameter is VDB voxel (min.x + ix, min.y + iy, min.z + iz) (x fastest, as in
// .vol and a NumPy rho[iz, iy, ix]); inactive voxels inside the box take the grid's background
// value. The box of the unit cube (VolumeGrid::bbox_min / bbox_max) is the world image of index
// [min − ½, max + ½], so voxel centres land at local ((ix + ½)/X, ...), backlight's (and Mitsuba 3
// gridvolume's) convention. Only transforms made of a per-axis scale and a translation are
// accepted (a rotated grid would need a rotated box, which media do not have).
// Writing does the inverse with every voxel of the box active, so a write/read round trip keeps
// the dimensions and the box exactly; zip compression keeps the zeros of sparse media cheap.
#include <cstddef>
#include <string>
#include <vector>

#include "engine/scene/volume_io.h"

namespace bl {

// Limits of the reader process (see read_vdb).
struct VdbReadLimits {
  // A crafted file of a few bytes can make OpenVDB allocate gigabytes (length fields are
  // trusted) or loop for minutes. 0 = $BACKLIGHT_VDB_MEMORY_MB, else 4096: enough for dense grids
  // of ~400 M floats (OpenVDB's tree and the dense copy coexist while reading).
  size_t memory_mb = 0;  // address space of the reader process (RSS limit under ASan)
  double seconds = 300;  // wall-clock time before the reader is killed
};

// Reads the float grid (one channel) or vec3s grid (three channels) named `grid_name`; an empty
// name picks the only float/vec3s grid, or the one named "density". Sizes are checked against
// limits::kGridVoxels before the dense array is allocated; every value must be finite. Errors
// are InputError "<file>: <problem>" (never an OpenVDB exception).
//
// OpenVDB's reader is not safe on hostile files (fuzzing finds invalid-bool loads, unbounded
// allocations and endless loops inside OpenVDB within seconds), so the file is parsed by the
// helper executable `backlight-vdb-read` in its own process under `limits`, which hands the
// dense grid back as a .vol in a private temporary folder. A reader that crashes, exceeds its
// memory or runs out of time becomes a one-line InputError naming the file. The helper is found
// through $BACKLIGHT_VDB_READER, next to the running executable, or in the build tree.
VolumeGrid read_vdb(const std::string& path, const std::string& grid_name = "", const VdbReadLimits& limits = {});
// Writes atomically (temporary file + rename) as a grid named `grid_name`.
void write_vdb(const std::string& path, const VolumeGrid& grid, const std::string& grid_name);

}  // namespace bl
