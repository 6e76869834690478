// Derivative shaders of the BSDFs against central differences of their own eval<double>, at
// random directions (upper hemisphere, down to 0.1° above the horizon; half of the wi inside the
// specular lobe) and random parameters (roughness in [0.02, 1], every tenth trial one of the
// loader's range's edges: 0 and 5e-4 under the α clamp of 1e-3, where eval is flat, 0.005, 2
// and 4; metallic 0, 1 or in (0, 1)).
#include <catch2/catch.hpp>

#include <array>
#include <cstdio>
#include <functional>
#include <sstream>
#include <vector>

#include "kernels/bsdf/diffuse.h"
#include "kernels/bsdf/metallic_roughness.h"
#include "kernels/bsdf/roughconductor.h"
#include "kernels/bsdf/roughplastic.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

constexpr int kTrials = 3000;
constexpr double kRelTolerance = 1e-3, kAbsFloor = 1e-6;

// Up to five scalar inputs: an RGB colour (albedo, specular or base colour), except for diffuse
// the roughness, and for metallic_roughness the metallic weight.
using Inputs = std::array<double, 5>;

struct Trial {
  Inputs inputs{};
  float ior;
  Vec3f wo, wi, adjoint;
  std::string describe(const char* bsdf) const {
    std::ostringstream o;
    o.precision(9);
    o << bsdf << " colour (" << inputs[0] << ", " << inputs[1] << ", " << inputs[2] << ") roughness " << inputs[3]
      << " metallic " << inputs[4] << " ior " << ior << " wo (" << wo.x << ", " << wo.y << ", " << wo.z << ") wi ("
      << wi.x << ", " << wi.y << ", " << wi.z << ") adjoint (" << adjoint.x << ", " << adjoint.y << ", " << adjoint.z
      << ")";
    return o.str();
  }
};

Trial random_trial(TestRng& rng, int trial) {
  Trial t;
  for (int c = 0; c < 3; ++c) t.inputs[size_t(c)] = double(float(rng.uniform(0.0, 1.0)));
  t.inputs[3] = double(float(rng.uniform(0.02, 1.0)));
  // A derivative seeded above the clamp (max(roughness, 1e-3)) survived the random range.
  constexpr float kEdges[] = {0.f, 5e-4f, 5e-3f, 2.f, 4.f};
  if (trial % 10 == 9) t.inputs[3] = double(kEdges[size_t(trial / 10) % 5]);
  t.ior = float(rng.uniform(1.1, 2.5));
  t.wo = rng.upper_hemisphere(std::cos(89.9 * M_PI / 180.0));
  t.wi = rng.upper_hemisphere(std::cos(89.9 * M_PI / 180.0));
  // Half of the trials sit inside the specular lobe, where D and its α-derivative are steepest
  // and float rounding matters most.
  if (rng.next_float() < 0.5f) {
    const Vec3f wi = reflect(t.wo, ggx_sample_normal(float(t.inputs[3]), {rng.next_float(), rng.next_float()}));
    if (wi.z > 1.7e-3f) t.wi = normalize(wi);
  }
  t.adjoint = Vec3f(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
  return t;
}

// Checks `backprop` (float) against finite differences of `eval` (double) for every input.
void check_backprop(const char* name, int parameter_count, const std::function<Inputs(const Trial&)>& backprop,
                    const std::function<Spectrum<double>(const Trial&, const Inputs&)>& eval, uint64_t seed) {
  TestRng rng(seed);
  const std::vector<std::string> names{"colour.r", "colour.g", "colour.b", "roughness", "metallic"};
  double worst = 0.0;
  std::string worst_trial;
  for (int trial = 0; trial < kTrials; ++trial) {
    Trial t = random_trial(rng, trial);
    // The metallic weight, drawn only when it is an input (the other BSDFs keep their trials):
    // every fifth trial the pure dielectric, every fifth the pure metal, else a blend.
    if (parameter_count == 5)
      t.inputs[4] = trial % 5 == 0 ? 0.0 : trial % 5 == 1 ? 1.0 : double(float(rng.uniform(0.0, 1.0)));
    const Inputs analytic = backprop(t);
    std::vector<double> got, expected;
    for (int k = 0; k < parameter_count; ++k) {
      got.push_back(analytic[size_t(k)]);
      auto f = [&](double x) {
        Inputs perturbed = t.inputs;
        perturbed[size_t(k)] = x;
        return adjoint_dot(t.adjoint, eval(t, perturbed));
      };
      // Every BSDF here is linear in its colour, so a wide step is exact for it; the default one
      // (1e-4 of the colour) lost the colour's term to double rounding where a specular peak under
      // the α clamp makes eval ~1e6 (a roughplastic at roughness 0: 0.2% off).
      const double h = 1e-2;
      expected.push_back(k < 3 ? (f(t.inputs[size_t(k)] + h) - f(t.inputs[size_t(k)] - h)) / (2 * h)
                               : central_difference(f, t.inputs[size_t(k)]));
    }
    const GradientComparison c = compare_gradients(got, expected, names, kRelTolerance, kAbsFloor);
    if (c.worst_ratio > worst) {
      worst = c.worst_ratio;
      worst_trial = t.describe(name) + "\n" + c.report;
    }
    INFO(t.describe(name) << "\n" << c.report);
    CHECK(c.ok);
  }
  std::printf("%s backprop: worst error / allowed = %.3g over %d trials, at %s", name, worst, kTrials,
              worst_trial.c_str());
}

}  // namespace

TEST_CASE("diffuse backprop matches finite differences of its eval", "[bsdf][backprop]") {
  check_backprop(
      "diffuse", 3,
      [](const Trial& t) {
        const DiffuseParams<float> p{Vec3f(float(t.inputs[0]), float(t.inputs[1]), float(t.inputs[2]))};
        const DiffuseParams<float> g = diffuse_backprop(p, t.wo, t.wi, t.adjoint);
        return Inputs{g.albedo.x, g.albedo.y, g.albedo.z, 0.0};
      },
      [](const Trial& t, const Inputs& x) {
        return diffuse_eval(DiffuseParams<double>{Spectrum<double>(x[0], x[1], x[2])}, t.wo, t.wi);
      },
      1);
}

TEST_CASE("roughconductor backprop matches finite differences of its eval", "[bsdf][backprop]") {
  check_backprop(
      "roughconductor", 4,
      [](const Trial& t) {
        const RoughConductorParams<float> p{Vec3f(float(t.inputs[0]), float(t.inputs[1]), float(t.inputs[2])),
                                            float(t.inputs[3])};
        const RoughConductorParams<float> g = roughconductor_backprop(p, t.wo, t.wi, t.adjoint);
        return Inputs{g.specular.x, g.specular.y, g.specular.z, g.roughness};
      },
      [](const Trial& t, const Inputs& x) {
        return roughconductor_eval(RoughConductorParams<double>{Spectrum<double>(x[0], x[1], x[2]), x[3]}, t.wo, t.wi);
      },
      2);
}

TEST_CASE("roughplastic backprop matches finite differences of its eval", "[bsdf][backprop]") {
  check_backprop(
      "roughplastic", 4,
      [](const Trial& t) {
        const RoughPlasticParams<float> p{Vec3f(float(t.inputs[0]), float(t.inputs[1]), float(t.inputs[2])),
                                          float(t.inputs[3]), t.ior};
        const RoughPlasticParams<float> g = roughplastic_backprop(p, t.wo, t.wi, t.adjoint);
        return Inputs{g.albedo.x, g.albedo.y, g.albedo.z, g.roughness};
      },
      [](const Trial& t, const Inputs& x) {
        return roughplastic_eval(RoughPlasticParams<double>{Spectrum<double>(x[0], x[1], x[2]), x[3], t.ior}, t.wo,
                                 t.wi);
      },
      3);
}

TEST_CASE("metallic_roughness backprop matches finite differences of its eval", "[bsdf][backprop]") {
  check_backprop(
      "metallic_roughness", 5,
      [](const Trial& t) {
        const MetallicRoughnessParams<float> p{Vec3f(float(t.inputs[0]), float(t.inputs[1]), float(t.inputs[2])),
                                               float(t.inputs[3]), float(t.inputs[4])};
        const MetallicRoughnessParams<float> g = metallic_roughness_backprop(p, t.wo, t.wi, t.adjoint);
        return Inputs{g.base_color.x, g.base_color.y, g.base_color.z, g.roughness, g.metallic};
      },
      [](const Trial& t, const Inputs& x) {
        return metallic_roughness_eval(MetallicRoughnessParams<double>{Spectrum<double>(x[0], x[1], x[2]), x[3], x[4]},
                                       t.wo, t.wi);
      },
      4);
}

// Below the horizon eval is zero, so the gradient must be too (no stray contributions from
// paths that arrive at the back of a one-sided surface).
TEST_CASE("BSDF backprop is zero below the horizon", "[bsdf][backprop]") {
  const Vec3f up(0.f, 0.f, 1.f), below(0.6f, 0.f, -0.8f), adjoint(1.f, -2.f, 0.5f);
  for (const auto& [wo, wi] : {std::pair{up, below}, std::pair{below, up}}) {
    const DiffuseParams<float> d = diffuse_backprop({Vec3f(0.5f)}, wo, wi, adjoint);
    CHECK(is_zero(d.albedo));
    const RoughConductorParams<float> c = roughconductor_backprop({Vec3f(0.5f), 0.3f}, wo, wi, adjoint);
    CHECK(is_zero(c.specular));
    CHECK(c.roughness == 0.f);
    const RoughPlasticParams<float> p = roughplastic_backprop({Vec3f(0.5f), 0.3f, 1.5f}, wo, wi, adjoint);
    CHECK(is_zero(p.albedo));
    CHECK(p.roughness == 0.f);
    const MetallicRoughnessParams<float> b = metallic_roughness_backprop({Vec3f(0.5f), 0.3f, 0.4f}, wo, wi, adjoint);
    CHECK(is_zero(b.base_color));
    CHECK(b.roughness == 0.f);
    CHECK(b.metallic == 0.f);
  }
}
