// OpenVDB grids: exact round trips, the index ↔ [Z, Y, X, C] ↔ world mapping of a file written
// with OpenVDB's own API, and bad files (one-line InputError, sizes checked before allocating).
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <random>

#include <openvdb/openvdb.h>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/grid_view.h"
#include "engine/scene/openvdb_io.h"
#include "test_scenes.h"

using namespace bl;

namespace {
std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

VolumeGrid random_grid(int x, int y, int z, int c, unsigned seed) {
  VolumeGrid g;
  g.x = x, g.y = y, g.z = z, g.channels = c;
  g.bbox_min = {-0.5f, 0.25f, 1.f};
  g.bbox_max = {1.5f, 0.75f, 4.f};
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.f, 3.f);
  for (size_t i = 0; i < g.voxels_checked(); ++i) g.data.push_back(i % 5 == 0 ? 0.f : u(rng));
  return g;
}

// Writes a file with OpenVDB directly: uniform voxel size 0.1, voxels (2,3,4)..(5,6,7) active,
// value 100·x + 10·y + z.
void write_reference_file(const std::string& path, const std::string& name) {
  openvdb::initialize();
  auto grid = openvdb::FloatGrid::create(0.f);
  grid->setName(name);
  grid->setTransform(openvdb::math::Transform::createLinearTransform(0.1));
  auto acc = grid->getAccessor();
  for (int x = 2; x <= 5; ++x)
    for (int y = 3; y <= 6; ++y)
      for (int z = 4; z <= 7; ++z) acc.setValueOn(openvdb::Coord(x, y, z), float(100 * x + 10 * y + z));
  openvdb::io::File(path).write({grid});
}
// A float grid with two active voxels, (0, 0, 0) = 1 and (far, far, far) = 2: its dense box has
// (far + 1)³ voxels.
openvdb::FloatGrid::Ptr two_voxels(const std::string& name, int far) {
  openvdb::initialize();
  auto grid = openvdb::FloatGrid::create(0.f);
  grid->setName(name);
  grid->tree().setValueOn(openvdb::Coord(0, 0, 0), 1.f);
  grid->tree().setValueOn(openvdb::Coord(far, far, far), 2.f);
  return grid;
}
}  // namespace

TEST_CASE("OpenVDB round trip keeps values, dimensions and the box", "[volume][io][vdb]") {
  const std::string dir = test::temp_dir("vdb");
  for (int c : {1, 3}) {
    const VolumeGrid g = c == 1 ? random_grid(7, 5, 3, 1, 1) : random_grid(4, 3, 2, 3, 2);
    write_vdb(dir + "/g.vdb", g, "density");
    const VolumeGrid back = read_vdb(dir + "/g.vdb", "density");
    CHECK(back.x == g.x);
    CHECK(back.y == g.y);
    CHECK(back.z == g.z);
    CHECK(back.channels == c);
    REQUIRE(back.data.size() == g.data.size());
    CHECK(back.data == g.data);
    for (int a = 0; a < 3; ++a) {
      CHECK(std::abs(back.bbox_min[a] - g.bbox_min[a]) < 1e-6f);
      CHECK(std::abs(back.bbox_max[a] - g.bbox_max[a]) < 1e-6f);
    }
    // The only grid is found without its name too.
    CHECK(read_vdb(dir + "/g.vdb").data == g.data);
  }
}

TEST_CASE("OpenVDB index space maps to [Z, Y, X] and to world as documented", "[volume][io][vdb]") {
  const std::string dir = test::temp_dir("vdbref");
  write_reference_file(dir + "/ref.vdb", "smoke");
  const VolumeGrid g = read_vdb(dir + "/ref.vdb", "smoke");
  CHECK(g.x == 4);
  CHECK(g.y == 4);
  CHECK(g.z == 4);
  // Index box [2, 5] × [3, 6] × [4, 7] widened by half a voxel, times 0.1.
  CHECK(std::abs(g.bbox_min.x - 0.15f) < 1e-6f);
  CHECK(std::abs(g.bbox_min.y - 0.25f) < 1e-6f);
  CHECK(std::abs(g.bbox_min.z - 0.35f) < 1e-6f);
  CHECK(std::abs(g.bbox_max.x - 0.55f) < 1e-6f);
  CHECK(std::abs(g.bbox_max.y - 0.65f) < 1e-6f);
  CHECK(std::abs(g.bbox_max.z - 0.75f) < 1e-6f);
  // VDB voxel (3, 5, 6) is [Z, Y, X] = [2, 2, 1].
  CHECK(g.data[(size_t(2) * 4 + 2) * 4 + 1] == 356.f);
  CHECK(g.data[0] == 234.f);
}

TEST_CASE("bad OpenVDB files are one-line input errors", "[volume][io][vdb]") {
  const std::string dir = test::temp_dir("vdbbad");
  CHECK(error_of([&] { read_vdb(dir + "/missing.vdb"); }).find("file not found") != std::string::npos);
  std::ofstream(dir + "/text.vdb") << "not a vdb file at all";
  const std::string text = error_of([&] { read_vdb(dir + "/text.vdb"); });
  CHECK(text.find("text.vdb") != std::string::npos);
  CHECK(text.find('\n') == std::string::npos);
  write_reference_file(dir + "/ref.vdb", "smoke");
  const std::string name = error_of([&] { read_vdb(dir + "/ref.vdb", "dens"); });
  CHECK(name.find("no float or vec3s grid named 'dens'") != std::string::npos);
  CHECK(name.find("smoke") != std::string::npos);  // lists what there is
  // Two far-apart active voxels: a dense box of 2001³ voxels, refused before allocating.
  openvdb::io::File(dir + "/huge.vdb").write({two_voxels("density", 2000)});
  CHECK(error_of([&] { read_vdb(dir + "/huge.vdb"); }).find("exceeds the limit") != std::string::npos);
  // NaN voxels.
  {
    auto grid = openvdb::FloatGrid::create(0.f);
    grid->setName("density");
    grid->tree().setValueOn(openvdb::Coord(1, 1, 1), std::nanf(""));
    openvdb::io::File(dir + "/nan.vdb").write({grid});
  }
  CHECK(error_of([&] { read_vdb(dir + "/nan.vdb"); }).find("not a finite number") != std::string::npos);
}

// Grid choice without a name, and transforms a box cannot express.
TEST_CASE("OpenVDB grid choice and unsupported transforms", "[volume][io][vdb]") {
  const std::string dir = test::temp_dir("vdbchoice");
  openvdb::io::File(dir + "/two.vdb").write({two_voxels("heat", 1), two_voxels("temperature", 1)});
  const std::string several = error_of([&] { read_vdb(dir + "/two.vdb"); });
  CHECK(several.find("several grids") != std::string::npos);
  CHECK(several.find("heat") != std::string::npos);
  CHECK(several.find("temperature") != std::string::npos);
  // "density" wins among several when no name is given.
  openvdb::io::File(dir + "/dens.vdb").write({two_voxels("heat", 1), two_voxels("density", 2)});
  CHECK(read_vdb(dir + "/dens.vdb").x == 3);
  // A rotation would need a rotated box; a frustum is not affine at all.
  auto rotated = two_voxels("density", 1);
  openvdb::math::Mat4d m = openvdb::math::Mat4d::identity();
  m.setToRotation(openvdb::math::Z_AXIS, 0.3);
  rotated->setTransform(openvdb::math::Transform::createLinearTransform(m));
  openvdb::io::File(dir + "/rot.vdb").write({rotated});
  CHECK(error_of([&] { read_vdb(dir + "/rot.vdb"); }).find("rotated or sheared") != std::string::npos);
  auto frustum = two_voxels("density", 1);
  frustum->setTransform(
      openvdb::math::Transform::createFrustumTransform(openvdb::BBoxd({0, 0, 0}, {10, 10, 10}), 0.5, 2.0, 0.5));
  openvdb::io::File(dir + "/frustum.vdb").write({frustum});
  CHECK(error_of([&] { read_vdb(dir + "/frustum.vdb"); }).find("non-linear transform") != std::string::npos);
  // Voxels 2^31 - 2 apart: the extent overflows int32 and must still be refused by size.
  openvdb::io::File(dir + "/far.vdb").write({two_voxels("density", std::numeric_limits<int>::max() - 2)});
  auto far_grid = two_voxels("density", -std::numeric_limits<int>::max() + 2);
  far_grid->tree().setValueOn(openvdb::Coord(std::numeric_limits<int>::max() - 2), 3.f);
  openvdb::io::File(dir + "/farther.vdb").write({far_grid});
  CHECK(error_of([&] { read_vdb(dir + "/far.vdb"); }).find("dense size") != std::string::npos);
  CHECK(error_of([&] { read_vdb(dir + "/farther.vdb"); }).find("dense size") != std::string::npos);
  // A voxel size beyond the coordinate limit gives a world box the scene cannot hold.
  auto huge = two_voxels("density", 1);
  huge->setTransform(openvdb::math::Transform::createLinearTransform(1e30));
  openvdb::io::File(dir + "/huge.vdb").write({huge});
  CHECK(error_of([&] { read_vdb(dir + "/huge.vdb"); }).find("world box") != std::string::npos);
  // The writer refuses a grid whose sizes disagree with its values instead of reading past them.
  VolumeGrid bad = random_grid(2, 2, 2, 1, 5);
  bad.data.pop_back();
  CHECK(error_of([&] { write_vdb(dir + "/short.vdb", bad, "density"); }).find("do not match") != std::string::npos);
  CHECK(!std::filesystem::exists(dir + "/short.vdb"));
}

TEST_CASE("grid sheets show four panels of the grid's values", "[volume][io]") {
  const VolumeGrid g = random_grid(8, 6, 4, 1, 3);
  const Image sheet = grid_sheet({&g.data, g.x, g.y, g.z, 1}, 3.f, 60);
  CHECK(sheet.height == 60);
  // Panels 8×6, 8×4, 4×6, 8×6 scaled to height 60, with three 4-pixel gaps.
  CHECK(sheet.width == 80 + 120 + 40 + 80 + 12);
  const std::string dir = test::temp_dir("sheet");
  write_grid_picture(dir + "/s.png", sheet);
  const Image back = read_image(dir + "/s.png", false);
  CHECK(back.width == sheet.width);
  // Code values are proportional to the values (value / vmax).
  float worst = 0.f;
  for (size_t i = 0; i < sheet.data.size(); ++i) worst = std::max(worst, std::abs(back.data[i] - sheet.data[i]));
  CHECK(worst <= 0.5f / 255.f + 1e-6f);
}

// OpenVDB parses in a helper process under memory and time limits: a crafted file that makes
// OpenVDB allocate what a length field says, or a small file that inflates to a 1.5 GB grid,
// ends as one-line errors, the helper's temporary folder is gone afterwards, and a missing
// helper is an error too (not a crash).
TEST_CASE("OpenVDB files are read in a helper process under limits", "[volume][io][vdb]") {
  const std::string bad = std::string(BL_SOURCE_DIR) + "/tests/data/bad/";
  const std::string dir = test::temp_dir("vdblimits");
  const char* old_tmp = std::getenv("TMPDIR");
  const std::string saved_tmp = old_tmp ? old_tmp : "";
  ::setenv("TMPDIR", dir.c_str(), 1);
  const std::string alloc = error_of([&] { read_vdb(bad + "vdb_fuzz_string_alloc.vdb", "", {256, 60}); });
  CHECK(alloc.rfind(bad + "vdb_fuzz_string_alloc.vdb: cannot read OpenVDB file (", 0) == 0);
  CHECK(alloc.find('\n') == std::string::npos);
  // The fuzzer's 7 KB that inflated to a 1.5 GB grid: its stream ends inside the grid's data (OpenVDB
  // read past the end without a word), which the reader now says before inflating anything.
  const std::string cut = error_of([&] { read_vdb(bad + "vdb_fuzz_grid_1p5GB.vdb", "", {512, 60}); });
  CHECK(cut.rfind(bad + "vdb_fuzz_grid_1p5GB.vdb: the file is cut short", 0) == 0);
  // A valid file that inflates: two active voxels, a dense box of 730³ floats (1.56 GB).
  openvdb::io::File(dir + "/inflates.vdb").write({two_voxels("density", 729)});
  const std::string slow = error_of([&] { read_vdb(dir + "/inflates.vdb", "", {4096, 0.05}); });
  CHECK(slow.find("took longer than") != std::string::npos);
  const std::string big = error_of([&] { read_vdb(dir + "/inflates.vdb", "", {512, 60}); });
  CHECK(big.find("512 MB") != std::string::npos);
  std::filesystem::remove(dir + "/inflates.vdb");
  const std::string invalid = error_of([&] { read_vdb(bad + "vdb_fuzz_invalid_bool.vdb", "", {512, 60}); });
  CHECK(invalid.rfind(bad + "vdb_fuzz_invalid_bool.vdb: ", 0) == 0);
  // Nothing left behind in TMPDIR.
  CHECK(std::distance(std::filesystem::directory_iterator(dir), std::filesystem::directory_iterator()) == 0);
  if (old_tmp)
    ::setenv("TMPDIR", saved_tmp.c_str(), 1);
  else
    ::unsetenv("TMPDIR");
  // A valid file still reads with the limits, and the helper can be named explicitly.
  const VolumeGrid g = random_grid(3, 2, 2, 1, 9);
  write_vdb(dir + "/ok.vdb", g, "density");
  CHECK(read_vdb(dir + "/ok.vdb", "", {512, 60}).data == g.data);
  ::setenv("BACKLIGHT_VDB_READER", (dir + "/no-such-reader").c_str(), 1);
  const std::string missing = error_of([&] { read_vdb(dir + "/ok.vdb"); });
  ::unsetenv("BACKLIGHT_VDB_READER");
  CHECK(missing.find("cannot start the OpenVDB reader") != std::string::npos);
}
