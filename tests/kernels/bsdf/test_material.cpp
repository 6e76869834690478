// Materials apply the chain rule from a BSDF's derivative shader into texture gradients. Checked
// against central differences of Material::eval<double> with respect to every element of every
// parameter it reads: bitmaps (repeat and clamp), constants of size 1 and 3, and roughness read
// from one- and three-channel textures (the scalar read takes channel 0), metallic likewise, and
// a vertex-colour tint on the colour texture (its texels then receive the adjoint times the tint). The same shaders are
// also checked against the taped mode's oracle: the partials a reverse sweep over the tape of
// Material::eval<Var> assigns to every parameter element.
#include <catch2/catch.hpp>

#include <sstream>
#include <string>
#include <vector>

#include "engine/core/tape.h"
#include "kernels/bsdf/material.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

constexpr double kRelTolerance = 1e-3, kAbsFloor = 1e-6;

int add_param(ParamStore& store, const std::string& name, std::vector<int> shape, double lo, double hi, TestRng& rng) {
  return store.add(random_param(name, std::move(shape), lo, hi, rng));
}

struct MaterialCase {
  std::string label;
  BsdfType type;
  std::vector<int> colour_shape, roughness_shape;  // [C] = constant, [H, W, C] = bitmap
  Wrap wrap;
  std::vector<int> metallic_shape = {};  // metallic_roughness
  Vec3f tint = Vec3f(1.f);               // vertex colour multiplying the colour texture
};

void check_material(const MaterialCase& mc, uint64_t seed) {
  TestRng rng(seed);
  ParamStore store;
  Material m;
  m.name = mc.label;
  m.type = mc.type;
  m.ior = 1.6f;
  TextureSlot colour{add_param(store, "m.colour", mc.colour_shape, 0.05, 1.0, rng), mc.colour_shape.size() == 3,
                     mc.wrap};
  if (mc.type == BsdfType::RoughConductor)
    m.specular = colour;
  else
    m.albedo = colour;
  if (mc.type != BsdfType::Diffuse)
    m.roughness = {add_param(store, "m.roughness", mc.roughness_shape, 0.05, 0.8, rng), mc.roughness_shape.size() == 3,
                   mc.wrap};
  if (mc.type == BsdfType::MetallicRoughness)
    m.metallic = {add_param(store, "m.metallic", mc.metallic_shape, 0.05, 0.95, rng), mc.metallic_shape.size() == 3,
                  mc.wrap};
  store.require_grad({});
  const Vec3f tint = mc.tint;
  Tape tape;  // one recording per (trial, parameter), its chunks reused

  for (int trial = 0; trial < 40; ++trial) {
    const Vec2f uv{float(rng.uniform(-0.5, 1.5)), float(rng.uniform(-0.5, 1.5))};
    const Vec3f wo = rng.upper_hemisphere(0.02),
                adjoint(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
    // Half the trials near the specular direction, where the roughness gradient is largest.
    Vec3f wi = rng.upper_hemisphere(0.02);
    if (trial % 2 == 1) wi = normalize(Vec3f(-wo.x, -wo.y, wo.z) + rng.upper_hemisphere(0.0) * 0.1f);
    if (wi.z <= 0.02f) wi = rng.upper_hemisphere(0.02);
    REQUIRE(m.wants_grad(GradientAccumulator(&store)));

    for (int handle = 0; handle < int(store.count()); ++handle) {
      const std::vector<double> analytic = gradient_through_sink(
          store, handle, [&](GradientAccumulator& g) { m.backprop(store, uv, wo, wi, adjoint, g, tint); });
      std::vector<double> numeric;
      Param& p = store[handle];
      for (size_t i = 0; i < p.size(); ++i)
        numeric.push_back(central_difference_of_param(
            p, i, [&] { return adjoint_dot(adjoint, m.eval<double>(store, uv, wo, wi, tint)); }));
      const GradientComparison c = compare_gradients(analytic, numeric, {}, kRelTolerance, kAbsFloor);
      // Tape oracle: record eval on the tape scalar, sweep back from ⟨adjoint, f⟩.
      tape.clear();
      current_tape = &tape;
      const Spectrum<Var> f = m.eval<Var>(store, uv, wo, wi, tint);
      current_tape = nullptr;
      std::vector<float> seeds(tape.size(), 0.f);
      for (int ch = 0; ch < 3; ++ch)
        if (f[ch].active()) seeds[f[ch].index] += adjoint[ch];
      std::vector<double> taped(p.size(), 0.0);
      reverse_sweep(tape, seeds, [&](uint32_t flat, float g) {
        if (flat >= p.tape_offset && flat < p.tape_offset + p.size()) taped[flat - p.tape_offset] += g;
      });
      // Both sides are float arithmetic on the same eval; only rounding may differ.
      const GradientComparison t = compare_gradients(analytic, taped, {}, 1e-4, 1e-7);
      INFO("tape oracle:\n" << t.report);
      CHECK(t.ok);
      std::ostringstream o;
      o.precision(9);
      o << mc.label << ", parameter " << p.name << " (" << store.shape_string(handle) << "), uv (" << uv.x << ", "
        << uv.y << ") wo (" << wo.x << ", " << wo.y << ", " << wo.z << ") wi (" << wi.x << ", " << wi.y << ", " << wi.z
        << ") adjoint (" << adjoint.x << ", " << adjoint.y << ", " << adjoint.z << ")\n"
        << c.report;
      INFO(o.str());
      CHECK(c.ok);
    }
  }
}

}  // namespace

TEST_CASE("material backprop applies the chain rule into texture gradients", "[bsdf][material][backprop]") {
  const std::vector<MaterialCase> cases{
      {"diffuse, bitmap albedo", BsdfType::Diffuse, {4, 3, 3}, {}, Wrap::Repeat},
      {"diffuse, grey constant albedo", BsdfType::Diffuse, {1}, {}, Wrap::Repeat},
      {"roughconductor, bitmap specular, grey bitmap roughness",
       BsdfType::RoughConductor,
       {3, 5, 3},
       {4, 2, 1},
       Wrap::Clamp},
      {"roughconductor, RGB constant specular, RGB bitmap roughness",
       BsdfType::RoughConductor,
       {3},
       {3, 3, 3},
       Wrap::Repeat},
      {"roughconductor, bitmap specular, constant roughness", BsdfType::RoughConductor, {2, 2, 3}, {1}, Wrap::Repeat},
      {"roughplastic, bitmap albedo, RGB constant roughness", BsdfType::RoughPlastic, {3, 4, 3}, {3}, Wrap::Clamp},
      {"roughplastic, grey bitmap albedo, grey bitmap roughness",
       BsdfType::RoughPlastic,
       {5, 3, 1},
       {2, 3, 1},
       Wrap::Repeat},
      {"metallic_roughness, bitmap base colour, constant roughness, grey bitmap metallic",
       BsdfType::MetallicRoughness,
       {3, 4, 3},
       {1},
       Wrap::Repeat,
       {2, 3, 1}},
      {"metallic_roughness, RGB constant base colour, bitmap roughness, RGB bitmap metallic",
       BsdfType::MetallicRoughness,
       {3},
       {2, 2, 1},
       Wrap::Clamp,
       {3, 2, 3}},
      {"diffuse, bitmap albedo, vertex colour", BsdfType::Diffuse, {4, 3, 3}, {}, Wrap::Repeat, {}, {0.9f, 0.2f, 0.5f}},
      {"roughconductor, bitmap specular, vertex colour",
       BsdfType::RoughConductor,
       {3, 3, 3},
       {1},
       Wrap::Clamp,
       {},
       {0.3f, 1.f, 0.6f}},
      {"roughplastic, grey constant albedo, vertex colour",
       BsdfType::RoughPlastic,
       {1},
       {1},
       Wrap::Repeat,
       {},
       {0.7f, 0.1f, 0.4f}},
      {"metallic_roughness, bitmap base colour, vertex colour",
       BsdfType::MetallicRoughness,
       {2, 3, 3},
       {1},
       Wrap::Repeat,
       {1},
       {0.2f, 0.8f, 1.f}},
  };
  uint64_t seed = 41;
  for (const MaterialCase& mc : cases) check_material(mc, seed++);
}

TEST_CASE("material sample and pdf agree with the BSDF they evaluate", "[bsdf][material]") {
  TestRng rng(43);
  ParamStore store;
  Material m;
  m.type = BsdfType::RoughPlastic;
  m.albedo = {add_param(store, "m.albedo", {3}, 0.2, 0.9, rng), false, Wrap::Repeat};
  m.roughness = {add_param(store, "m.roughness", {2, 2, 1}, 0.1, 0.5, rng), true, Wrap::Repeat};
  for (int i = 0; i < 200; ++i) {
    const Vec2f uv{float(rng.uniform(0, 1)), float(rng.uniform(0, 1))};
    const Vec3f wo = rng.upper_hemisphere(0.05);
    const BsdfSample s = m.sample(store, uv, wo, rng.next_float(), {rng.next_float(), rng.next_float()});
    if (s.pdf <= 0.f) continue;
    INFO("uv (" << uv.x << ", " << uv.y << ") wo (" << wo.x << ", " << wo.y << ", " << wo.z << ")");
    CHECK(s.pdf == Approx(m.pdf(store, uv, wo, s.wi)).epsilon(1e-4));
    const RoughPlasticParams<float> direct{m.albedo.eval<float>(store, uv), m.roughness.eval_scalar<float>(store, uv),
                                           m.ior};
    CHECK(m.eval<float>(store, uv, wo, s.wi).x == Approx(roughplastic_eval(direct, wo, s.wi).x).epsilon(1e-6));
  }
}

TEST_CASE("a metallic_roughness material samples and evaluates its kernel with the tinted base colour",
          "[bsdf][material]") {
  TestRng rng(47);
  ParamStore store;
  Material m;
  m.type = BsdfType::MetallicRoughness;
  m.albedo = {add_param(store, "m.base_color", {2, 2, 3}, 0.2, 0.9, rng), true, Wrap::Repeat};
  m.roughness = {add_param(store, "m.roughness", {1}, 0.1, 0.5, rng), false, Wrap::Repeat};
  m.metallic = {add_param(store, "m.metallic", {2, 2, 1}, 0.2, 0.8, rng), true, Wrap::Repeat};
  const Vec3f tint(0.5f, 1.f, 0.25f);
  int sampled = 0;
  for (int i = 0; i < 200; ++i) {
    const Vec2f uv{float(rng.uniform(0, 1)), float(rng.uniform(0, 1))};
    const Vec3f wo = rng.upper_hemisphere(0.05);
    const BsdfValue<float> v = m.at<float>(store, uv, tint);
    const BsdfSample s = v.sample(wo, rng.next_float(), {rng.next_float(), rng.next_float()});
    if (s.pdf <= 0.f) continue;
    ++sampled;
    INFO("uv (" << uv.x << ", " << uv.y << ") wo (" << wo.x << ", " << wo.y << ", " << wo.z << ")");
    const MetallicRoughnessParams<float> direct{tinted(m.albedo.eval<float>(store, uv), tint),
                                                m.roughness.eval_scalar<float>(store, uv),
                                                m.metallic.eval_scalar<float>(store, uv)};
    CHECK(s.pdf == Approx(metallic_roughness_pdf(direct, wo, s.wi)).epsilon(1e-6));
    const Vec3f f = m.eval<float>(store, uv, wo, s.wi, tint), expected = metallic_roughness_eval(direct, wo, s.wi);
    for (int c = 0; c < 3; ++c) CHECK(f[c] == expected[c]);
  }
  CHECK(sampled > 150);
}
