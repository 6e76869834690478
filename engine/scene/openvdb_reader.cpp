#include "engine/scene/openvdb_reader.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <mutex>

#include <openvdb/io/Stream.h>
#include <openvdb/openvdb.h>

#include "engine/core/errors.h"
#include "engine/core/limits.h"

namespace bl {

namespace fs = std::filesystem;

void openvdb_initialize_once() {
  static std::once_flag once;
  std::call_once(once, [] { openvdb::initialize(); });
}

namespace {

bool supported(const openvdb::GridBase& g) { return g.isType<openvdb::FloatGrid>() || g.isType<openvdb::Vec3SGrid>(); }

template <class GridT, int C>
void densify(const GridT& grid, const openvdb::CoordBBox& box, VolumeGrid& out, const std::string& path) {
  auto acc = grid.getConstAccessor();
  size_t i = 0;
  for (int z = box.min().z(); z <= box.max().z(); ++z)
    for (int y = box.min().y(); y <= box.max().y(); ++y)
      for (int x = box.min().x(); x <= box.max().x(); ++x) {
        const auto v = acc.getValue(openvdb::Coord(x, y, z));
        for (int c = 0; c < C; ++c) {
          float f;
          if constexpr (C == 1)
            f = v;
          else
            f = v[c];
          if (!std::isfinite(f))
            throw file_error(path, "voxel (" + std::to_string(x) + ", " + std::to_string(y) + ", " + std::to_string(z) +
                                       ") is not a finite number");
          out.data[i++] = f;
        }
      }
}

VolumeGrid read_unguarded(const std::string& path, const std::string& grid_name, const std::function<void()>& parsed) {
  require_input_file(path);
  limits::require_at_most(path, "file size", uint64_t(fs::file_size(path)), limits::kFileBytes);
  openvdb_initialize_once();
  // Read through a stream of our own, not openvdb::io::File: OpenVDB does not check its reads,
  // and the bundled smoke grid cut short by 1 to 7 bytes loaded with garbage in its last voxel.
  // The stream's state after the whole file is read tells (no delayed loading: the file may
  // change under us). Every grid of the file is read, not only the chosen one: the reader's
  // memory limit covers them all.
  std::ifstream in(path, std::ios::binary);
  if (!in) throw file_error(path, "cannot open the file");
  openvdb::io::Stream stream(in, /*delayLoad=*/false);
  if (in.fail()) throw file_error(path, "the file is cut short (it ends inside its grids' data)");
  openvdb::GridPtrVecPtr grids = stream.getGrids();
  std::string chosen, candidates;
  openvdb::GridBase::Ptr base;
  int supported_count = 0;
  for (const auto& g : *grids) {
    candidates += (candidates.empty() ? "" : ", ") + printable_name(g->getName()) + " (" + g->valueType() + ")";
    if (!supported(*g)) continue;
    ++supported_count;
    if (!grid_name.empty() ? g->getName() == grid_name && !base
                           : (g->getName() == "density" && chosen != "density") || chosen.empty()) {
      chosen = g->getName();
      base = g;
    }
  }
  if (grids->empty()) throw file_error(path, "no grids in the file");
  if (!grid_name.empty() && chosen.empty())
    throw file_error(path,
                     "no float or vec3s grid named '" + printable_name(grid_name) + "' (grids: " + candidates + ")");
  if (grid_name.empty() && (supported_count == 0 || (supported_count > 1 && chosen != "density")))
    throw file_error(path, supported_count == 0 ? "no float or vec3s grid (grids: " + candidates + ")"
                                                : "several grids; name one (grids: " + candidates + ")");
  chosen = printable_name(chosen);  // for messages
  if (parsed) parsed();
  const openvdb::CoordBBox box = base->evalActiveVoxelBoundingBox();
  if (box.empty()) throw file_error(path, "grid '" + chosen + "' has no active voxels");
  // Extent in 64 bits: CoordBBox::dim() overflows int32 for voxels far apart.
  uint64_t extent[3];
  for (int a = 0; a < 3; ++a) extent[a] = uint64_t(int64_t(box.max()[a]) - int64_t(box.min()[a]) + 1);
  const int channels = base->isType<openvdb::FloatGrid>() ? 1 : 3;
  limits::checked_product(path, "dense size of grid '" + chosen + "' (voxels × channels)",
                          {extent[0], extent[1], extent[2], uint64_t(channels)}, limits::kGridVoxels);
  VolumeGrid out;
  out.x = int(extent[0]), out.y = int(extent[1]), out.z = int(extent[2]);
  out.channels = channels;
  // Transform: a per-axis scale and a translation only.
  const openvdb::math::Transform& t = base->transform();
  if (!t.isLinear()) throw file_error(path, "grid '" + chosen + "' has a non-linear transform");
  const openvdb::Vec3d o = t.indexToWorld(openvdb::Vec3d(0, 0, 0));
  for (int a = 0; a < 3; ++a) {
    openvdb::Vec3d e(0, 0, 0);
    e[a] = 1;
    const openvdb::Vec3d axis = t.indexToWorld(e) - o;
    for (int b = 0; b < 3; ++b)
      if (b != a && std::abs(axis[b]) > 1e-9 * axis.length())
        throw file_error(path,
                         "grid '" + chosen + "' is rotated or sheared (only scale and translation are supported)");
    if (!(axis[a] > 0)) throw file_error(path, "grid '" + chosen + "' has a mirrored or degenerate transform");
  }
  const openvdb::Vec3d lo = t.indexToWorld(box.min().asVec3d() - openvdb::Vec3d(0.5));
  const openvdb::Vec3d hi = t.indexToWorld(box.max().asVec3d() + openvdb::Vec3d(0.5));
  for (int a = 0; a < 3; ++a)
    if (!(std::abs(lo[a]) <= limits::kCoordinate && std::abs(hi[a]) <= limits::kCoordinate && hi[a] > lo[a] &&
          float(hi[a]) > float(lo[a])))
      throw file_error(path, "grid '" + chosen + "' has a world box that is not finite, too large or degenerate");
  out.bbox_min = {float(lo.x()), float(lo.y()), float(lo.z())};
  out.bbox_max = {float(hi.x()), float(hi.y()), float(hi.z())};
  out.data.resize(out.voxels_checked());
  if (out.channels == 1)
    densify<openvdb::FloatGrid, 1>(*openvdb::gridPtrCast<openvdb::FloatGrid>(base), box, out, path);
  else
    densify<openvdb::Vec3SGrid, 3>(*openvdb::gridPtrCast<openvdb::Vec3SGrid>(base), box, out, path);
  return out;
}

}  // namespace

VolumeGrid read_vdb_in_process(const std::string& path, const std::string& grid_name,
                               const std::function<void()>& parsed) {
  return with_path_errors([&] {
    try {
      return read_unguarded(path, grid_name, parsed);
    } catch (const InputError&) {
      throw;
    } catch (const std::bad_alloc&) {
      throw;  // the reader process names its memory limit
    } catch (const std::exception& e) {
      std::string what = e.what();
      if (auto nl = what.find('\n'); nl != std::string::npos) what.resize(nl);
      throw file_error(path, "cannot read OpenVDB file (" + what.substr(0, 200) + ")");
    }
  });
}

}  // namespace bl
