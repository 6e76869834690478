// BSDF samplers against their own pdfs: chi-square goodness of fit over the hemisphere, the pdf
// each sample reports against pdf(wo, wi), ∫ pdf dω against the fraction of samples not lost, and
// the path loop's weight eval/pdf of sampled directions against quadrature of eval (a sampler must
// reach every direction where eval is non-zero).
#include <catch2/catch.hpp>

#include <cmath>
#include <vector>

#include "tests/kernels/bsdf/bsdf_under_test.h"
#include "tests/kernels/chi2.h"

using namespace bl;
using namespace bl::test;

namespace {

constexpr double kDegree = M_PI / 180.0;

// Outgoing directions from normal incidence to grazing, off the x axis so that no bin edge lines
// up with the lobe's plane of symmetry.
std::vector<Vec3f> outgoing_directions() {
  std::vector<Vec3f> result;
  for (double theta : {0.0, 30.0, 60.0, 80.0, 88.0}) result.push_back(spherical_direction(theta * kDegree, 0.7));
  return result;
}

void check_sampler(const BsdfUnderTest& bsdf, const Vec3f& wo, uint64_t seed) {
  Chi2Options opt;
  opt.label = bsdf.describe(wo);
  opt.seed = seed;
  const Chi2Result r = chi2_test(
      upper_hemisphere(),
      [&](float u_lobe, Vec2f u) {
        const BsdfSample s = bsdf.sample(wo, u_lobe, u);
        return DirectionSample{s.wi, s.pdf};
      },
      [&](const Vec3f& wi) { return bsdf.pdf(wo, wi); }, opt);
  INFO(r.report);
  CHECK(r.passed(opt.significance));
  // ∫ pdf is the probability of not losing the sample (binomial noise plus quadrature error).
  const double sigma = std::sqrt(r.accepted_fraction * (1.0 - r.accepted_fraction) / double(opt.sample_count));
  CHECK(r.pdf_integral <= 1.0 + 1e-3);
  CHECK(std::abs(r.pdf_integral - r.accepted_fraction) <= 5.0 * sigma + 1e-3);
}

}  // namespace

// [expectation]: not under the sanitizers (10^5 draws of the same sampler); "BSDF pdfs integrate to
// the fraction of samples kept" and the horizon case run every sampler and pdf there.
TEST_CASE("diffuse sampler matches its pdf (chi-square)", "[bsdf][chi2][expectation]") {
  BsdfUnderTest bsdf{BsdfKind::Diffuse, {0.7f, 0.5f, 0.3f}};
  uint64_t seed = 100;
  for (const Vec3f& wo : outgoing_directions()) check_sampler(bsdf, wo, seed++);
}

// [expectation]: not under the sanitizers (10^5 draws of the same sampler); "BSDF pdfs integrate to
// the fraction of samples kept" and the horizon case run every sampler and pdf there.
TEST_CASE("roughconductor sampler matches its pdf (chi-square)", "[bsdf][chi2][expectation]") {
  uint64_t seed = 200;
  for (float alpha : {0.05f, 0.2f, 0.6f})
    for (const Vec3f& wo : outgoing_directions())
      check_sampler(BsdfUnderTest{BsdfKind::RoughConductor, {0.9f, 0.6f, 0.3f}, alpha}, wo, seed++);
}

// [expectation]: not under the sanitizers (10^5 draws of the same sampler); "BSDF pdfs integrate to
// the fraction of samples kept" and the horizon case run every sampler and pdf there.
TEST_CASE("roughplastic sampler matches its pdf (chi-square)", "[bsdf][chi2][expectation]") {
  uint64_t seed = 300;
  for (float alpha : {0.05f, 0.2f, 0.6f})
    for (const Vec3f& wo : outgoing_directions())
      check_sampler(BsdfUnderTest{BsdfKind::RoughPlastic, {0.8f, 0.4f, 0.2f}, alpha}, wo, seed++);
}

// The blend picks its conductor lobe with probability m and its plastic lobe otherwise; both
// lobes must show up in the histogram with the mixture's weights.
// [expectation]: not under the sanitizers (10^5 draws of the same sampler); "BSDF pdfs integrate to
// the fraction of samples kept" and the horizon case run every sampler and pdf there.
TEST_CASE("metallic_roughness sampler matches its pdf (chi-square)", "[bsdf][chi2][expectation]") {
  uint64_t seed = 400;
  for (float metallic : {0.3f, 0.7f})
    for (float alpha : {0.05f, 0.2f, 0.6f})
      for (const Vec3f& wo : outgoing_directions())
        check_sampler(BsdfUnderTest{BsdfKind::MetallicRoughness, {0.8f, 0.5f, 0.2f}, alpha, 1.5f, metallic}, wo,
                      seed++);
}

// Where every sample is kept ∫ pdf must be 1; where some are lost (GGX reflections below the
// horizon) it must equal the kept fraction and never exceed 1.
TEST_CASE("BSDF pdfs integrate to the fraction of samples kept", "[bsdf][pdf]") {
  std::vector<BsdfUnderTest> bsdfs{{BsdfKind::Diffuse, {1.f, 1.f, 1.f}}};
  for (float alpha : {0.05f, 0.3f, 1.0f}) {
    bsdfs.push_back({BsdfKind::RoughConductor, {1.f, 1.f, 1.f}, alpha});
    bsdfs.push_back({BsdfKind::RoughPlastic, {1.f, 1.f, 1.f}, alpha});
    for (float metallic : {0.3f, 0.7f})
      bsdfs.push_back({BsdfKind::MetallicRoughness, {1.f, 1.f, 1.f}, alpha, 1.5f, metallic});
  }
  const long kSamples = 200'000;
  for (const BsdfUnderTest& bsdf : bsdfs)
    for (double theta : {0.0, 45.0, 89.5}) {
      const Vec3f wo = spherical_direction(theta * kDegree, 2.1);
      const double integral =
          integrate_over_domain(upper_hemisphere(), [&](const Vec3f& wi) { return bsdf.pdf(wo, wi); });
      TestRng rng(uint64_t(theta * 10) + 7);
      long kept = 0;
      for (long s = 0; s < kSamples; ++s) {
        const float u_lobe = rng.next_float();
        const Vec2f u{rng.next_float(), rng.next_float()};
        if (bsdf.sample(wo, u_lobe, u).pdf > 0.f) ++kept;
      }
      const double kept_fraction = double(kept) / double(kSamples);
      const double sigma = std::sqrt(kept_fraction * (1.0 - kept_fraction) / double(kSamples));
      INFO(bsdf.describe(wo) << ": ∫pdf = " << integral << ", kept fraction = " << kept_fraction);
      CHECK(integral <= 1.0 + 1e-3);
      CHECK(std::abs(integral - kept_fraction) <= 5.0 * sigma + 1e-3);
      if (kept == kSamples) CHECK(std::abs(integral - 1.0) <= 1e-3);
    }
}

TEST_CASE("BSDF samplers reject outgoing directions below the horizon", "[bsdf]") {
  const Vec3f below = spherical_direction(100.0 * kDegree, 0.3);
  for (const BsdfUnderTest& bsdf :
       {BsdfUnderTest{BsdfKind::Diffuse}, BsdfUnderTest{BsdfKind::RoughConductor},
        BsdfUnderTest{BsdfKind::RoughPlastic}, BsdfUnderTest{BsdfKind::MetallicRoughness}}) {
    INFO(bsdf.describe(below));
    CHECK(bsdf.sample(below, 0.3f, {0.4f, 0.6f}).pdf == 0.f);
    CHECK(bsdf.pdf(below, Vec3f(0.f, 0.f, 1.f)) == 0.f);
    CHECK(bsdf.pdf(Vec3f(0.f, 0.f, 1.f), below) == 0.f);
    CHECK(is_zero(bsdf.eval<float>(below, Vec3f(0.f, 0.f, 1.f))));
    CHECK(is_zero(bsdf.eval<float>(Vec3f(0.f, 0.f, 1.f), below)));
  }
}

// The path loop weights a sampled direction by eval/pdf (bsdf.h: sample returns no weight of its
// own). Its mean must be the directional albedo ∫ eval dωi, which quadrature gives independently:
// this holds only if the reported pdf is the density samples are drawn from and is non-zero
// wherever eval is.
// [expectation]: not under the sanitizers (a Monte Carlo mean against quadrature); the pdf-integral
// case runs the same sample, eval and pdf there.
TEST_CASE("sampled weights eval/pdf estimate the directional albedo without bias", "[bsdf][pdf][expectation]") {
  std::vector<BsdfUnderTest> bsdfs{{BsdfKind::Diffuse, {0.7f, 0.5f, 0.3f}}};
  for (float alpha : {0.1f, 0.5f}) {
    bsdfs.push_back({BsdfKind::RoughConductor, {0.9f, 0.6f, 0.3f}, alpha});
    bsdfs.push_back({BsdfKind::RoughPlastic, {0.8f, 0.4f, 0.2f}, alpha});
    for (float metallic : {0.3f, 0.7f})
      bsdfs.push_back({BsdfKind::MetallicRoughness, {0.8f, 0.5f, 0.2f}, alpha, 1.5f, metallic});
  }
  const long kSamples = 400'000;
  uint64_t seed = 500;
  for (const BsdfUnderTest& bsdf : bsdfs)
    for (double theta : {10.0, 50.0, 80.0}) {
      const Vec3f wo = spherical_direction(theta * kDegree, 0.9);
      TestRng rng(seed++);
      Vec3d sum(0.0), sum2(0.0);
      for (long s = 0; s < kSamples; ++s) {
        const float u_lobe = rng.next_float();
        const Vec2f u{rng.next_float(), rng.next_float()};
        const BsdfSample bs = bsdf.sample(wo, u_lobe, u);
        if (!(bs.pdf > 0.f)) continue;
        const Vec3f weight = bsdf.eval<float>(wo, bs.wi) / bs.pdf;
        for (int c = 0; c < 3; ++c) sum[c] += weight[c], sum2[c] += double(weight[c]) * weight[c];
      }
      for (int c = 0; c < 3; ++c) {
        const double quadrature =
            integrate_over_domain(upper_hemisphere(), [&](const Vec3f& wi) { return bsdf.eval<float>(wo, wi)[c]; });
        const double mean = sum[c] / double(kSamples);
        const double sigma = std::sqrt(std::max(0.0, sum2[c] / double(kSamples) - mean * mean) / double(kSamples));
        INFO(bsdf.describe(wo) << " channel " << c << ": sampled " << mean << " ± " << sigma << ", quadrature "
                               << quadrature);
        CHECK(std::abs(mean - quadrature) <= 5.0 * sigma + 1e-3 * quadrature);
      }
    }
}

TEST_CASE("GGX normals are drawn to float precision at small roughness", "[bsdf][microfacet]") {
  // tan²θm = α² u / (1 − u) exactly (in distribution, to float rounding), however small α: sin θm
  // was sqrt(1 − cos²θm), which cancels in float, so at the α clamp (1e-3) the normals' tan²θm were
  // off by 22% on average and the lobe's core (tan²θm < α²/4, probability 0.2) drew 29% of them;
  // a chi-square test cannot see a lobe that narrow.
  for (float alpha : {kMinAlpha, 3e-3f, 1e-2f, 0.3f}) {
    double worst = 0;
    int core = 0;
    const int n = 20000;
    for (int i = 0; i < n; ++i) {
      const Vec2f u{(float(i) + 0.5f) / float(n), 0.37f};
      const Vec3f m = ggx_sample_normal(alpha, u);
      const double want = double(alpha) * alpha * u.x / (1.0 - u.x);
      const double got = (double(m.x) * m.x + double(m.y) * m.y) / (double(m.z) * m.z);
      worst = std::max(worst, std::abs(got / want - 1));
      core += got < 0.25 * double(alpha) * alpha;
    }
    INFO("alpha " << alpha << ": worst relative error of tan^2 " << worst << ", core fraction " << double(core) / n);
    CHECK(worst < 2e-6);
    CHECK(std::abs(double(core) / n - 0.2) < 1e-3);
  }
}
