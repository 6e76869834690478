// libbacklight_openvdb.so: writing .vdb files with OpenVDB (plugin_api.h), opened by write_vdb
// (engine/scene/openvdb_io.cpp) on the first grid written, so that other runs never load OpenVDB.
#include <openvdb/io/Stream.h>
#include <openvdb/openvdb.h>

#include <fstream>
#include <type_traits>

#include "engine/plugins/plugin_api.h"

namespace {

template <class GridT>
typename GridT::Ptr make_grid(const bl::VolumeGrid& g) {
  auto grid = GridT::create(typename GridT::ValueType(0.f));
  auto acc = grid->getAccessor();
  size_t i = 0;
  for (int z = 0; z < g.z; ++z)
    for (int y = 0; y < g.y; ++y)
      for (int x = 0; x < g.x; ++x) {
        typename GridT::ValueType v;
        if constexpr (std::is_same_v<GridT, openvdb::FloatGrid>)
          v = g.data[i++];
        else
          v = openvdb::Vec3s(g.data[i], g.data[i + 1], g.data[i + 2]), i += 3;
        acc.setValueOn(openvdb::Coord(x, y, z), v);
      }
  return grid;
}

bool write_vdb(const std::string& path, const bl::VolumeGrid& g, const std::string& name, std::string* error) {
  try {
    openvdb::initialize();
    openvdb::GridBase::Ptr grid;
    if (g.channels == 1)
      grid = make_grid<openvdb::FloatGrid>(g);
    else
      grid = make_grid<openvdb::Vec3SGrid>(g);
    grid->setName(name);
    // Index i ↦ world centre of voxel i: bbox_min + (i + ½)·voxel size, per axis.
    const double vx = (double(g.bbox_max.x) - g.bbox_min.x) / g.x, vy = (double(g.bbox_max.y) - g.bbox_min.y) / g.y,
                 vz = (double(g.bbox_max.z) - g.bbox_min.z) / g.z;
    openvdb::math::Mat4d m(vx, 0., 0., 0., 0., vy, 0., 0., 0., 0., vz, 0., g.bbox_min.x + 0.5 * vx,
                           g.bbox_min.y + 0.5 * vy, g.bbox_min.z + 0.5 * vz, 1.);
    grid->setTransform(openvdb::math::Transform::createLinearTransform(m));
    grid->setGridClass(openvdb::GRID_FOG_VOLUME);
    openvdb::io::File file(path);
    file.setCompression(openvdb::io::COMPRESS_ZIP | openvdb::io::COMPRESS_ACTIVE_MASK);
    file.write({grid});
    file.close();
    // OpenVDB does not check its writes: a file cut short by a full disk or a file size limit
    // was renamed into place as if complete (helper-45). What was written must read back whole.
    std::ifstream in(path, std::ios::binary);
    openvdb::io::Stream back(in, /*delayLoad=*/false);
    if (!in || in.fail() || back.getGrids()->size() != 1) {
      *error = "write failed (the file written does not read back whole: a full disk or a file size limit?)";
      return false;
    }
    return true;
  } catch (const std::exception& e) {
    *error = std::string("cannot write OpenVDB file (") + e.what() + ")";
    return false;
  }
}

const bl::plugin::OpenVdbApi api = {bl::plugin::kPluginAbi, write_vdb};

}  // namespace

extern "C" __attribute__((visibility("default"))) const bl::plugin::OpenVdbApi* backlight_openvdb_plugin() {
  return &api;
}
