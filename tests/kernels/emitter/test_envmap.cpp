// Environment emitters: the importance sampler of a latitude-longitude map (and of a constant
// environment) against its pdf with the shared chi-square harness, ∫ pdf = 1, and the derivative
// shader against central differences of Environment::eval<double> per texel.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <sstream>
#include <vector>

#include "kernels/emitter/envmap.h"
#include "tests/kernels/chi2.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

constexpr int kWidth = 32, kHeight = 16;

// A smooth sky with a bright sun (≈ 1000× the sky) at row 5, column 20; optionally black below
// the horizon, so that whole rows of the sampling distribution are empty.
Param structured_map(bool black_lower_half) {
  Param p;
  p.name = "environment.radiance";
  p.shape = {kHeight, kWidth, 3};
  for (int row = 0; row < kHeight; ++row)
    for (int col = 0; col < kWidth; ++col) {
      const double sky = 0.2 + 0.1 * std::sin(0.4 * col) * std::cos(0.3 * row);
      const double d2 = (row - 5.0) * (row - 5.0) + (col - 20.0) * (col - 20.0);
      const double sun = 200.0 * std::exp(-d2 / 1.5);
      const bool black = black_lower_half && row >= kHeight / 2;
      p.value.push_back(black ? 0.f : float(sky + sun));
      p.value.push_back(black ? 0.f : float(0.8 * sky + 0.9 * sun));
      p.value.push_back(black ? 0.f : float(1.3 * sky + 0.5 * sun));
    }
  return p;
}

// A constant environment's radiance parameter.
Param constant_radiance() {
  Param p;
  p.name = "environment.radiance";
  p.shape = {3};
  p.value = {0.5f, 1.f, 2.f};
  return p;
}

// A direction uniform on the sphere.
Vec3f random_direction(TestRng& rng) {
  const double z = rng.uniform(-1, 1), phi = rng.uniform(0, 2 * M_PI), r = std::sqrt(1 - z * z);
  return Vec3f(float(r * std::cos(phi)), float(z), float(r * std::sin(phi)));
}

Environment make_environment(ParamStore& store, Param radiance, bool is_map, float scale, bool bilinear = false) {
  Environment env;
  env.present = true;
  env.is_map = is_map;
  env.bilinear = bilinear;
  env.param = store.add(std::move(radiance));
  env.scale = scale;
  env.prepare(store);
  return env;
}

// Orients env by the rotation about axis (degrees), as a scene's "transform" does.
void rotate(Environment& env, const Vec3f& axis, float degrees) {
  const Transform t = Transform::rotate(axis, degrees);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) env.rotation[i][j] = t.m[i][j];
  env.rotated = true;
}

Chi2Result chi2_environment(const Environment& env, const std::string& label, uint64_t seed) {
  Chi2Options opt;
  opt.label = label;
  opt.seed = seed;
  // Two bins per texel (bilinear: per cell between samples) along each axis, aligned with them:
  // the expected counts integrate a pdf that jumps at their borders.
  opt.theta_bins = 2 * (env.bilinear ? kHeight - 1 : kHeight);
  opt.phi_bins = 2 * kWidth;
  return chi2_test(
      latlong_sphere(),
      [&](float, Vec2f u) {
        const EmitterSample s = env.sample(u.x, u.y);
        return DirectionSample{s.wi, s.pdf};
      },
      [&](const Vec3f& w) { return env.pdf(w); }, opt);
}

// Directions at random and on the awkward places of the parameterisation: poles, the u seam
// (−z… +z half-plane with x = 0), and texel corners.
std::vector<Vec3f> lookup_directions(TestRng& rng) {
  std::vector<Vec3f> dirs{{0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}, {1, 0, 0}, {-1, 0, 0}};
  dirs.push_back(Environment::uv_to_direction({5.f / kWidth, 3.f / kHeight}));
  dirs.push_back(Environment::uv_to_direction({0.9999f, 0.5f}));
  dirs.push_back(Environment::uv_to_direction({20.5f / kWidth, 5.5f / kHeight}));
  for (int i = 0; i < 20; ++i) dirs.push_back(random_direction(rng));
  return dirs;
}

void check_environment_backprop(ParamStore& store, const Environment& env, const std::string& label, TestRng& rng) {
  store.require_grad({});
  for (const Vec3f& dir : lookup_directions(rng)) {
    const Vec3f adjoint(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
    const std::vector<double> analytic =
        gradient_through_sink(store, env.param, [&](GradientAccumulator& g) { env.backprop(store, dir, adjoint, g); });
    std::vector<double> numeric;
    Param& p = store[env.param];
    for (size_t i = 0; i < p.size(); ++i)
      numeric.push_back(
          central_difference_of_param(p, i, [&] { return adjoint_dot(adjoint, env.eval<double>(store, dir)); }));
    // eval is linear in the radiance: exact up to rounding.
    const GradientComparison c = compare_gradients(analytic, numeric, {}, 1e-5, 1e-7);
    INFO(label << " scale " << env.scale << ", direction (" << dir.x << ", " << dir.y << ", " << dir.z << ") adjoint ("
               << adjoint.x << ", " << adjoint.y << ", " << adjoint.z << ")\n"
               << c.report);
    CHECK(c.ok);
  }
}

}  // namespace

TEST_CASE("environment map sampler matches its pdf (chi-square)", "[emitter][envmap][chi2]") {
  for (bool bilinear : {false, true})
    for (bool black_lower_half : {false, true}) {
      ParamStore store;
      const Environment env = make_environment(store, structured_map(black_lower_half), true, 1.5f, bilinear);
      const std::string label = std::string("32x16 map with a sun") +
                                (black_lower_half ? ", black below the horizon" : "") +
                                (bilinear ? ", Mitsuba's bilinear lookup" : "");
      const Chi2Result r = chi2_environment(env, label, (black_lower_half ? 7 : 6) + (bilinear ? 10 : 0));
      INFO(r.report);
      CHECK(r.passed(1e-3));
      CHECK(r.pdf_integral == Approx(1.0).epsilon(1e-4));
      // The sampler never loses a sample: every generated direction has a positive pdf, including
      // directions within ~3e-4 rad of the poles where dir.y rounds to ±1 in float.
      CHECK(r.accepted_fraction == 1.0);
    }
}

TEST_CASE("constant environment sampler matches its pdf (chi-square)", "[emitter][envmap][chi2]") {
  ParamStore store;
  const Environment env = make_environment(store, constant_radiance(), false, 1.f);
  const Chi2Result r = chi2_environment(env, "constant environment", 8);
  INFO(r.report);
  CHECK(r.passed(1e-3));
  CHECK(r.pdf_integral == Approx(1.0).epsilon(1e-4));
}

TEST_CASE("environment map pdf integrates to one", "[emitter][envmap][pdf]") {
  for (bool bilinear : {false, true})
    for (bool black_lower_half : {false, true}) {
      ParamStore store;
      const Environment env = make_environment(store, structured_map(black_lower_half), true, 1.f, bilinear);
      // Integration cells aligned with the texels (the bilinear mode's cells: H − 1 rows between
      // sample rows, columns shifted by half a turn), inside which pdf · sin θ is constant.
      const double integral =
          bilinear ? integrate_over_domain(
                         latlong_sphere(), [&](const Vec3f& w) { return env.pdf(w); }, 1e-6, kHeight - 1, 2 * kWidth)
                   : integrate_over_domain(
                         latlong_sphere(), [&](const Vec3f& w) { return env.pdf(w); }, 1e-6, kHeight, kWidth);
      INFO("black lower half: " << black_lower_half << ", bilinear " << bilinear);
      CHECK(integral == Approx(1.0).epsilon(1e-5));
    }
}

TEST_CASE("environment map pdf is proportional to luminance", "[emitter][envmap][pdf]") {
  ParamStore store;
  const Environment env = make_environment(store, structured_map(false), true, 1.f);
  const Param& p = store[env.param];
  // pdf / luminance is the same for every texel centre (the sampler is exact for a
  // piecewise-constant map up to the sin θ of the row centre it uses).
  double ratio0 = 0.0;
  for (int row = 0; row < kHeight; ++row)
    for (int col = 0; col < kWidth; ++col) {
      const Vec3f dir = Environment::uv_to_direction({(col + 0.5f) / kWidth, (row + 0.5f) / kHeight});
      const size_t b = (size_t(row) * kWidth + size_t(col)) * 3;
      const double ratio = env.pdf(dir) / luminance({p.value[b], p.value[b + 1], p.value[b + 2]});
      if (ratio0 == 0.0) ratio0 = ratio;
      INFO("row " << row << " col " << col);
      CHECK(ratio == Approx(ratio0).epsilon(1e-4));
    }
}

TEST_CASE("environment backprop matches finite differences of eval", "[emitter][envmap][backprop]") {
  TestRng rng(51);
  for (bool bilinear : {false, true}) {
    ParamStore store;
    const Environment env = make_environment(store, structured_map(false), true, 1.5f, bilinear);
    check_environment_backprop(store, env, bilinear ? "32x16 map, bilinear" : "32x16 map", rng);
  }
  for (int size : {1, 3}) {
    ParamStore store;
    Param radiance;
    radiance.name = "environment.radiance";
    radiance.shape = {size};
    for (int c = 0; c < size; ++c) radiance.value.push_back(float(rng.uniform(0.1, 3.0)));
    const Environment env = make_environment(store, radiance, false, 0.7f);
    check_environment_backprop(store, env, "constant of size " + std::to_string(size), rng);
  }
}

// Mitsuba 3's envmap lookup, written out independently of envmap.cpp: u = atan2(d.x, −d.z)/(2π)
// wrapped to [0, 1), v = acos(d.y)/π, then bilinear interpolation at (u·W, v·(H−1)) in the
// bitmap extended by a copy of its first column (Mitsuba's envmap.cpp). The bilinear mode must
// agree everywhere, and its texel samples sit exactly at their directions.
TEST_CASE("the bilinear mode is Mitsuba 3's envmap lookup", "[emitter][envmap]") {
  ParamStore store;
  const Param map = structured_map(false);
  const Environment env = make_environment(store, map, true, 1.f, true);
  auto mitsuba = [&](const Vec3f& d) {
    double u = std::atan2(double(d.x), -double(d.z)) / (2 * M_PI);
    u -= std::floor(u);
    const double v = std::acos(std::clamp(double(d.y), -1.0, 1.0)) / M_PI;
    const double x = u * kWidth, y = v * (kHeight - 1);
    const int x0 = std::min(int(x), kWidth - 1), y0 = std::min(int(y), kHeight - 2);
    const double fx = x - x0, fy = y - y0;
    auto texel = [&](int r, int c, int ch) {
      return double(map.value[(size_t(r) * kWidth + size_t(c % kWidth)) * 3 + size_t(ch)]);
    };
    Vec3d out;
    for (int ch = 0; ch < 3; ++ch)
      out[ch] = (1 - fx) * (1 - fy) * texel(y0, x0, ch) + fx * (1 - fy) * texel(y0, x0 + 1, ch) +
                (1 - fx) * fy * texel(y0 + 1, x0, ch) + fx * fy * texel(y0 + 1, x0 + 1, ch);
    return out;
  };
  TestRng rng(77);
  std::vector<Vec3f> dirs = lookup_directions(rng);
  for (int i = 0; i < 200; ++i) dirs.push_back(random_direction(rng));
  for (const Vec3f& d : dirs) {
    const Spectrum<double> ours = env.eval<double>(store, d);
    const Vec3d ref = mitsuba(d);
    INFO("direction (" << d.x << ", " << d.y << ", " << d.z << ")");
    for (int ch = 0; ch < 3; ++ch) CHECK(ours[ch] == Approx(ref[ch]).epsilon(2e-4).margin(1e-4));
  }
  // Texel (row 5, column 20) — the sun's centre — is seen exactly along its direction:
  // φ = 2π·20/W from −z towards +x, θ = π·5/(H−1).
  const double phi = 2 * M_PI * 20 / kWidth, theta = M_PI * 5 / (kHeight - 1);
  const Vec3f sun(float(std::sin(theta) * std::sin(phi)), float(std::cos(theta)),
                  float(-std::sin(theta) * std::cos(phi)));
  const Spectrum<double> at_sun = env.eval<double>(store, sun);
  CHECK(at_sun[0] == Approx(map.value[(5 * kWidth + 20) * 3]).epsilon(1e-4));
  // Negative control: the nearest lookup of the same map differs there (its u origin is +z).
  ParamStore other;
  const Environment nearest = make_environment(other, map, true, 1.f, false);
  CHECK(std::abs(nearest.eval<double>(other, sun)[0] - at_sun[0]) > 1.0);
}

TEST_CASE("environment lookups keep the polar angle near the poles", "[emitter][envmap]") {
  // v = θ/π of the direction as stored, against θ in long double: acos(d.y) lost θ near the poles
  // (2.4e-4 rad within 1e-3 rad of one: a light sample drawn in one row of a large map was looked up
  // in another; a 3-row sun at the zenith of an 8192-row map came out 3.2% too bright).
  double worst = 0;
  for (double theta : {1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 0.1, 1.0, M_PI - 1e-2, M_PI - 1e-4, M_PI - 1e-6})
    for (double phi : {0.1, 1.3, 2.9, 4.4}) {
      const Vec3f d(float(std::sin(theta) * std::cos(phi)), float(std::cos(theta)),
                    float(std::sin(theta) * std::sin(phi)));
      const long double x = d.x, y = d.y, z = d.z;
      const long double exact = std::atan2(std::sqrt(x * x + z * z), y);
      const double err = double(std::abs((long double)Environment::direction_to_uv(d).y * M_PIl - exact));
      INFO("theta " << theta << " phi " << phi << ": error " << err << " rad");
      CHECK(err < 1e-6);
      worst = std::max(worst, err);
    }
  std::printf("environment polar angle: worst error %.3g rad\n", worst);
}

// A camera turning in front of a bilinear map sees its radiance along d + ω × d: the direction
// gradient against central differences of eval along two tangents of the sphere, at directions
// whose ± steps stay in one cell (the lookup is smooth inside a cell, continuous across).
TEST_CASE("the bilinear map's direction gradient matches finite differences of eval", "[emitter][envmap][backprop]") {
  for (bool rotated : {false, true}) {
    CAPTURE(rotated);
    ParamStore store;
    Environment env = make_environment(store, structured_map(false), true, 1.5f, true);
    if (rotated) rotate(env, {0.3f, 1.f, -0.4f}, 70.f);
    TestRng rng(93);
    int checked = 0;
    for (int i = 0; i < 400 && checked < 120; ++i) {
      const double z = rng.uniform(-0.98, 0.98), phi = rng.uniform(0, 2 * M_PI), r = std::sqrt(1 - z * z);
      const Vec3d d(r * std::cos(phi), z, r * std::sin(phi));
      const Vec3d adjoint(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
      const Vec3d g = env.direction_gradient(store, Vec3f(d), adjoint);
      const Vec3d t1 = normalize(cross(d, Vec3d(0.3, 0.2, 1.0))), t2 = cross(d, t1);
      const double h = 3e-3;
      bool one_cell = true;
      double fd[2];
      for (int k = 0; k < 2; ++k) {
        const Vec3d t = k == 0 ? t1 : t2;
        const Vec3f plus(normalize(d + t * h)), minus(normalize(d - t * h));
        const EnvLookup a = env.lookup(plus), b = env.lookup(minus), c = env.lookup(Vec3f(d));
        one_cell = one_cell && a.row == c.row && a.col == c.col && b.row == c.row && b.col == c.col;
        auto f = [&](const Vec3f& w) {
          const Spectrum<double> L = env.eval<double>(store, w);
          return adjoint.x * L[0] + adjoint.y * L[1] + adjoint.z * L[2];
        };
        fd[k] = (f(plus) - f(minus)) / (2 * h);
      }
      if (!one_cell) continue;
      ++checked;
      INFO("direction (" << d.x << ", " << d.y << ", " << d.z << "), gradient (" << g.x << ", " << g.y << ", " << g.z
                         << ")");
      CHECK(dot(g, t1) == Approx(fd[0]).epsilon(3e-3).margin(2e-3));
      CHECK(dot(g, t2) == Approx(fd[1]).epsilon(3e-3).margin(2e-3));
      // Only d's direction is read (rotated: to float rounding of the rotation).
      CHECK(std::abs(dot(g, Vec3d(Vec3f(d)))) < (rotated ? 1e-6 : 1e-12) * (1 + length(g)));
    }
    CHECK(checked >= 100);
  }
  // Nothing for the nearest lookup (jumps at texel edges, no gradient) or a constant environment.
  ParamStore other;
  const Environment nearest = make_environment(other, structured_map(false), true, 1.5f, false);
  CHECK(length(nearest.direction_gradient(other, Vec3f(0.6f, 0.48f, 0.64f), Vec3d(1.0))) == 0.0);
  ParamStore third;
  const Environment uniform = make_environment(third, constant_radiance(), false, 1.f);
  CHECK(length(uniform.direction_gradient(third, Vec3f(0.6f, 0.48f, 0.64f), Vec3d(1.0))) == 0.0);
}

// An oriented map (Mitsuba's to_world): along R·d it shows what the unrotated map shows along d,
// with the same pdf, and its sampler draws R·d with that pdf (chi-square in world directions).
TEST_CASE("a rotated environment map reads R^T d and samples R d", "[emitter][envmap][chi2]") {
  for (bool bilinear : {false, true}) {
    CAPTURE(bilinear);
    ParamStore a, b;
    const Environment plain = make_environment(a, structured_map(true), true, 1.5f, bilinear);
    Environment turned = make_environment(b, structured_map(true), true, 1.5f, bilinear);
    rotate(turned, {0.3f, 1.f, -0.4f}, 70.f);
    const Transform r = Transform::rotate({0.3f, 1.f, -0.4f}, 70.f);
    TestRng rng(101);
    for (int i = 0; i < 500; ++i) {
      const Vec3f d = random_direction(rng);
      const Vec3f rd = r.vector(d);
      const Spectrum<double> want = plain.eval<double>(a, d), got = turned.eval<double>(b, rd);
      INFO("direction (" << d.x << ", " << d.y << ", " << d.z << ")");
      for (int c = 0; c < 3; ++c) CHECK(got[c] == Approx(want[c]).epsilon(1e-4).margin(1e-4));
      CHECK(turned.pdf(rd) == Approx(plain.pdf(d)).epsilon(1e-4));
    }
    // The chi-square's bins are the world's latitude-longitude cells, which a rotated map's texels
    // cross: integrating the pdf over them by quadrature would miss slivers of a black region,
    // so the sampler is tested on the map without one.
    ParamStore c;
    Environment sky = make_environment(c, structured_map(false), true, 1.5f, bilinear);
    rotate(sky, {0.3f, 1.f, -0.4f}, 70.f);
    const Chi2Result result = chi2_environment(sky, bilinear ? "rotated map, bilinear" : "rotated map", 23);
    INFO(result.report);
    CHECK(result.passed(1e-3));
    CHECK(result.accepted_fraction == 1.0);
    // Unrotated, the same chi-square fails: the pdf describes a different sky.
    Environment wrong = sky;
    wrong.rotated = false;
    CHECK(!chi2_test(
               latlong_sphere(),
               [&](float, Vec2f u) {
                 const EmitterSample s = sky.sample(u.x, u.y);
                 return DirectionSample{s.wi, s.pdf};
               },
               [&](const Vec3f& w) { return wrong.pdf(w); },
               [] {
                 Chi2Options o;
                 o.label = "a rotated sampler against the unrotated pdf";
                 o.seed = 24;
                 o.theta_bins = 2 * kHeight;
                 o.phi_bins = 2 * kWidth;
                 return o;
               }())
               .passed(1e-3));
  }
}
