// The chi-square harness itself: its p-values against closed forms and tables, and its power —
// it must accept a correct sampler and reject subtly wrong ones (a harness that never fails
// proves nothing about the samplers it passes).
#include <catch2/catch.hpp>

#include <cmath>

#include "tests/kernels/chi2.h"

using namespace bl;
using namespace bl::test;

namespace {

// Q(n, x) for integer n from the Poisson tail, e^{−x} Σ_{k<n} x^k / k!, summed in log space.
double poisson_tail(int n, double x) {
  double sum = 0.0;
  for (int k = 0; k < n; ++k) sum += std::exp(k * std::log(x) - x - std::lgamma(k + 1.0));
  return sum;
}

// Directions with pdf ∝ cos^n θ over the upper hemisphere, sampled by inversion.
Vec3f sample_cosine_power(double n, Vec2f u) {
  const double cos_theta = std::pow(1.0 - double(u.x), 1.0 / (n + 1.0));
  return spherical_direction(std::acos(cos_theta), 2.0 * M_PI * u.y);
}
float cosine_power_pdf(double n, const Vec3f& w) {
  return w.z > 0.f ? float((n + 1.0) / (2.0 * M_PI) * std::pow(double(w.z), n)) : 0.f;
}

Chi2Result run(double sampled_power, double claimed_power, double keep = 1.0, double claimed_keep = 1.0) {
  Chi2Options opt;
  opt.label = "cos^n test sampler";
  opt.sample_count = 400'000;
  return chi2_test(
      upper_hemisphere(),
      [&](float u_lobe, Vec2f u) {
        if (u_lobe >= keep) return DirectionSample{};
        const Vec3f w = sample_cosine_power(sampled_power, u);
        // The sample reports the claimed pdf, so only the histogram can expose the mismatch.
        return DirectionSample{w, float(claimed_keep) * cosine_power_pdf(claimed_power, w)};
      },
      [&](const Vec3f& w) { return float(claimed_keep) * cosine_power_pdf(claimed_power, w); }, opt);
}

}  // namespace

TEST_CASE("regularized incomplete gamma matches closed forms and tables", "[chi2]") {
  for (double x : {0.01, 0.5, 1.0, 2.0, 7.5, 30.0}) {
    CHECK(regularized_gamma_q(1.0, x) == Approx(std::exp(-x)).epsilon(1e-12));
    CHECK(regularized_gamma_q(0.5, x) == Approx(std::erfc(std::sqrt(x))).epsilon(1e-10));
  }
  for (int n : {3, 40, 400, 2000})
    for (double ratio : {0.8, 0.95, 1.0, 1.05, 1.2}) {
      const double x = ratio * n;
      INFO("a = " << n << ", x = " << x);
      CHECK(regularized_gamma_q(n, x) == Approx(poisson_tail(n, x)).epsilon(1e-9).margin(1e-300));
    }
  // Upper 5% and 0.1% points of the chi-square distribution (standard tables).
  CHECK(chi2_p_value(3.841459, 1) == Approx(0.05).epsilon(1e-5));
  CHECK(chi2_p_value(18.307038, 10) == Approx(0.05).epsilon(1e-5));
  CHECK(chi2_p_value(124.342113, 100) == Approx(0.05).epsilon(1e-5));
  CHECK(chi2_p_value(149.449252, 100) == Approx(0.001).epsilon(1e-4));
  CHECK(chi2_p_value(0.0, 5) == 1.0);
}

TEST_CASE("chi-square harness accepts a correct sampler", "[chi2]") {
  const Chi2Result r = run(1.0, 1.0);
  INFO(r.report);
  CHECK(r.passed(1e-3));
  CHECK(r.pdf_integral == Approx(1.0).epsilon(1e-4));
}

TEST_CASE("chi-square harness rejects a sampler off by 5% in its exponent", "[chi2]") {
  const Chi2Result r = run(1.0, 1.05);
  INFO(r.report);
  CHECK(r.p_value < 1e-6);
}

TEST_CASE("chi-square harness accounts for lost samples", "[chi2]") {
  // Losing 30% of the samples is correct when the pdf integrates to 0.7 ...
  const Chi2Result honest = run(2.0, 2.0, 0.7, 0.7);
  INFO(honest.report);
  CHECK(honest.passed(1e-3));
  CHECK(honest.pdf_integral == Approx(0.7).epsilon(1e-4));
  // ... and wrong when it claims 0.75.
  const Chi2Result dishonest = run(2.0, 2.0, 0.7, 0.75);
  INFO(dishonest.report);
  CHECK(dishonest.p_value < 1e-6);
}

TEST_CASE("chi-square harness flags pdf mismatches and impossible samples", "[chi2]") {
  Chi2Options opt;
  opt.sample_count = 10'000;
  // A sample reporting a pdf different from pdf(wi).
  const Chi2Result mismatch = chi2_test(
      upper_hemisphere(),
      [](float, Vec2f u) {
        return DirectionSample{sample_cosine_power(1.0, u), 1.f};
      },
      [](const Vec3f& w) { return cosine_power_pdf(1.0, w); }, opt);
  CHECK(mismatch.pdf_mismatches > 0);
  CHECK_FALSE(mismatch.passed(1e-3));
  // Samples where the pdf is zero: half of them land where pdf(wi) says nothing can.
  const Chi2Result impossible = chi2_test(
      upper_hemisphere(),
      [](float, Vec2f u) {
        const Vec3f w = sample_cosine_power(1.0, u);
        return DirectionSample{w, w.x > 0.f ? 1.f : 0.5f};
      },
      [](const Vec3f& w) { return w.x > 0.f ? 1.f : 0.f; }, opt);
  CHECK(impossible.impossible > 0);
  CHECK_FALSE(impossible.passed(1e-3));
}

TEST_CASE("latitude-longitude domain round-trips directions", "[chi2]") {
  const SphericalDomain d = latlong_sphere();
  for (double theta : {0.1, 1.0, 2.0, 3.0})
    for (double phi : {0.05, 1.0, 3.0, 4.5, 6.2}) {
      const auto [t, p] = d.to_angles(d.to_direction(theta, phi));
      CHECK(t == Approx(theta).epsilon(1e-5));
      CHECK(p == Approx(phi).epsilon(1e-5));
    }
  const double area = integrate_over_domain(d, [](const Vec3f&) { return 1.0; });
  CHECK(area == Approx(4.0 * M_PI).epsilon(1e-5));
}
