// Volume grids: trilinear lookup against a hand computation (including the clamped half voxel at
// the faces), exact values at voxel centres, the derivative shader as the exact transpose of the
// lookup, majorants that bound the interpolant along rays, and a DDA whose segments tile the ray.
#include <catch2/catch.hpp>

#include <array>
#include <cmath>
#include <vector>

#include "kernels/medium/grid.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

Param random_grid(int x, int y, int z, int channels, uint64_t seed, double scale = 1.0) {
  TestRng rng(seed);
  Param p;
  p.name = "fog.density";
  p.shape = {z, y, x, channels};
  p.value.resize(size_t(x) * size_t(y) * size_t(z) * size_t(channels));
  for (float& v : p.value) v = float(scale * rng.next_double());
  return p;
}

// The reference README's rule, written out independently of grid.h.
double trilinear_by_hand(const Param& p, double lx, double ly, double lz, int channel) {
  const int n[3] = {p.shape[2], p.shape[1], p.shape[0]}, c = p.shape[3];
  const double l[3] = {lx, ly, lz};
  int i0[3];
  double f[3];
  for (int a = 0; a < 3; ++a) {
    const double q = l[a] * n[a] - 0.5;
    i0[a] = int(std::floor(q));
    f[a] = q - std::floor(q);
  }
  double sum = 0;
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx) {
        const int ix = std::clamp(i0[0] + dx, 0, n[0] - 1), iy = std::clamp(i0[1] + dy, 0, n[1] - 1),
                  iz = std::clamp(i0[2] + dz, 0, n[2] - 1);
        const double w = (dx ? f[0] : 1 - f[0]) * (dy ? f[1] : 1 - f[1]) * (dz ? f[2] : 1 - f[2]);
        sum += w * p.value[((size_t(iz) * n[1] + iy) * n[0] + ix) * c + channel];
      }
  return sum;
}

}  // namespace

TEST_CASE("trilinear lookup follows the clamped voxel-centre rule", "[medium][grid]") {
  const Param p = random_grid(5, 4, 3, 3, 1);
  const GridSize n = grid_size(p);
  TestRng rng(2);
  for (int i = 0; i < 5000; ++i) {
    // Half the points within half a voxel of some face, where clamping acts.
    Vec3f l(float(rng.next_double()), float(rng.next_double()), float(rng.next_double()));
    if (i % 2) l[i % 3] = float(i % 4 < 2 ? 0.5 / n.x * rng.next_double() : 1 - 0.5 / n.x * rng.next_double());
    const TrilinearFootprint fp = trilinear_footprint(n, l);
    for (int c = 0; c < 3; ++c)
      REQUIRE(grid_eval<double>(p, fp, c) == Approx(trilinear_by_hand(p, l.x, l.y, l.z, c)).margin(1e-6));
  }
  // Voxel centres return the voxel.
  for (int iz = 0; iz < n.z; ++iz)
    for (int iy = 0; iy < n.y; ++iy)
      for (int ix = 0; ix < n.x; ++ix) {
        const Vec3f l((ix + 0.5f) / n.x, (iy + 0.5f) / n.y, (iz + 0.5f) / n.z);
        for (int c = 0; c < 3; ++c)
          REQUIRE(grid_eval<float>(p, trilinear_footprint(n, l), c) ==
                  Approx(p.value[n.index(ix, iy, iz) * 3 + size_t(c)]).margin(1e-6));
      }
}

TEST_CASE("the tracking reader returns grid_eval's value bit for bit", "[medium][grid]") {
  // Tracking reads the density through GridReader; the taped mode and the derivative shaders go
  // through the footprint. prb replays and the taped oracle rely on both giving the same float.
  for (int channels : {1, 3}) {
    const Param p = random_grid(7, 4, 5, channels, 11);
    const GridSize n = grid_size(p);
    TestRng rng(12);
    size_t differing = 0;
    for (int i = 0; i < 20000; ++i) {
      // Inside the grid, within half a voxel of a face, on voxel centres and outside the unit
      // cube (a ray's end point may round past a face): the clamped cases included.
      Vec3f l(float(rng.next_double()), float(rng.next_double()), float(rng.next_double()));
      if (i % 4 == 1) l[i % 3] = float(i % 8 < 4 ? 0.5 / n.x * rng.next_double() : 1 - 0.5 / n.x * rng.next_double());
      if (i % 4 == 2) l = Vec3f((std::floor(l.x * n.x) + 0.5f) / n.x, (std::floor(l.y * n.y) + 0.5f) / n.y, l.z);
      if (i % 4 == 3) l[i % 3] = float(-0.01 + 1.02 * rng.next_double());
      for (int c = 0; c < channels; ++c) {
        const float expected = grid_eval<float>(p, trilinear_footprint(n, l), c);
        differing += GridReader(p, c)(l) != expected;
      }
    }
    CHECK(differing == 0);
  }
}

TEST_CASE("grid backprop is the exact transpose of the lookup", "[medium][grid][gradient]") {
  // <a, J v> = <J^T a, v> for the map J from voxels to values at M points.
  for (int channels : {1, 3}) {
    ParamStore store;
    const int h = store.add(random_grid(6, 5, 7, channels, 3));
    store.require_grad({"fog.density"});
    Param& p = store[h];
    const GridSize n = grid_size(p);
    TestRng rng(4);
    std::vector<TrilinearFootprint> points;
    std::vector<Vec3f> adjoints;
    for (int m = 0; m < 300; ++m) {
      points.push_back(
          trilinear_footprint(n, {float(rng.next_double()), float(rng.next_double()), float(rng.next_double())}));
      adjoints.push_back({float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1))});
    }
    double a_jv = 0;
    for (size_t m = 0; m < points.size(); ++m) {
      const Spectrum<double> v = grid_eval_rgb<double>(p, points[m]);
      a_jv += adjoints[m].x * v.x + adjoints[m].y * v.y + adjoints[m].z * v.z;
    }
    {
      GradientSink sink(store);
      for (size_t m = 0; m < points.size(); ++m) grid_backprop_rgb(h, p, points[m], adjoints[m], sink.local());
      sink.reduce();
    }
    double jta_v = 0;
    for (size_t i = 0; i < p.size(); ++i) jta_v += double(p.grad[i]) * p.value[i];
    INFO("channels " << channels);
    CHECK(jta_v == Approx(a_jv).epsilon(1e-5));
    // Voxels no point touches get exactly zero.
    size_t untouched = 0, zero = 0;
    std::vector<bool> touched(n.voxels(), false);
    for (const auto& fp : points)
      for (int k = 0; k < 8; ++k)
        if (fp.weight[k] != 0.f) touched[fp.voxel[k]] = true;
    for (size_t v = 0; v < n.voxels(); ++v)
      if (!touched[v]) {
        ++untouched;
        zero += p.grad[v * size_t(channels)] == 0.f;
      }
    CHECK(zero == untouched);
  }
}

TEST_CASE("majorants bound the interpolant and the DDA tiles the ray", "[medium][grid]") {
  // Spiky grids: a few large voxels in a thin field, where too-narrow blocks would fail. The second
  // is long along z (2000 voxels): its blocks there are longer than `block` (at most
  // kMaxBlocksPerAxis of them), and different from its blocks along x and y.
  for (const auto [gx, gy, gz] : {std::array<int, 3>{19, 13, 11}, std::array<int, 3>{3, 2, 2000}}) {
    Param p = random_grid(gx, gy, gz, 1, 5, 0.1);
    TestRng rng(6);
    for (int k = 0; k < 12 + gz / 50; ++k) p.value[size_t(rng.next_u64() % p.value.size())] = 5.f;
    const GridSize n = grid_size(p);
    for (int block : {1, 4, 8}) {
      const MajorantGrid m = build_majorants(p, block, 1.f);
      INFO("grid " << gx << "x" << gy << "x" << gz << " block " << block);
      CHECK(std::max({m.bx, m.by, m.bz}) <= kMaxBlocksPerAxis);
      CHECK(m.size[0] == block);
      CHECK(m.size[2] == std::max(block, (gz + kMaxBlocksPerAxis - 1) / kMaxBlocksPerAxis));
      CHECK(int64_t(m.bz) * m.size[2] >= gz);
      CHECK(int64_t(m.bz - 1) * m.size[2] < gz);
      for (int r = 0; r < 400; ++r) {
        const Vec3f o(float(rng.uniform(-0.5, 1.5)), float(rng.uniform(-0.5, 1.5)), float(rng.uniform(-0.5, 1.5)));
        Vec3f d(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
        if (r % 7 == 0) d[r % 3] = 0.f;  // axis-parallel rays
        if (length(d) < 1e-3f) continue;
        d = normalize(d);
        float previous_end = -1.f, first = -1.f;
        bool ok = true;
        int segments = 0;
        traverse_majorants(m, o, d, 0.f, 10.f, [&](const MajorantSegment& s) {
          ++segments;
          if (first < 0) first = s.t0;
          if (previous_end >= 0 && std::abs(s.t0 - previous_end) > 1e-5f) ok = false;  // contiguous, in order
          if (!(s.t1 > s.t0)) ok = false;
          previous_end = s.t1;
          for (int i = 0; i <= 16; ++i) {
            const float t = s.t0 + (s.t1 - s.t0) * (i + 0.5f) / 17.f;
            Vec3f l = o + d * t;
            for (int a = 0; a < 3; ++a) l[a] = std::clamp(l[a], 0.f, 1.f);
            const float value = grid_eval<float>(p, trilinear_footprint(n, l), 0);
            if (value > s.majorant * (1 + 1e-6f) + 1e-7f) ok = false;
          }
          return true;
        });
        // The segments cover exactly the part of [0, 10] inside the unit cube.
        float enter = 0.f, leave = 10.f;
        for (int a = 0; a < 3; ++a) {
          if (d[a] == 0.f) {
            if (o[a] < 0.f || o[a] > 1.f) enter = 1.f, leave = 0.f;
            continue;
          }
          float t0 = (0.f - o[a]) / d[a], t1 = (1.f - o[a]) / d[a];
          if (t0 > t1) std::swap(t0, t1);
          enter = std::max(enter, t0), leave = std::min(leave, t1);
        }
        INFO("ray " << r);
        REQUIRE(ok);
        REQUIRE(segments <= m.bx + m.by + m.bz);
        if (enter < leave) {
          REQUIRE(first == Approx(enter).margin(1e-5));
          REQUIRE(previous_end == Approx(leave).margin(1e-5));
        } else {
          REQUIRE(first < 0.f);
        }
      }
    }
  }
}
