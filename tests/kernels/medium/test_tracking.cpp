// Null-collision tracking as the renderer calls it: medium_free_flight (delta tracking) and
// medium_transmittance (ratio tracking) of kernels/medium/medium.h, on a Medium and its ParamStore.
//  - Beer–Lambert: in a homogeneous medium and in a 1-voxel grid, the escape fraction of free
//    flights and the mean transmittance estimate are e^{−σd} (σ = scale · density), for several σ,
//    d and majorant headrooms, 3 standard errors.
//  - Through a random 8³ density grid: both against quadrature of the optical depth, for
//    headrooms 1 and 2.5 and majorant blocks of 2 and 8 voxels: the expectation does not depend on
//    the majorant.
//  - Exact replay: the same TrackingSampler stream gives bitwise the same free flight and
//    transmittance, with or without the callbacks prb's replay passes; another stream id of the
//    same vertex draws other numbers.
//  - dT/dσ = −d·T in expectation from delta tracking's score terms (taped mode): the escape
//    probability through FreeFlight::weight alone, the collision probability 1 − T through
//    ::real × ::weight, |z| < 4; negative controls (the escape derivative × 0.7, the collision
//    without ::real) must give |z| > 4.
// Not repeated here: the derivative of ratio tracking's estimate in expectation and its 0.7×
// control (medium_transmittance<Var> against Beer–Lambert and quadrature for every parameter
// element), which test_medium_backprop.cpp checks on the same functions.
#include <catch2/catch.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "engine/core/tape.h"
#include "kernels/medium/medium.h"
#include "tests/kernels/medium/medium_fixtures.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

Param constant_param(const std::string& name, std::vector<int> shape, float value) {
  Param p;
  p.name = name;
  p.shape = std::move(shape);
  size_t size = 1;
  for (int s : p.shape) size *= size_t(s);
  p.value.assign(size, value);
  return p;
}

// A medium of extinction σ_t = scale · density: homogeneous for a [1] density, else a grid.
TestMedium make_fog(Param density, float scale, int block, float headroom) {
  TestMedium t;
  t.medium.density = t.store.add(std::move(density));
  t.medium.scale = t.store.add(constant_param("fog.scale", {1}, scale));
  t.medium.block = block;
  t.medium.headroom = headroom;
  prepare_test_medium(t);
  return t;
}

// Running mean and standard error of a per-sample value.
struct Estimate {
  double sum = 0, sum2 = 0;
  long n = 0;
  void add(double x) { sum += x, sum2 += x * x, ++n; }
  double mean() const { return sum / double(n); }
  double standard_error() const { return std::sqrt(std::max(0.0, sum2 / double(n) - mean() * mean()) / double(n)); }
  double z(double expected) const { return std::abs(mean() - expected) / standard_error(); }
};

}  // namespace

TEST_CASE("Beer-Lambert: free flight and transmittance give exp(-sigma d)", "[medium][tracking]") {
  // Inside the test box for d ≤ 1 (a grid medium) and anywhere in a homogeneous one; not along an
  // axis, so that the grid's traversal clips on all three axes.
  const Vec3f origin(-0.9f, 0.8f, 2.2f), direction = normalize(Vec3f(2.f, 0.5f, 0.3f));
  for (bool grid : {false, true})
    for (float sigma : {0.5f, 2.f, 6.f})
      for (float d : {0.25f, 1.f})
        for (float headroom : {1.f, 3.f}) {
          // σ = 2 · (σ/2): the scale and the density both take part (σ/2 is exact in float).
          const std::vector<int> shape = grid ? std::vector<int>{1, 1, 1, 1} : std::vector<int>{1};
          const TestMedium t = make_fog(constant_param("fog.density", shape, sigma / 2), 2.f, 8, headroom);
          Estimate escaped, transmittance;
          for (uint64_t i = 0; i < 40000; ++i) {
            TrackingSampler a(i, 1, 0), b(i, 1, 1);
            escaped.add(!medium_free_flight<float>(t.medium, t.store, origin, direction, d, a).collided);
            transmittance.add(medium_transmittance<float>(t.medium, t.store, origin, direction, d, b));
          }
          const double expected = std::exp(-double(sigma) * d);
          INFO((grid ? "1-voxel grid" : "homogeneous")
               << ", sigma " << sigma << " d " << d << " headroom " << headroom << ": free flight " << escaped.mean()
               << " ± " << escaped.standard_error() << " (z " << escaped.z(expected) << "), transmittance "
               << transmittance.mean() << " ± " << transmittance.standard_error() << " (z " << transmittance.z(expected)
               << "), exact " << expected);
          CHECK(std::abs(escaped.mean() - expected) < 3 * escaped.standard_error() + 1e-9);
          CHECK(std::abs(transmittance.mean() - expected) < 3 * transmittance.standard_error() + 1e-9);
        }
}

TEST_CASE("density grid: free flight and transmittance match quadrature, whatever the majorant", "[medium][tracking]") {
  TestRng rng(21);
  Param density;
  density.name = "fog.density";
  density.shape = {8, 8, 8, 1};
  density.value.resize(512);
  for (float& v : density.value) v = float(4.0 * rng.next_double() * rng.next_double());
  // σ_t for the quadrature (sigma_t<double>: the footprint and grid_eval, not tracking's reader).
  const TestMedium reference = make_fog(density, 1.f, 8, 1.f);
  const Medium& m = reference.medium;
  for (int r = 0; r < 6; ++r) {
    // From the box's z = min face, leaving through the opposite face or a side (even r), or ending
    // inside the box (odd r).
    const Vec3f local_origin(float(rng.uniform(0.1, 0.9)), float(rng.uniform(0.1, 0.9)), 0.f);
    const Vec3f direction = normalize(Vec3f(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)), 1.f));
    RaySegment ray{"", to_world(m, local_origin), direction, std::numeric_limits<float>::infinity()};
    const double exit = inside_interval(m, ray).second;
    ray.length = float(r % 2 ? 0.6 * exit : exit + 1.0);
    // The optical depth by the midpoint rule over the part inside the box.
    const auto [t0, t1] = inside_interval(m, ray);
    const int steps = 20000;
    double depth = 0;
    for (int i = 0; i < steps; ++i) {
      const double t = t0 + (t1 - t0) * (i + 0.5) / steps;
      depth += m.sigma_t<double>(reference.store, ray.origin + ray.direction * float(t)) * (t1 - t0) / steps;
    }
    const double expected = std::exp(-depth);
    for (float headroom : {1.f, 2.5f})
      for (int block : {2, 8}) {
        const TestMedium t = make_fog(density, 1.f, block, headroom);
        Estimate escaped, transmittance;
        for (uint64_t i = 0; i < 20000; ++i) {
          TrackingSampler a(i + 1000000 * uint64_t(r), 2, 0), b(i + 1000000 * uint64_t(r), 2, 1);
          escaped.add(!medium_free_flight<float>(t.medium, t.store, ray.origin, ray.direction, ray.length, a).collided);
          transmittance.add(medium_transmittance<float>(t.medium, t.store, ray.origin, ray.direction, ray.length, b));
        }
        INFO("ray " << r << " block " << block << " headroom " << headroom << ": free flight " << escaped.mean()
                    << " ± " << escaped.standard_error() << " (z " << escaped.z(expected) << "), transmittance "
                    << transmittance.mean() << " ± " << transmittance.standard_error() << " (z "
                    << transmittance.z(expected) << ") vs quadrature " << expected);
        CHECK(std::abs(escaped.mean() - expected) < 3 * escaped.standard_error() + 1e-4);
        CHECK(std::abs(transmittance.mean() - expected) < 3 * transmittance.standard_error() + 1e-4);
      }
  }
}

TEST_CASE("tracking replays exactly from its sub-stream", "[medium][tracking]") {
  // σ_t rising from 1 to 3 along x; blocks of 2 voxels: two majorants along the ray, which enters
  // the box from outside and leaves it.
  Param density = constant_param("fog.density", {1, 1, 4, 1}, 0.f);
  density.value = {1.f, 5.f / 3.f, 7.f / 3.f, 3.f};
  const TestMedium t = make_fog(std::move(density), 1.f, 2, 2.f);
  const Vec3f origin(-1.2f, 1.1f, 2.4f), direction = normalize(Vec3f(1.f, 0.1f, 0.05f));
  const float length = 3.f;
  int events = 0, real_events = 0;
  const auto count = [&](const Vec3f&, float, float, bool real) { ++events, real_events += real; };
  const auto bits = [](float x) { return std::bit_cast<uint32_t>(x); };
  int same_first_draw = 0;
  for (uint64_t key = 0; key < 200; ++key) {
    // The primal run (no callback) and prb's replay (with one) of the same stream.
    TrackingSampler a(key, 3, 0), b(key, 3, 0);
    const FreeFlight<float> x = medium_free_flight<float>(t.medium, t.store, origin, direction, length, a);
    events = real_events = 0;
    const FreeFlight<float> y = medium_free_flight<float>(t.medium, t.store, origin, direction, length, b, count);
    REQUIRE(x.collided == y.collided);
    REQUIRE(bits(x.t) == bits(y.t));
    REQUIRE(bits(x.weight) == bits(y.weight));
    REQUIRE(bits(x.real) == bits(y.real));
    REQUIRE(x.null_collisions == y.null_collisions);
    REQUIRE(a.draws() == b.draws());
    // The callback saw every tentative collision: the null ones and the real one.
    REQUIRE(events == x.null_collisions + int(x.collided));
    REQUIRE(real_events == int(x.collided));
    TrackingSampler c(key, 3, 1), d(key, 3, 1);
    const float u = medium_transmittance<float>(t.medium, t.store, origin, direction, length, c);
    const float v = medium_transmittance<float>(t.medium, t.store, origin, direction, length, d, count);
    REQUIRE(bits(u) == bits(v));
    REQUIRE(c.draws() == d.draws());
    // Another stream id of the same vertex draws other numbers.
    same_first_draw += TrackingSampler(key, 3, 1).next() == TrackingSampler(key, 3, 0).next();
  }
  CHECK(same_first_draw == 0);
}

TEST_CASE("free-flight derivative in expectation: dT/dsigma = -d T from the score terms",
          "[medium][tracking][gradient]") {
  const float d = 0.8f;
  const Vec3f origin(0.f, 0.f, 0.f), direction(1.f, 0.f, 0.f);
  Tape tape;
  current_tape = &tape;
  std::vector<float> adjoint;
  std::vector<double> gradient(2);
  for (float sigma : {0.7f, 2.5f}) {
    // σ = density (scale 1): dT/dσ is the derivative with respect to the density.
    const TestMedium t = make_fog(constant_param("fog.density", {1}, sigma), 1.f, 8, 2.f);
    const size_t density = t.store[t.medium.density].tape_offset;
    const auto derivative = [&](const Var& estimate) {
      taped_gradient(tape, estimate, adjoint, gradient);
      return gradient[density];
    };
    Estimate escape, collision, escape_scaled, collision_without_real;
    for (uint64_t i = 0; i < 60000; ++i) {
      tape.clear();
      TrackingSampler rng(i, 1, 0);
      const FreeFlight<Var> f = medium_free_flight<Var>(t.medium, t.store, origin, direction, d, rng);
      // The escape probability T: the indicator × the weight, whose derivative is the null
      // choices' score terms. The collision probability 1 − T also needs the real choice's.
      const double escape_derivative = derivative(f.collided ? Var(0.f) : f.weight);
      escape.add(escape_derivative);
      collision.add(derivative(f.collided ? f.real * f.weight : Var(0.f)));
      // Negative controls: a derivative 0.7 times too small, the collision without its score term.
      escape_scaled.add(0.7 * escape_derivative);
      collision_without_real.add(derivative(f.collided ? f.weight : Var(0.f)));
    }
    const double expected = -double(d) * std::exp(-double(sigma) * d);
    INFO("sigma " << sigma << ": escape " << escape.mean() << " ± " << escape.standard_error() << " (z "
                  << escape.z(expected) << "), collision " << collision.mean() << " ± " << collision.standard_error()
                  << " (z " << collision.z(-expected) << "), exact " << expected << " (collision: " << -expected
                  << "); controls: escape × 0.7 z " << escape_scaled.z(expected) << ", collision without real z "
                  << collision_without_real.z(-expected));
    CHECK(std::abs(escape.mean() - expected) < 4 * escape.standard_error() + 1e-9);
    CHECK(std::abs(collision.mean() + expected) < 4 * collision.standard_error() + 1e-9);
    // The controls fail the same comparisons, each against its own standard error.
    CHECK(std::abs(escape_scaled.mean() - expected) > 4 * escape_scaled.standard_error());
    CHECK(std::abs(collision_without_real.mean() + expected) > 4 * collision_without_real.standard_error());
  }
  current_tape = nullptr;
}
