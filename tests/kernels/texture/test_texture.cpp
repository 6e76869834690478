// Textures: bilinear lookup conventions (texel centres, repeat, clamp) and the derivative shaders
// — bitmap backprop, the scalar (first-channel) reads and constants — against central
// differences of eval<double> with respect to every texel.
#include <catch2/catch.hpp>

#include <functional>
#include <sstream>
#include <string>
#include <vector>

#include "kernels/texture/texture.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

// Texture eval is linear in the texels, so finite differences are exact up to rounding and the
// float shader can be held to a tight tolerance.
constexpr double kRelTolerance = 1e-5, kAbsFloor = 1e-7;

Param random_param(const std::string& name, std::vector<int> shape, TestRng& rng) {
  Param p;
  p.name = name;
  p.shape = std::move(shape);
  size_t size = 1;
  for (int s : p.shape) size *= size_t(s);
  for (size_t i = 0; i < size; ++i) p.value.push_back(float(rng.uniform(0.1, 1.0)));
  return p;
}

// Lookups at random places, at texel centres, on edges and corners, and outside [0, 1].
std::vector<Vec2f> lookup_points(int width, int height, TestRng& rng) {
  std::vector<Vec2f> uvs{{0.f, 0.f},      {1.f, 1.f},        {0.f, 1.f},      {1.f, 0.f},
                         {0.5f, 0.f},     {0.f, 0.5f},       {1.f, 0.3f},     {0.7f, 1.f},
                         {-0.001f, 0.5f}, {1.0001f, 0.999f}, {-1.f, -1.f},    {2.3f, -0.7f},
                         {-3.62f, 5.11f}, {0.999f, 0.001f},  {-0.25f, 1.25f}, {1.5f, 1.5f}};
  // Exactly at texel centres and halfway between them (bilinear weights 1 and ½).
  uvs.push_back({0.5f / float(width), 0.5f / float(height)});
  uvs.push_back({(float(width) - 0.5f) / float(width), (float(height) - 0.5f) / float(height)});
  uvs.push_back({1.f / float(width), 2.f / float(height)});
  for (int i = 0; i < 40; ++i) uvs.push_back({float(rng.uniform(-2.0, 3.0)), float(rng.uniform(-2.0, 3.0))});
  return uvs;
}

std::string describe(const Param& p, Wrap wrap, Vec2f uv, const Vec3f& adjoint) {
  std::ostringstream o;
  o.precision(9);
  o << p.name << " shape " << p.height() << "x" << p.width() << "x" << p.channels() << " wrap "
    << (wrap == Wrap::Repeat  ? "repeat"
        : wrap == Wrap::Clamp ? "clamp"
                              : "mirror")
    << " uv (" << uv.x << ", " << uv.y << ") adjoint (" << adjoint.x << ", " << adjoint.y << ", " << adjoint.z << ")";
  return o.str();
}

// Compares a texture's backprop with finite differences of ⟨adjoint, eval<double>⟩ per element.
void check_texture_gradient(ParamStore& store, int handle, const std::string& what,
                            const std::function<double()>& eval_dot_adjoint,
                            const std::function<void(GradientAccumulator&)>& backprop) {
  const std::vector<double> analytic = gradient_through_sink(store, handle, backprop);
  std::vector<double> numeric;
  Param& p = store[handle];
  for (size_t i = 0; i < p.size(); ++i) numeric.push_back(central_difference_of_param(p, i, eval_dot_adjoint));
  const GradientComparison c = compare_gradients(analytic, numeric, {}, kRelTolerance, kAbsFloor);
  INFO(what << "\n" << c.report);
  CHECK(c.ok);
}

struct BitmapCase {
  std::vector<int> shape;
  Wrap wrap;
};

// The RGB read (eval/backprop) and the scalar read of channel 0 (eval_scalar/backprop_scalar,
// as roughness uses it), both against central differences.
void check_rgb_and_scalar_reads(ParamStore& store, int h, const TextureSlot& slot, Vec2f uv, const Vec3f& adjoint,
                                const std::string& what) {
  check_texture_gradient(
      store, h, what + " (eval)", [&] { return adjoint_dot(adjoint, slot.eval<double>(store, uv)); },
      [&](GradientAccumulator& g) { slot.backprop(store, uv, adjoint, g); });
  check_texture_gradient(
      store, h, what + " (eval_scalar)", [&] { return double(adjoint.x) * slot.eval_scalar<double>(store, uv); },
      [&](GradientAccumulator& g) { slot.backprop_scalar(store, uv, adjoint.x, g); });
}

}  // namespace

TEST_CASE("bitmap lookups follow the texel-centre convention", "[texture]") {
  TestRng rng(3);
  ParamStore store;
  const int h = store.add(random_param("t.rgb", {5, 7, 3}, rng));
  const Param& p = store[h];
  for (Wrap wrap : {Wrap::Repeat, Wrap::Clamp, Wrap::Mirror}) {
    // A lookup at a texel centre returns that texel exactly.
    for (int row = 0; row < 5; ++row)
      for (int col = 0; col < 7; ++col) {
        const Vec2f uv{(float(col) + 0.5f) / 7.f, (float(row) + 0.5f) / 5.f};
        const Vec3f v = bitmap_eval<float>(p, wrap, uv);
        const size_t base = (size_t(row) * 7 + size_t(col)) * 3;
        INFO(describe(p, wrap, uv, Vec3f(0.f)));
        CHECK(v.x == Approx(p.value[base]).epsilon(1e-6));
        CHECK(v.y == Approx(p.value[base + 1]).epsilon(1e-6));
        CHECK(v.z == Approx(p.value[base + 2]).epsilon(1e-6));
      }
  }
  // Halfway between two horizontally adjacent centres: their average.
  const Vec3f mid = bitmap_eval<float>(p, Wrap::Clamp, {2.f / 7.f, 1.5f / 5.f});
  CHECK(mid.x == Approx(0.5f * (p.value[(1 * 7 + 1) * 3] + p.value[(1 * 7 + 2) * 3])).epsilon(1e-6));
  // Repeat is periodic; clamp is constant beyond the outermost centres.
  for (int i = 0; i < 50; ++i) {
    const Vec2f uv{float(rng.uniform(0.0, 1.0)), float(rng.uniform(0.0, 1.0))};
    const Vec3f a = bitmap_eval<float>(p, Wrap::Repeat, uv),
                b = bitmap_eval<float>(p, Wrap::Repeat, {uv.x + 2.f, uv.y - 1.f});
    INFO("uv (" << uv.x << ", " << uv.y << ")");
    CHECK(a.x == Approx(b.x).epsilon(1e-4));
    CHECK(a.z == Approx(b.z).epsilon(1e-4));
    const Vec3f left = bitmap_eval<float>(p, Wrap::Clamp, {-0.4f, uv.y}),
                edge = bitmap_eval<float>(p, Wrap::Clamp, {0.5f / 7.f, uv.y});
    CHECK(left.y == Approx(edge.y).epsilon(1e-6));
    const Vec3f below = bitmap_eval<float>(p, Wrap::Clamp, {uv.x, 1.7f}),
                last_row = bitmap_eval<float>(p, Wrap::Clamp, {uv.x, 4.5f / 5.f});
    CHECK(below.y == Approx(last_row.y).epsilon(1e-6));
    // Mirror reflects the texture about u = 0 and u = 1 (and v alike), with period 2.
    const Vec3f m = bitmap_eval<float>(p, Wrap::Mirror, uv);
    for (const Vec2f reflected :
         {Vec2f{-uv.x, uv.y}, Vec2f{2.f - uv.x, uv.y}, Vec2f{uv.x, -uv.y}, Vec2f{uv.x + 2.f, uv.y - 2.f}}) {
      const Vec3f r = bitmap_eval<float>(p, Wrap::Mirror, reflected);
      INFO("reflected (" << reflected.x << ", " << reflected.y << ")");
      CHECK(r.x == Approx(m.x).epsilon(1e-4));
      CHECK(r.z == Approx(m.z).epsilon(1e-4));
    }
    // Inside [0, 1]² all three agree away from the border cells.
    if (uv.x > 1.f / 7.f && uv.x < 6.f / 7.f && uv.y > 1.f / 5.f && uv.y < 4.f / 5.f)
      CHECK(m.y == Approx(a.y).epsilon(1e-5));
  }
  // At the border the mirror repeats the edge texel across it: halfway between the last centre and
  // its mirror image is that texel.
  const Vec3f edge = bitmap_eval<float>(p, Wrap::Mirror, {1.f, 0.5f / 5.f});
  CHECK(edge.x == Approx(p.value[6 * 3]).epsilon(1e-6));
}

TEST_CASE("bitmap backprop matches finite differences per texel", "[texture][backprop]") {
  TestRng rng(17);
  const std::vector<BitmapCase> cases{{{5, 7, 3}, Wrap::Repeat}, {{5, 7, 3}, Wrap::Clamp},  {{5, 7, 1}, Wrap::Repeat},
                                      {{5, 7, 1}, Wrap::Clamp},  {{1, 4, 3}, Wrap::Repeat}, {{3, 1, 1}, Wrap::Clamp},
                                      {{5, 7, 3}, Wrap::Mirror}, {{1, 4, 1}, Wrap::Mirror}};
  for (const BitmapCase& bc : cases) {
    ParamStore store;
    store.add(random_param("other", {3}, rng));
    const int h = store.add(random_param("t.bitmap", bc.shape, rng));
    store.require_grad({});
    TextureSlot slot{h, true, bc.wrap};
    for (const Vec2f uv : lookup_points(bc.shape[1], bc.shape[0], rng)) {
      const Vec3f adjoint(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
      const std::string what = describe(store[h], bc.wrap, uv, adjoint);
      check_rgb_and_scalar_reads(store, h, slot, uv, adjoint, what);
    }
  }
}

TEST_CASE("one-channel bitmaps are broadcast to grey", "[texture]") {
  TestRng rng(5);
  ParamStore store;
  const int h = store.add(random_param("t.grey", {5, 7, 1}, rng));
  TextureSlot slot{h, true, Wrap::Repeat};
  for (int i = 0; i < 20; ++i) {
    const Vec2f uv{float(rng.uniform(-1, 2)), float(rng.uniform(-1, 2))};
    const Vec3f v = slot.eval<float>(store, uv);
    CHECK(v.x == v.y);
    CHECK(v.y == v.z);
    CHECK(slot.eval_scalar<float>(store, uv) == v.x);
  }
}

TEST_CASE("constant texture backprop matches finite differences", "[texture][backprop]") {
  TestRng rng(23);
  for (int size : {1, 3}) {
    ParamStore store;
    const int h = store.add(random_param("t.constant", {size}, rng));
    store.require_grad({});
    TextureSlot slot{h, false, Wrap::Repeat};
    for (int i = 0; i < 10; ++i) {
      const Vec3f adjoint(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)));
      const Vec2f uv{float(rng.uniform(-1, 2)), float(rng.uniform(-1, 2))};
      const std::string what = "constant of size " + std::to_string(size);
      check_rgb_and_scalar_reads(store, h, slot, uv, adjoint, what);
    }
    const Vec3f v = slot.eval<float>(store, {0.3f, 0.3f});
    CHECK(v.x == store[h].value[0]);
    CHECK(v.z == store[h].value[size_t(size - 1)]);
  }
}

TEST_CASE("texture backprop writes only parameters that require gradients", "[texture][backprop]") {
  TestRng rng(29);
  ParamStore store;
  const int wanted = store.add(random_param("t.wanted", {2, 2, 3}, rng));
  const int frozen = store.add(random_param("t.frozen", {2, 2, 3}, rng));
  store.require_grad({"t.wanted"});
  const TextureSlot a{wanted, true, Wrap::Repeat}, b{frozen, true, Wrap::Repeat};
  const std::vector<double> g = gradient_through_sink(store, frozen, [&](GradientAccumulator& acc) {
    a.backprop(store, {0.3f, 0.6f}, Vec3f(1.f), acc);
    b.backprop(store, {0.3f, 0.6f}, Vec3f(1.f), acc);
    b.backprop_scalar(store, {0.3f, 0.6f}, 1.f, acc);
  });
  for (double x : g) CHECK(x == 0.0);
  double total = 0.0;
  for (float x : store[wanted].grad) total += double(x);
  CHECK(total == Approx(3.0).epsilon(1e-6));  // bilinear weights sum to 1 per channel
}

TEST_CASE("bitmap uv gradient matches central differences of eval in u and v", "[texture][uv]") {
  // The lookup is piecewise bilinear in (u, v): central differences with a step inside one cell are
  // exact up to rounding. Points away from texel centres (where the slope jumps) and cell borders.
  // Mirror flips the slope in every other copy of the image (a Repeat slope there survived an
  // audit's mutation); its kinks at the image's edges sit at cell fraction 0.5 and are kept clear of.
  TestRng rng(31);
  for (Wrap wrap : {Wrap::Repeat, Wrap::Clamp, Wrap::Mirror})
    for (int channels : {3, 1}) {
      ParamStore store;
      const int h = store.add(random_param("t.bitmap", {5, 7, channels}, rng));
      TextureSlot slot{h, true, wrap};
      for (int i = 0; i < 40; ++i) {
        // Cell coordinates with fractions in [0.2, 0.8]: a step of 1e-3 cells stays in the cell.
        auto coordinate = [&](double lo, double hi) {
          double fraction = rng.uniform(0.2, 0.8);
          while (wrap == Wrap::Mirror && std::abs(fraction - 0.5) < 0.01) fraction = rng.uniform(0.2, 0.8);
          return std::floor(rng.uniform(lo, hi)) + fraction;
        };
        const double cx = coordinate(-9, 16), cy = coordinate(-7, 12);
        const Vec2f uv{float((cx + 0.5) / 7), float((cy + 0.5) / 5)};
        Vec3f du, dv;
        slot.uv_gradient(store, uv, du, dv);
        const double eu = 1e-3 / 7, ev = 1e-3 / 5;
        const Vec3d fu = (Vec3d(slot.eval<double>(store, {uv.x + float(eu), uv.y})) -
                          Vec3d(slot.eval<double>(store, {uv.x - float(eu), uv.y}))) /
                         (2 * eu);
        const Vec3d fv = (Vec3d(slot.eval<double>(store, {uv.x, uv.y + float(ev)})) -
                          Vec3d(slot.eval<double>(store, {uv.x, uv.y - float(ev)}))) /
                         (2 * ev);
        INFO("wrap " << int(wrap) << " channels " << channels << " uv " << uv.x << "," << uv.y);
        for (int c = 0; c < 3; ++c) {
          CHECK(du[c] == Approx(fu[c]).epsilon(5e-3).margin(5e-3));
          CHECK(dv[c] == Approx(fv[c]).epsilon(5e-3).margin(5e-3));
        }
      }
      // A constant slot has no slope.
      TextureSlot constant{store.add(random_param("t.c", {3}, rng)), false, wrap};
      Vec3f du, dv;
      constant.uv_gradient(store, {0.3f, 0.4f}, du, dv);
      CHECK((du.x == 0.f && du.y == 0.f && du.z == 0.f && dv.x == 0.f && dv.y == 0.f && dv.z == 0.f));
    }
}
