// Physical properties every BSDF must have: Helmholtz reciprocity of f = eval / cos θi, and
// energy conservation — a white BSDF reflects at most what arrives (the white furnace:
// ∫ eval(wo, wi) dwi ≤ 1 for every wo, since eval includes cos θi).
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>
#include <vector>

#include "kernels/bsdf/metallic_roughness.h"
#include "tests/kernels/bsdf/bsdf_under_test.h"
#include "tests/kernels/spherical_quadrature.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

constexpr double kDegree = M_PI / 180.0;

BsdfUnderTest random_bsdf(BsdfKind kind, TestRng& rng) {
  BsdfUnderTest b{kind};
  b.color = Vec3f(float(rng.uniform(0.05, 1.0)), float(rng.uniform(0.05, 1.0)), float(rng.uniform(0.05, 1.0)));
  b.roughness = float(rng.uniform(0.02, 1.0));
  b.ior = float(rng.uniform(1.2, 2.0));
  // Drawn only for the blend, so the other BSDFs see the same random parameters as before.
  if (kind == BsdfKind::MetallicRoughness) b.metallic = float(rng.uniform(0.0, 1.0));
  return b;
}

// Directional albedo ∫ eval(wo, wi) dwi of the first channel.
double directional_albedo(const BsdfUnderTest& bsdf, const Vec3f& wo) {
  return integrate_over_domain(upper_hemisphere(), [&](const Vec3f& wi) { return bsdf.eval<float>(wo, wi).x; });
}

// White-furnace table over roughness and incidence; returns the largest albedo.
double white_furnace(BsdfKind kind, const std::vector<float>& roughnesses, float metallic = 0.5f) {
  const std::vector<double> incidence{0, 30, 60, 75, 85, 89};
  double worst = 0.0;
  std::printf("white furnace, %s: directional albedo with colour 1", BsdfUnderTest{kind}.name().c_str());
  if (kind == BsdfKind::MetallicRoughness) std::printf(", metallic %.2f", metallic);
  std::printf("\n  alpha \\ theta_o:");
  for (double t : incidence) std::printf(" %7.1f", t);
  std::printf("\n");
  for (float alpha : roughnesses) {
    std::printf("  %15.3f:", alpha);
    for (double theta : incidence) {
      const BsdfUnderTest bsdf{kind, {1.f, 1.f, 1.f}, alpha, 1.5f, metallic};
      const Vec3f wo = spherical_direction(theta * kDegree, 0.4);
      const double albedo = directional_albedo(bsdf, wo);
      std::printf(" %7.4f", albedo);
      worst = std::max(worst, albedo);
      INFO(bsdf.describe(wo) << ": directional albedo " << albedo);
      CHECK(albedo <= 1.0 + 1e-3);
      CHECK(albedo >= 0.0);
    }
    std::printf("\n");
  }
  std::printf("  max %.6f\n", worst);
  return worst;
}

}  // namespace

TEST_CASE("BSDFs are reciprocal: eval(wo, wi)/cos θi = eval(wi, wo)/cos θo", "[bsdf][reciprocity]") {
  TestRng rng(11);
  for (BsdfKind kind :
       {BsdfKind::Diffuse, BsdfKind::RoughConductor, BsdfKind::RoughPlastic, BsdfKind::MetallicRoughness}) {
    double worst = 0.0;
    for (int trial = 0; trial < 4000; ++trial) {
      const BsdfUnderTest bsdf = random_bsdf(kind, rng);
      const Vec3f wo = rng.upper_hemisphere(1e-2), wi = rng.upper_hemisphere(1e-2);
      const Vec3f forward = bsdf.eval<float>(wo, wi) / wi.z, backward = bsdf.eval<float>(wi, wo) / wo.z;
      for (int c = 0; c < 3; ++c) {
        const double scale = std::max(std::abs(forward[c]), std::abs(backward[c]));
        const double error = std::abs(forward[c] - backward[c]) / std::max(scale, 1e-30);
        worst = std::max(worst, error);
        INFO(bsdf.describe(wo) << " wi (" << wi.x << ", " << wi.y << ", " << wi.z << ") channel " << c << ": "
                               << forward[c] << " vs " << backward[c]);
        CHECK(error <= 1e-4);
      }
    }
    std::printf("reciprocity, %s: max relative difference %.3g\n", BsdfUnderTest{kind}.name().c_str(), worst);
  }
}

TEST_CASE("white furnace: diffuse reflects exactly what arrives", "[bsdf][energy]") {
  for (double theta : {0.0, 45.0, 89.0}) {
    const Vec3f wo = spherical_direction(theta * kDegree, 1.0);
    const double albedo = directional_albedo(BsdfUnderTest{BsdfKind::Diffuse, {1.f, 1.f, 1.f}}, wo);
    INFO("theta_o " << theta << ": albedo " << albedo);
    CHECK(albedo == Approx(1.0).epsilon(1e-4));
  }
}

// A white conductor (F = 1) loses energy only to masking/shadowing and to reflections below
// the horizon; it must never exceed 1.
// [expectation]: not under the sanitizers (quadrature: eval again and again); the reciprocity case
// runs every BSDF's eval there.
TEST_CASE("white furnace: roughconductor conserves energy", "[bsdf][energy][expectation]") {
  white_furnace(BsdfKind::RoughConductor, {0.02f, 0.05f, 0.2f, 0.5f, 1.0f});
}

// A white plastic: coat reflection plus the base seen through the coat (1 − Fr twice).
// [expectation]: not under the sanitizers (quadrature: eval again and again); the reciprocity case
// runs every BSDF's eval there.
TEST_CASE("white furnace: roughplastic conserves energy", "[bsdf][energy][expectation]") {
  white_furnace(BsdfKind::RoughPlastic, {0.02f, 0.05f, 0.2f, 0.5f, 1.0f});
}

// A white blend mixes two lobes that each conserve energy, so it does too.
// [expectation]: not under the sanitizers (quadrature: eval again and again); the reciprocity case
// runs every BSDF's eval there.
TEST_CASE("white furnace: metallic_roughness conserves energy", "[bsdf][energy][expectation]") {
  for (float metallic : {0.3f, 0.7f}) white_furnace(BsdfKind::MetallicRoughness, {0.02f, 0.2f, 1.0f}, metallic);
}

// The blend is glTF's mix(dielectric, metal, metallic) of backlight's own lobes, channel by
// channel, and its pdf the same mixture of theirs; at m = 0 and 1 it is exactly one lobe.
TEST_CASE("metallic_roughness is the metallic-weighted blend of roughplastic and roughconductor", "[bsdf]") {
  TestRng rng(17);
  for (int trial = 0; trial < 2000; ++trial) {
    const float metallic = trial % 10 == 0 ? 0.f : trial % 10 == 1 ? 1.f : float(rng.uniform(0.0, 1.0));
    const Vec3f base(float(rng.uniform(0.0, 1.0)), float(rng.uniform(0.0, 1.0)), float(rng.uniform(0.0, 1.0)));
    const float alpha = float(rng.uniform(0.02, 1.0));
    const Vec3f wo = rng.upper_hemisphere(1e-2), wi = rng.upper_hemisphere(1e-2);
    const MetallicRoughnessParams<double> p{Spectrum<double>(base), double(alpha), double(metallic)};
    const RoughPlasticParams<double> plastic{Spectrum<double>(base), double(alpha), 1.5f};
    const RoughConductorParams<double> conductor{Spectrum<double>(base), double(alpha)};
    const Vec3d blend = metallic_roughness_eval(p, wo, wi);
    const Vec3d expected = roughplastic_eval(plastic, wo, wi) * (1.0 - metallic) +
                           roughconductor_eval(conductor, wo, wi) * double(metallic);
    INFO("metallic " << metallic << " alpha " << alpha << " wo (" << wo.x << ", " << wo.y << ", " << wo.z << ") wi ("
                     << wi.x << ", " << wi.y << ", " << wi.z << ")");
    for (int c = 0; c < 3; ++c) CHECK(blend[c] == Approx(expected[c]).epsilon(1e-12).margin(1e-300));
    const MetallicRoughnessParams<float> pf{base, alpha, metallic};
    const double pdf = metallic_roughness_pdf(pf, wo, wi);
    const double expected_pdf = double(metallic) * roughconductor_pdf({base, alpha}, wo, wi) +
                                (1.0 - metallic) * roughplastic_pdf({base, alpha, 1.5f}, wo, wi);
    CHECK(pdf == Approx(expected_pdf).epsilon(1e-6));
  }
}
