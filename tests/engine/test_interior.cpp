// The interior term's local derivatives (engine/integrators/interior.h) against central
// differences of the same templates evaluated in double: the hit of a fixed ray on a moving
// triangle (point and shading normal), and the log-factors of a path's continuation, light
// samples and MIS weights. Whole-image checks (finite differences in expectation) are in
// test_boundary.cpp.
#include <catch2/catch.hpp>

#include <array>
#include <cmath>
#include <functional>
#include <random>

#include "engine/core/dual.h"
#include "engine/integrators/interior.h"

using namespace bl;
using namespace bl::interior_detail;

namespace {

// f maps an input vector to one output; compares ∂f/∂x_i (from the Dual evaluation) with central
// differences of the double evaluation at step h, relative to the gradient's largest entry.
template <int N>
void check_gradient(const std::function<Dual<double, N>(const std::array<Dual<double, N>, N>&)>& f,
                    const std::array<double, N>& x, double h, double tolerance, const char* what) {
  std::array<Dual<double, N>, N> xd;
  for (int i = 0; i < N; ++i) xd[size_t(i)] = Dual<double, N>::variable(x[size_t(i)], i);
  const Dual<double, N> y = f(xd);
  double largest = 0;
  for (int i = 0; i < N; ++i) largest = std::max(largest, std::abs(y.d[size_t(i)]));
  REQUIRE(largest > 0);
  for (int i = 0; i < N; ++i) {
    auto at = [&](double step) {
      std::array<Dual<double, N>, N> p;
      for (int k = 0; k < N; ++k) p[size_t(k)] = Dual<double, N>(x[size_t(k)] + (k == i ? step : 0.0));
      return f(p).v;
    };
    const double fd = (at(h) - at(-h)) / (2 * h);
    INFO(what << ": input " << i << " analytic " << y.d[size_t(i)] << " finite differences " << fd);
    CHECK(std::abs(y.d[size_t(i)] - fd) <= tolerance * largest);
  }
}

template <class A>
Vec3<typename A::value_type> vec(const A& x, int first) {
  return {x[size_t(first)], x[size_t(first + 1)], x[size_t(first + 2)]};
}

template <int N>
std::array<double, N> random_point(std::mt19937& rng, const std::array<double, N>& centre, double spread) {
  std::uniform_real_distribution<double> u(-spread, spread);
  std::array<double, N> x = centre;
  for (double& v : x) v += u(rng);
  return x;
}

// A log-factor of a vertex seen from either side of a two-sided surface: 4 points around
// `centre` with components [flip, flip + 3) (the side's normal) negated for sign −1, each checked
// against central differences; f(v, sign) is the factor.
template <int N, class F>
void check_both_sides(std::mt19937& rng, const std::array<double, N>& centre, int flip, double spread, const F& f,
                      const char* name) {
  for (double sign : {1.0, -1.0})
    for (int trial = 0; trial < 4; ++trial) {
      std::array<double, N> c = centre;
      for (int k = flip; k < flip + 3; ++k) c[size_t(k)] *= sign;
      const std::array<double, N> x = random_point<N>(rng, c, spread);
      check_gradient<N>([&](const std::array<Dual<double, N>, N>& v) { return f(v, sign); }, x, 1e-6, 1e-6, name);
    }
}

}  // namespace

TEST_CASE("moving_hit: the hit point and shading normal of a fixed ray on a moving triangle", "[interior]") {
  std::mt19937 rng(7);
  // o, d, p0, p1, p2, n0, n1, n2: a ray from above hitting a triangle near the origin.
  const std::array<double, 24> centre = {0.1, 2, 0.2, -0.05, -1, 0.02, -1,   0, -1,  1, 0, -1,
                                         0,   0, 1,   0.1,   1,  0,    -0.1, 1, 0.1, 0, 1, -0.1};
  for (int trial = 0; trial < 4; ++trial) {
    const std::array<double, 24> x = random_point<24>(rng, centre, 0.05);
    for (int output = 0; output < 6; ++output)
      for (bool smooth : {true, false}) {
        using D = Dual<double, 24>;
        check_gradient<24>(
            [&](const std::array<D, 24>& v) {
              const Vec3<D> n[3] = {vec(v, 15), vec(v, 18), vec(v, 21)};
              const MovingHit<D> h =
                  moving_hit(vec(v, 0), vec(v, 3), vec(v, 6), vec(v, 9), vec(v, 12), smooth ? n : nullptr);
              return output < 3 ? h.x[output] : h.m[output - 3];
            },
            x, 1e-6, 1e-6, smooth ? "moving_hit (smooth)" : "moving_hit (flat)");
      }
  }
  // The point is on the ray and in the triangle's plane.
  const Vec3d o(0.1, 2, 0.2), d = normalize(Vec3d(-0.05, -1, 0.02));
  const Vec3d p0(-1, 0, -1), p1(1, 0, -1), p2(0, 0.1, 1);
  const MovingHit<double> h = moving_hit(o, d, p0, p1, p2, static_cast<const Vec3d*>(nullptr));
  CHECK(std::abs(dot(h.x - p0, normalize(cross(p1 - p0, p2 - p0)))) < 1e-12);
  CHECK(length(cross(h.x - o, d)) < 1e-12);
}

TEST_CASE("log-factors of continuations, light samples and MIS weights", "[interior]") {
  std::mt19937 rng(11);
  const Vec3d d = normalize(Vec3d(0.3, 1, -0.2));
  for (int trial = 0; trial < 4; ++trial)
    for (double sign : {1.0, -1.0}) {
      const std::array<double, 3> m = random_point<3>(rng, {0.1, sign * 1.2, 0.05}, 0.1);
      check_gradient<3>([&](const std::array<Dual<double, 3>, 3>& v) { return log_continuation(vec(v, 0), sign, d); },
                        m, 1e-6, 1e-6, "log_continuation");
      check_gradient<3>(
          [&](const std::array<Dual<double, 3>, 3>& v) { return log_environment_sample(vec(v, 0), sign, d, 0.4); }, m,
          1e-6, 1e-6, "log_environment_sample");
      check_gradient<3>(
          [&](const std::array<Dual<double, 3>, 3>& v) { return log_environment_hit_weight(vec(v, 0), sign, d, 0.4); },
          m, 1e-6, 1e-6, "log_environment_hit_weight");
    }
  // A point x below a light triangle, its normal m, the triangle's corners q, log of the emitter area.
  const std::array<double, 16> light_centre = {0.1,  0,   -0.1, 0,    1, 0.1, -0.5, 1.5,
                                               -0.4, 0.5, 1.6,  -0.5, 0, 1.4, 0.6,  std::log(0.8)};
  // sign −1: the back of a two-sided surface, its shading normal m pointing away from the light.
  check_both_sides<16>(
      rng, light_centre, 3, 0.1,
      [](const std::array<Dual<double, 16>, 16>& v, double sign) {
        const Vec3<Dual<double, 16>> q[3] = {vec(v, 6), vec(v, 9), vec(v, 12)};
        return log_light_sample(vec(v, 0), vec(v, 3), sign, q, 0.3, 0.25, v[15], 0.5);
      },
      "log_light_sample");
  // The previous vertex's normal, the ray's origin, the emitter hit x and its triangle, log area.
  const Vec3d dir = normalize(Vec3d(0.05, 1, 0.02));
  const std::array<double, 19> hit_centre = {0,   1,    0.1, 0,   0,    0, 0.05, 1.5, 0.03,         -0.5,
                                             1.5, -0.4, 0.5, 1.6, -0.5, 0, 1.4,  0.6, std::log(0.8)};
  check_both_sides<19>(
      rng, hit_centre, 0, 0.05,
      [&](const std::array<Dual<double, 19>, 19>& v, double sign) {
        const Vec3<Dual<double, 19>> p[3] = {vec(v, 9), vec(v, 12), vec(v, 15)};
        return log_emitter_hit_weight(vec(v, 0), sign, dir, vec(v, 3), vec(v, 6), p, v[18], 0.5);
      },
      "log_emitter_hit_weight");
}

TEST_CASE("the power heuristic's derivative: the two strategies' weights sum to one", "[interior]") {
  using D = Dual<double, 2>;
  const D a = D::variable(0.7, 0), b = D::variable(1.9, 1);
  const D sum = power_heuristic_of(a, b) + power_heuristic_of(b, a);
  CHECK(sum.v == Approx(1.0));
  CHECK(std::abs(sum.d[0]) < 1e-12);
  CHECK(std::abs(sum.d[1]) < 1e-12);
}

TEST_CASE("moving_hit_adjoint: the reverse-mode derivative equals the dual-number one, barycentrics included",
          "[interior]") {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  const std::array<double, 24> centre = {0.1, 2, 0.2, -0.05, -1, 0.02, -1,   0, -1,  1, 0, -1,
                                         0,   0, 1,   0.1,   1,  0,    -0.1, 1, 0.1, 0, 1, -0.1};
  for (int trial = 0; trial < 8; ++trial)
    for (bool smooth : {true, false}) {
      const std::array<double, 24> x = random_point<24>(rng, centre, 0.05);
      const Vec3d gx(u(rng), u(rng), u(rng)), gm(u(rng), u(rng), u(rng));
      const double gb[2] = {u(rng), u(rng)};  // the barycentrics' own adjoints (a textured uv)
      using D = Dual<double, 24>;
      std::array<D, 24> v;
      for (int i = 0; i < 24; ++i) v[size_t(i)] = D::variable(x[size_t(i)], i);
      const Vec3<D> nd[3] = {vec(v, 15), vec(v, 18), vec(v, 21)};
      const MovingHit<D> h = moving_hit(vec(v, 0), vec(v, 3), vec(v, 6), vec(v, 9), vec(v, 12), smooth ? nd : nullptr);
      auto plain = [&](int first) { return Vec3d(x[size_t(first)], x[size_t(first + 1)], x[size_t(first + 2)]); };
      const Vec3d p[3] = {plain(6), plain(9), plain(12)}, n[3] = {plain(15), plain(18), plain(21)};
      const HitAdjoint r = moving_hit_adjoint(plain(0), plain(3), p, smooth ? n : nullptr, gx, gm, gb);
      const Vec3d got[8] = {r.origin, r.direction, r.p[0], r.p[1], r.p[2], r.n[0], r.n[1], r.n[2]};
      for (int i = 0; i < 24; ++i) {
        double want = 0;
        for (int c = 0; c < 3; ++c) want += gx[c] * h.x[c].d[size_t(i)] + gm[c] * h.m[c].d[size_t(i)];
        want += gb[0] * h.b1.d[size_t(i)] + gb[1] * h.b2.d[size_t(i)];
        const double have = got[i / 3][i % 3];
        INFO((smooth ? "smooth" : "flat") << ", input " << i << ": reverse " << have << ", dual " << want);
        CHECK(std::abs(have - want) <= 1e-9 * (1 + std::abs(want)));
      }
    }
}
