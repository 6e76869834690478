// Mitsuba's .vol format: round trip, the Mitsuba 3 reference grid, and bad files (one-line
// InputError, checked before allocating).
#include <catch2/catch.hpp>

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include "engine/core/errors.h"
#include "engine/scene/volume_io.h"

using namespace bl;
namespace fs = std::filesystem;

namespace {
std::string temp_path(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / ("backlight-test-vol-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  return (dir / name).string();
}
std::string header(int version, int encoding, int x, int y, int z, int c) {
  std::string h = "VOL";
  h += char(version);
  const int32_t ints[5] = {encoding, x, y, z, c};
  h.append(reinterpret_cast<const char*>(ints), sizeof ints);
  const float bbox[6] = {0, 0, 0, 1, 1, 1};
  h.append(reinterpret_cast<const char*>(bbox), sizeof bbox);
  return h;
}
void write_bytes(const std::string& path, const std::string& bytes) {
  std::ofstream f(path, std::ios::binary);
  f << bytes;
}
}  // namespace

TEST_CASE(".vol round trip", "[volume][io]") {
  VolumeGrid g;
  g.x = 3, g.y = 4, g.z = 5, g.channels = 3;
  g.bbox_min = {-1, -2, -3}, g.bbox_max = {1, 2, 3};
  for (size_t i = 0; i < 3 * 4 * 5 * 3; ++i) g.data.push_back(float(i) * 0.25f - 3.f);
  const std::string path = temp_path("round.vol");
  write_vol(path, g);
  const VolumeGrid r = read_vol(path);
  CHECK(r.x == 3);
  CHECK(r.y == 4);
  CHECK(r.z == 5);
  CHECK(r.channels == 3);
  CHECK(r.shape() == std::vector<int>{5, 4, 3, 3});
  CHECK(r.data == g.data);
  CHECK(r.bbox_max.z == 3.f);
  fs::remove_all(fs::path(path).parent_path());
}

TEST_CASE("the Mitsuba 3 reference density grid reads as documented", "[volume][io]") {
  const std::string path = std::string(BL_SOURCE_DIR) + "/../shared/reference/mitsuba3-volume/density.vol";
  if (!fs::exists(path)) {
    WARN("skipped: " << path << " not present (../shared is beside the repository in CI)");
    return;
  }
  const VolumeGrid g = read_vol(path);
  CHECK(g.x == 64);
  CHECK(g.y == 64);
  CHECK(g.z == 64);
  CHECK(g.channels == 1);
  CHECK(*std::max_element(g.data.begin(), g.data.end()) == 1.0f);
  CHECK(*std::min_element(g.data.begin(), g.data.end()) >= 0.0f);
  CHECK(g.bbox_min.y == Approx(-0.75f));
  CHECK(g.bbox_max.y == Approx(0.25f));
}

TEST_CASE("bad .vol files are one-line input errors", "[volume][io]") {
  const std::string path = temp_path("bad.vol");
  auto expect_error = [&](const std::string& bytes, const std::string& needle) {
    write_bytes(path, bytes);
    try {
      read_vol(path);
      FAIL("no error for a file that should mention '" << needle << "'");
    } catch (const InputError& e) {
      const std::string msg = e.what();
      INFO(msg);
      CHECK(msg.find(path) != std::string::npos);
      CHECK(msg.find(needle) != std::string::npos);
      CHECK(msg.find('\n') == std::string::npos);
    }
  };
  const std::string one_float(4, '\0');
  expect_error("VO", "truncated");
  expect_error("XYZ" + header(3, 1, 1, 1, 1, 1).substr(3), "magic");
  expect_error(header(2, 1, 1, 1, 1, 1) + one_float, "version");
  expect_error(header(3, 2, 1, 1, 1, 1) + one_float, "encoding");
  expect_error(header(3, 1, 0, 1, 1, 1), "positive");
  expect_error(header(3, 1, 1, 1, 1, 2) + one_float + one_float, "channels");
  // Dimensions whose product overflows 64 bits, or exceeds the voxel limit, before any allocation.
  expect_error(header(3, 1, 2000000000, 2000000000, 2000000000, 1), "exceeds the limit");
  expect_error(header(3, 1, 2048, 2048, 2048, 1), "exceeds the limit");
  expect_error(header(3, 1, 2, 2, 2, 1) + one_float, "needs");  // truncated data
  float nan = std::nanf("");
  expect_error(header(3, 1, 1, 1, 1, 1) + std::string(reinterpret_cast<const char*>(&nan), 4), "not a finite number");
  fs::remove_all(fs::path(path).parent_path());
}
