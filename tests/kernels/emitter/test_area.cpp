// Area emitters: radiance is read from a texture (constant or bitmap) on the side the normal
// faces; its derivative shader against central differences of eval<double>, and the solid-angle
// pdf of area sampling.
#include <catch2/catch.hpp>

#include <vector>

#include "kernels/emitter/area.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

AreaEmitter make_emitter(ParamStore& store, std::vector<int> shape, TestRng& rng) {
  Param p;
  p.name = "light.radiance";
  p.shape = shape;
  size_t size = 1;
  for (int s : shape) size *= size_t(s);
  for (size_t i = 0; i < size; ++i) p.value.push_back(float(rng.uniform(0.5, 20.0)));
  AreaEmitter e;
  e.radiance = {store.add(std::move(p)), shape.size() == 3, Wrap::Repeat};
  e.total_area = 2.5f;
  store.require_grad({});
  return e;
}

}  // namespace

TEST_CASE("area emitter backprop matches finite differences of eval", "[emitter][area][backprop]") {
  TestRng rng(61);
  for (const std::vector<int>& shape :
       {std::vector<int>{3}, std::vector<int>{1}, std::vector<int>{4, 6, 3}, std::vector<int>{3, 2, 1}}) {
    ParamStore store;
    const AreaEmitter e = make_emitter(store, shape, rng);
    for (int trial = 0; trial < 20; ++trial) {
      const Vec2f uv{float(rng.uniform(-0.5, 1.5)), float(rng.uniform(-0.5, 1.5))};
      const float cos_viewer = float(rng.uniform(0.01, 1.0));
      const Vec3f adjoint(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
      const std::vector<double> analytic = gradient_through_sink(
          store, e.radiance.param, [&](GradientAccumulator& g) { e.backprop(store, uv, cos_viewer, adjoint, g); });
      std::vector<double> numeric;
      Param& p = store[e.radiance.param];
      for (size_t i = 0; i < p.size(); ++i)
        numeric.push_back(central_difference_of_param(
            p, i, [&] { return adjoint_dot(adjoint, e.eval<double>(store, uv, cos_viewer)); }));
      const GradientComparison c = compare_gradients(analytic, numeric, {}, 1e-5, 1e-7);
      INFO("radiance " << store.shape_string(e.radiance.param) << " uv (" << uv.x << ", " << uv.y << ") cos "
                       << cos_viewer << "\n"
                       << c.report);
      CHECK(c.ok);
    }
  }
}

TEST_CASE("area emitters emit only on the side their normal faces", "[emitter][area]") {
  TestRng rng(67);
  ParamStore store;
  const AreaEmitter e = make_emitter(store, {3}, rng);
  CHECK(is_zero(e.eval<float>(store, {0.5f, 0.5f}, 0.f)));
  CHECK(is_zero(e.eval<float>(store, {0.5f, 0.5f}, -0.3f)));
  CHECK(e.eval<float>(store, {0.5f, 0.5f}, 0.3f).y == store[e.radiance.param].value[1]);
  // backprop mirrors eval: nothing flows into the radiance from the back side.
  for (float cos_viewer : {0.f, -0.3f}) {
    const std::vector<double> g = gradient_through_sink(store, e.radiance.param, [&](GradientAccumulator& a) {
      e.backprop(store, {0.5f, 0.5f}, cos_viewer, Vec3f(1.f), a);
    });
    for (double x : g) CHECK(x == 0.0);
  }
}

TEST_CASE("area emitter solid-angle pdf is d² / (A cos θ)", "[emitter][area]") {
  TestRng rng(71);
  ParamStore store;
  const AreaEmitter e = make_emitter(store, {3}, rng);
  CHECK(e.pdf(2.f, 0.5f) == Approx(4.f / (0.5f * 2.5f)));
  CHECK(e.pdf(2.f, 0.f) == 0.f);
  CHECK(e.pdf(2.f, -0.5f) == 0.f);
}
