// Null-collision tracking: Beer–Lambert for homogeneous media by delta and ratio tracking, ratio
// tracking against quadrature through a heterogeneous grid, independence of the majorant, exact
// replay, and the derivative of transmittance in expectation (dT/dσ = −d·T), including the score
// terms of delta tracking's real/null choices, with negative controls (derivatives scaled by 0.7,
// the collision probability without the real choice's score term) that must fail.
#include <catch2/catch.hpp>

#include <cmath>

#include "engine/core/dual.h"
#include "kernels/medium/tracking.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

Param constant_grid(float value) {
  Param p;
  p.name = "fog.density";
  p.shape = {1, 1, 1, 1};
  p.value = {value};
  return p;
}

struct Stats {
  double sum = 0, sum2 = 0;
  long n = 0;
  void add(double x) { sum += x, sum2 += x * x, ++n; }
  double mean() const { return sum / double(n); }
  double stderr_() const { return std::sqrt(std::max(0.0, sum2 / double(n) - mean() * mean()) / double(n)); }
};

// A ray along +x through the unit cube's middle: local distance = t.
const Vec3f kOrigin(0.f, 0.5f, 0.5f), kDir(1.f, 0.f, 0.f);

}  // namespace

TEST_CASE("homogeneous slab: delta and ratio tracking give exp(-sigma d)", "[medium][tracking]") {
  for (float sigma : {0.5f, 2.f, 6.f})
    for (float d : {0.25f, 1.f})
      for (float headroom : {1.f, 3.f}) {
        const Param p = constant_grid(sigma);
        const MajorantGrid m = build_majorants(p, 8, headroom);
        auto sigma_t = [&](float) { return sigma; };
        Stats escaped, ratio;
        for (uint64_t i = 0; i < 40000; ++i) {
          TrackingSampler a(i, 1, 0), b(i, 1, 1);
          escaped.add(!delta_tracking<float>(m, kOrigin, kDir, 0.f, d, sigma_t, a).collided);
          ratio.add(ratio_tracking<float>(m, kOrigin, kDir, 0.f, d, sigma_t, b));
        }
        const double expected = std::exp(-double(sigma) * d);
        INFO("sigma " << sigma << " d " << d << " headroom " << headroom << ": delta " << escaped.mean() << " ± "
                      << escaped.stderr_() << ", ratio " << ratio.mean() << " ± " << ratio.stderr_() << ", exact "
                      << expected);
        CHECK(std::abs(escaped.mean() - expected) < 3 * escaped.stderr_() + 1e-9);
        CHECK(std::abs(ratio.mean() - expected) < 3 * ratio.stderr_() + 1e-9);
      }
}

TEST_CASE("heterogeneous grid: ratio tracking matches quadrature, whatever the majorant", "[medium][tracking]") {
  TestRng rng(21);
  Param p;
  p.name = "fog.density";
  p.shape = {8, 8, 8, 1};
  p.value.resize(512);
  for (float& v : p.value) v = float(4.0 * rng.next_double() * rng.next_double());
  const GridSize n = grid_size(p);
  auto sigma_at = [&](const Vec3f& o, const Vec3f& d, float t) {
    Vec3f l = o + d * t;
    for (int a = 0; a < 3; ++a) l[a] = std::clamp(l[a], 0.f, 1.f);
    return grid_eval<float>(p, trilinear_footprint(n, l), 0);
  };
  for (int r = 0; r < 6; ++r) {
    const Vec3f o(float(rng.uniform(0.1, 0.9)), float(rng.uniform(0.1, 0.9)), 0.f);
    const Vec3f d = normalize(Vec3f(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)), 1.f));
    // Exit through z = 1 (or a side): quadrature of the optical depth with the midpoint rule.
    float t_exit = 1.f / d.z;
    for (int a = 0; a < 2; ++a)
      if (d[a] != 0.f) t_exit = std::min(t_exit, ((d[a] > 0 ? 1.f : 0.f) - o[a]) / d[a]);
    double depth = 0;
    const int steps = 20000;
    for (int i = 0; i < steps; ++i) depth += sigma_at(o, d, t_exit * (i + 0.5f) / steps) * double(t_exit) / steps;
    const double expected = std::exp(-depth);
    for (float headroom : {1.f, 2.5f})
      for (int block : {2, 8}) {
        const MajorantGrid m = build_majorants(p, block, headroom);
        Stats ratio;
        for (uint64_t i = 0; i < 20000; ++i) {
          TrackingSampler s(i + 1000000 * uint64_t(r), 2, 1);
          ratio.add(ratio_tracking<float>(
              m, o, d, 0.f, t_exit, [&](float t) { return sigma_at(o, d, t); }, s));
        }
        INFO("ray " << r << " block " << block << " headroom " << headroom << ": " << ratio.mean() << " ± "
                    << ratio.stderr_() << " vs quadrature " << expected);
        CHECK(std::abs(ratio.mean() - expected) < 3 * ratio.stderr_() + 1e-4);
      }
  }
}

TEST_CASE("tracking replays exactly from its sub-stream", "[medium][tracking]") {
  const Param p = constant_grid(3.f);
  const MajorantGrid m = build_majorants(p, 8, 2.f);
  auto sigma_t = [](float t) { return 1.f + 2.f * t; };
  for (uint64_t key = 0; key < 200; ++key) {
    TrackingSampler a(key, 3, 0), b(key, 3, 0), c(key, 3, 1);
    const FreeFlight<float> x = delta_tracking<float>(m, kOrigin, kDir, 0.f, 1.f, sigma_t, a);
    const FreeFlight<float> y = delta_tracking<float>(m, kOrigin, kDir, 0.f, 1.f, sigma_t, b);
    REQUIRE(x.collided == y.collided);
    REQUIRE(x.t == y.t);
    REQUIRE(a.draws() == b.draws());
    // Another stream id of the same vertex draws other numbers.
    if (key == 0) CHECK(c.next() != TrackingSampler(key, 3, 0).next());
  }
}

TEST_CASE("transmittance derivative in expectation: dT/dsigma = -d T", "[medium][tracking][gradient]") {
  using D = Dual<double, 1>;
  const float d = 0.8f;
  for (float sigma : {0.7f, 2.5f}) {
    const Param p = constant_grid(sigma);
    const MajorantGrid m = build_majorants(p, 8, 2.f);
    auto sigma_t = [&](float) { return D::variable(sigma, 0); };
    Stats ratio, delta, collision, ratio_scaled, delta_scaled, collision_without_real;
    for (uint64_t i = 0; i < 60000; ++i) {
      TrackingSampler a(i, 1, 1), b(i, 1, 0);
      const double ratio_derivative = ratio_tracking<D>(m, kOrigin, kDir, 0.f, d, sigma_t, a).d[0];
      ratio.add(ratio_derivative);
      // Escape probability by delta tracking: indicator × weight; its derivative comes from the
      // score terms the weight carries. The collision probability 1 − T also needs the real
      // choice's score term, FreeFlight::real.
      const FreeFlight<D> f = delta_tracking<D>(m, kOrigin, kDir, 0.f, d, sigma_t, b);
      const double delta_derivative = f.collided ? 0.0 : f.weight.d[0];
      delta.add(delta_derivative);
      collision.add(f.collided ? (f.real * f.weight).d[0] : 0.0);
      // Negative controls: derivatives 0.7 times too small, and the collision without its score term.
      ratio_scaled.add(0.7 * ratio_derivative);
      delta_scaled.add(0.7 * delta_derivative);
      collision_without_real.add(f.collided ? f.weight.d[0] : 0.0);
    }
    const double expected = -double(d) * std::exp(-double(sigma) * d);
    INFO("sigma " << sigma << ": ratio " << ratio.mean() << " ± " << ratio.stderr_() << ", delta " << delta.mean()
                  << " ± " << delta.stderr_() << ", collision " << collision.mean() << " ± " << collision.stderr_()
                  << ", exact " << expected << " (collision: " << -expected << "); controls: ratio × 0.7 "
                  << ratio_scaled.mean() << " ± " << ratio_scaled.stderr_() << ", delta × 0.7 " << delta_scaled.mean()
                  << " ± " << delta_scaled.stderr_() << ", collision without real " << collision_without_real.mean()
                  << " ± " << collision_without_real.stderr_());
    CHECK(std::abs(ratio.mean() - expected) < 4 * ratio.stderr_() + 1e-9);
    CHECK(std::abs(delta.mean() - expected) < 4 * delta.stderr_() + 1e-9);
    CHECK(std::abs(collision.mean() + expected) < 4 * collision.stderr_() + 1e-9);
    // The controls fail the same comparisons, each against its own standard error.
    CHECK(std::abs(ratio_scaled.mean() - expected) > 4 * ratio_scaled.stderr_());
    CHECK(std::abs(delta_scaled.mean() - expected) > 4 * delta_scaled.stderr_());
    CHECK(std::abs(collision_without_real.mean() + expected) > 4 * collision_without_real.stderr_());
  }
}
