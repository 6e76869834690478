// Henyey–Greenstein: sampling against its pdf (chi-square over the sphere), normalisation,
// reciprocity, the sign convention (mean cosine between d_in and wo is g), and the derivative
// shader against central differences of its own eval, with a negative control that a known-wrong
// derivative fails the same check.
#include <catch2/catch.hpp>

#include <cmath>

#include "kernels/phase/hg.h"
#include "tests/kernels/chi2.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

Vec3f random_direction(TestRng& rng) {
  const double z = rng.uniform(-1, 1), phi = rng.uniform(0, 2 * M_PI), r = std::sqrt(1 - z * z);
  return {float(r * std::cos(phi)), float(r * std::sin(phi)), float(z)};
}

// p as a function of μ = wi·wo, in double, straight from the formula (independent of hg_eval).
double hg_formula(double g, double mu) { return (1 - g * g) / (4 * M_PI * std::pow(1 + g * g + 2 * g * mu, 1.5)); }

// The exact p of two float directions, in long double (where 1 + g² + 2gμ keeps 1e-13 of itself
// at the peak), μ the cosine of the vectors as stored, normalized by their lengths; independent of
// hg_eval's float arithmetic.
long double hg_exact(long double g, const Vec3f& a, const Vec3f& b) {
  long double dot = 0, na = 0, nb = 0;
  for (int k = 0; k < 3; ++k) {
    const long double x = a[k], y = b[k];
    dot += x * y, na += x * x, nb += y * y;
  }
  const long double mu = dot / std::sqrt(na * nb), denom = 1 + g * g + 2 * g * mu;
  return (1 - g * g) / (4 * M_PIl * denom * std::sqrt(denom));
}

}  // namespace

TEST_CASE("HG sampling matches its pdf (chi-square over the sphere)", "[phase][chi2]") {
  uint64_t seed = 500;
  for (float g : {-0.7f, 0.f, 0.3f, 0.9f})
    for (const Vec3f& wi :
         {Vec3f(0, 0, 1), normalize(Vec3f(0.3f, -0.5f, 0.8f)), normalize(Vec3f(-0.9f, 0.2f, -0.4f))}) {
      Chi2Options opt;
      opt.label = "hg g " + std::to_string(g) + " wi (" + std::to_string(wi.x) + ", " + std::to_string(wi.y) + ", " +
                  std::to_string(wi.z) + ")";
      opt.seed = seed++;
      const Chi2Result r = chi2_test(
          latlong_sphere(),
          [&](float, Vec2f u) {
            const PhaseSample s = hg_sample({g}, wi, u);
            return DirectionSample{s.wo, s.pdf};
          },
          [&](const Vec3f& wo) { return hg_pdf({g}, wi, wo); }, opt);
      INFO(r.report);
      CHECK(r.passed(opt.significance));
      CHECK(r.pdf_integral == Approx(1.0).epsilon(2e-3));
    }
}

// Sampling inverts the CDF of μ = cos θ (θ between d_in and wo): μ(ξ) = (1 + g² − s²)/(2g) with
// s = (1 − g²)/(1 − g + 2gξ), here in double. For 0 < |g| < 1e-3 the sampler drew uniformly
// while returning the HG pdf (μ off by up to ~g: 5e-4), and in float the formula loses ~1e-7/g to
// cancellation (7e-5 in μ at g = 2e-3); both fail this check.
TEST_CASE("HG sampling inverts its CDF, small g included", "[phase]") {
  const Vec3f wi{0.f, 0.f, -1.f};  // d_in = +z: cos θ = wo.z
  for (float g : {-7e-4f, -1e-5f, 1e-4f, 5e-4f, 9.9e-4f, 2e-3f, -0.03f, 0.099f, 0.1f, 0.3f, -0.8f, 0.95f}) {
    double worst = 0;
    for (int k = 1; k < 200; ++k) {
      const float xi = float(k) / 200.f;
      const PhaseSample sample = hg_sample({g}, wi, {xi, 0.25f});
      const double gd = g, s = (1 - gd * gd) / (1 - gd + 2 * gd * double(xi));
      const double mu = (1 + gd * gd - s * s) / (2 * gd);
      worst = std::max(worst, std::abs(double(sample.wo.z) - mu));
    }
    INFO("g = " << g << ": largest |cos θ(ξ) − exact| = " << worst);
    CHECK(worst < 1e-5);
  }
}

TEST_CASE("HG sampling keeps its precision near |g| = 1", "[phase]") {
  // The angle each ξ maps to, measured on the direction drawn, against the exact inversion of the
  // same ξ in long double, on the side of the peak: 1 − cos θ = |wi + wo|²/2 for g > 0 and
  // 1 + cos θ = |wi − wo|²/2 for g < 0 (d_in = −wi). The textbook inversion and sqrt(1 − cos²θ)
  // cancelled near the peak: at g = 0.999 1 − cos θ was off by 11.5% on average and the cone
  // θ < 0.1(1 − g) drew 12× its share.
  TestRng rng(9);
  for (double g : {0.05, 0.5, 0.9, 0.99, 0.999, -0.5, -0.99, -0.999}) {
    const int n = 20000;
    const long double gl = float(g);
    // 1 ∓ cos θ(ξ) on the peak's side, exactly.
    auto exact_near = [&](long double x) {
      const long double t = 1 - gl + 2 * gl * x;
      return g > 0 ? 2 * (1 - gl) * (1 - gl) * (1 - x) * (1 + gl * x) / (t * t)
                   : 2 * (1 + gl) * (1 + gl) * x * (1 - gl * (1 - x)) / (t * t);
    };
    const long double cone = 1 - std::cos(0.3L * (1 - std::abs(gl)));  // θ within 0.3(1 − |g|) of the peak
    const Vec3f wi = random_direction(rng);
    double mean_error = 0;
    int in_cone = 0, exact_cone = 0;
    for (int i = 0; i < n; ++i) {
      const float xi = (float(i) + 0.5f) / float(n);
      const Vec3f wo = hg_sample({float(g)}, wi, {xi, rng.next_float()}).wo;
      long double near = 0;
      for (int k = 0; k < 3; ++k) {
        const long double d = g > 0 ? (long double)wi[k] + wo[k] : (long double)wi[k] - wo[k];
        near += d * d / 2;
      }
      const long double exact = exact_near(xi);
      mean_error += double(std::abs(near - exact) / exact) / n;
      in_cone += near < cone;
      exact_cone += exact < cone;
    }
    INFO("g " << g << ": mean relative error " << mean_error << ", cone " << in_cone << " of " << exact_cone);
    CHECK(mean_error < 1e-4);
    CHECK(std::abs(in_cone - exact_cone) <= 2 + exact_cone / 1000);
  }
}

TEST_CASE("HG integrates to one, is reciprocal, and g > 0 scatters forward", "[phase]") {
  for (double g : {-0.95, -0.7, -0.2, 0.0, 0.3, 0.9, 0.95}) {
    // Simpson's rule over μ on a grid fine enough for g = ±0.95's peak.
    const int n = 200000;
    double integral = 0;
    for (int i = 0; i <= n; ++i) {
      const double mu = -1 + 2.0 * i / n, w = (i == 0 || i == n) ? 1 : (i % 2 ? 4 : 2);
      integral += w * hg_formula(g, mu);
    }
    integral *= 2 * M_PI * (2.0 / n) / 3;
    INFO("g " << g);
    CHECK(integral == Approx(1.0).epsilon(1e-6));
  }
  TestRng rng(7);
  double worst = 0;
  for (int i = 0; i < 10000; ++i) {
    const float g = float(rng.uniform(-0.99, 0.99));
    const Vec3f a = random_direction(rng), b = random_direction(rng);
    const double pab = hg_eval<double>({g}, a, b), pba = hg_eval<double>({g}, b, a);
    worst = std::max(worst, std::abs(pab - pba) / pab);
    // μ of the normalized vectors (their lengths differ from 1 by ~1e-7, which at g = 0.99 and μ
    // near −1 moves p by 2e-5 when the unnormalized cosine is taken).
    const double formula = double(hg_exact(g, a, b));
    REQUIRE(pab == Approx(formula).epsilon(1e-5));
  }
  CHECK(worst < 1e-6);
  // Mean cosine between the propagation directions d_in = −wi and wo is g (exact sampling).
  for (float g : {-0.6f, 0.f, 0.4f, 0.85f}) {
    const Vec3f wi = normalize(Vec3f(0.2f, 0.7f, -0.3f));
    double sum = 0, sum2 = 0;
    const int n = 200000;
    for (int i = 0; i < n; ++i) {
      const PhaseSample s = hg_sample({g}, wi, {rng.next_float(), rng.next_float()});
      const double c = dot(-wi, s.wo);
      sum += c, sum2 += c * c;
    }
    const double mean = sum / n, se = std::sqrt((sum2 / n - mean * mean) / n);
    INFO("g " << g << ": mean cos " << mean << " ± " << se);
    CHECK(std::abs(mean - g) < 4 * se + 1e-6);
  }
}

namespace {
// Largest relative error of `derivative(g, wi, wo)` against central differences of hg_eval in
// double over random trials.
template <class Derivative>
double worst_relative_error(Derivative&& derivative, uint64_t seed) {
  TestRng rng(seed);
  double worst = 0;
  for (int i = 0; i < 3000; ++i) {
    const double g = rng.uniform(-0.95, 0.95);
    const Vec3f wi = random_direction(rng), wo = random_direction(rng);
    const double h = 1e-6;
    const double fd = (hg_eval<double>({g + h}, wi, wo) - hg_eval<double>({g - h}, wi, wo)) / (2 * h);
    const double ad = derivative(float(g), wi, wo);
    worst = std::max(worst, std::abs(ad - fd) / std::max(std::abs(fd), 1e-3));
  }
  return worst;
}
}  // namespace

TEST_CASE("HG derivative shader matches central differences of eval", "[phase][gradient]") {
  const double err = worst_relative_error(
      [](float g, const Vec3f& wi, const Vec3f& wo) { return double(hg_backprop({g}, wi, wo, 1.f).g); }, 11);
  INFO("worst relative error " << err);
  CHECK(err < 1e-3);
}

TEST_CASE("HG eval and derivative hold their precision near |g| = 1, and are flat beyond the clamp",
          "[phase][gradient]") {
  // On directions HG samples (where it peaks) and uniform ones, against the exact value of the
  // same float directions. 1 + g² + 2gμ cancelled in float at the peak: the value was off by 0.6%
  // at g = 0.99 and 55% at 0.999, the derivative by 14% and 6× (its scale: |dp/dg| + 0.01 p/(1 − |g|)).
  TestRng rng(5);
  for (double g : {0.9, 0.98, 0.99, 0.995, 0.998, 0.999, -0.9, -0.99, -0.999}) {
    double worst_value = 0, worst_derivative = 0;
    for (int i = 0; i < 4000; ++i) {
      const Vec3f wi = random_direction(rng);
      const Vec3f wo =
          i % 2 ? hg_sample({float(g)}, wi, {rng.next_float(), rng.next_float()}).wo : random_direction(rng);
      const long double exact = hg_exact(float(g), wi, wo), h = 1e-5L * (1 - std::abs(g));
      const double fd = double((hg_exact(float(g) + h, wi, wo) - hg_exact(float(g) - h, wi, wo)) / (2 * h));
      const double scale = std::abs(fd) + 1e-2 * double(exact) / (1 - std::abs(g));
      worst_value = std::max(worst_value, double(std::abs(hg_eval<float>({float(g)}, wi, wo) - exact) / exact));
      worst_derivative =
          std::max(worst_derivative, std::abs(double(hg_backprop({float(g)}, wi, wo, 1.f).g) - fd) / scale);
    }
    INFO("g " << g << ": worst relative value error " << worst_value << ", derivative " << worst_derivative);
    CHECK(worst_value < 1e-4);
    CHECK(worst_derivative < 5e-3);
  }
  // Beyond ±0.999 the clamp holds g, so eval is flat and the derivative 0 (the loader bounds g to
  // ±0.999; an optimizer's step may still land outside before its projection).
  for (float g : {0.9995f, 1.f, -0.9995f, -1.f}) {
    const Vec3f wi = random_direction(rng), wo = hg_sample({g}, wi, {0.3f, 0.6f}).wo;
    CHECK(hg_eval<float>({g}, wi, wo) == hg_eval<float>({std::copysign(kHgMaxAbsG, g)}, wi, wo));
    CHECK(hg_backprop({g}, wi, wo, 1.f).g == 0.f);
  }
}

TEST_CASE("negative control: a known-wrong HG derivative fails the same check", "[phase][gradient]") {
  // The Mitsuba-class error: the derivative of 1 + g² − 2gμ instead of 1 + g² + 2gμ (μ = wi·wo),
  // i.e. a sign slip in the direction convention inside the derivative only.
  const double err = worst_relative_error(
      [](float g, const Vec3f& wi, const Vec3f& wo) {
        const double mu = dot(wi, wo), a = 1 + double(g) * g - 2 * double(g) * mu;
        return (-2 * double(g) / std::pow(a, 1.5) - 3 * (1 - double(g) * g) * (double(g) - mu) / std::pow(a, 2.5)) /
               (4 * M_PI);
      },
      11);
  INFO("worst relative error of the wrong derivative " << err);
  CHECK(err > 1e-1);
}
