// Determinism across thread counts. The primal render sums each pixel's samples in a fixed order
// inside one task, so images must be bitwise identical for 1 and 2 worker threads. Gradients are
// accumulated by several threads: small parameters (≤ kSmallParamLimit floats) in per-thread
// double sums reduced once, large ones by atomic float adds whose order varies. The tests below
// pin down what holds (measured, see the comments at each check).
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>

#include "engine/core/sampler.h"
#include "engine/integrators/gradient.h"
#include "engine/scene/scene_load.h"
#include "test_scenes.h"

using namespace bl;

namespace {

template <class F>
auto with_threads(int n, F&& f) {
  tbb::global_control limit(tbb::global_control::max_allowed_parallelism, size_t(n));
  return f();
}

std::unique_ptr<Scene> cornell(int res) {
  auto scene = load_scene(std::string(BL_SOURCE_DIR) + "/scenes/cornell/scene.json");
  for (auto& c : scene->cameras) c.width = c.height = res, c.update();
  return scene;
}

std::unique_ptr<Scene> open_scene() { return load_scene(test::write_open_scene(test::temp_dir("determinism"))); }

bool bitwise_equal(const Image& a, const Image& b) {
  return a.width == b.width && a.height == b.height && a.channels == b.channels &&
         std::memcmp(a.data.data(), b.data.data(), a.data.size() * sizeof(float)) == 0;
}

size_t count_differences(const Image& a, const Image& b) {
  size_t n = 0;
  for (size_t i = 0; i < a.data.size(); ++i) n += std::memcmp(&a.data[i], &b.data[i], sizeof(float)) != 0;
  return n;
}

std::vector<std::vector<float>> gradients(Scene& scene, const Image& target, GradientMethod m, int threads,
                                          Image* image) {
  return with_threads(threads, [&] {
    GradientRequest rq;
    rq.method = m;
    rq.target = &target;
    rq.pass = {0, 4, 7, false};
    rq.adjoint_seed = 7;
    scene.params.require_grad({});
    GradientResult r = compute_gradient(scene, rq);
    if (image) *image = r.image;
    std::vector<std::vector<float>> g;
    for (const auto& p : scene.params.all()) g.push_back(p.grad);
    return g;
  });
}

}  // namespace

TEST_CASE("primal renders are bitwise identical for 1 and 2 threads", "[determinism]") {
  SECTION("scenes/cornell, 64x64, 4 spp") {
    auto scene = cornell(64);
    Image one = with_threads(1, [&] { return render(*scene, {0, 4, 3, false}); });
    Image two = with_threads(2, [&] { return render(*scene, {0, 4, 3, false}); });
    Image again = with_threads(2, [&] { return render(*scene, {0, 4, 3, false}); });
    INFO(count_differences(one, two) << " of " << one.data.size() << " values differ");
    CHECK(bitwise_equal(one, two));
    CHECK(bitwise_equal(two, again));
    // Another seed really changes the image (the seed is used).
    Image other = render(*scene, {0, 4, 4, false});
    CHECK(count_differences(one, other) > one.data.size() / 2);
  }
  SECTION("the generated open scene (bitmap, envmap, plastic, conductor, area light, roulette)") {
    auto scene = open_scene();
    Image one = with_threads(1, [&] { return render(*scene, {0, 4, 3, false}); });
    Image two = with_threads(2, [&] { return render(*scene, {0, 4, 3, false}); });
    INFO(count_differences(one, two) << " of " << one.data.size() << " values differ");
    CHECK(bitwise_equal(one, two));
  }
}

TEST_CASE("prb gradients across thread counts", "[determinism][gradient]") {
  auto scene = open_scene();
  Image target = render(*scene, {0, 16, 99, false});
  for (auto& v : target.data) v *= 0.7f;
  for (GradientMethod m : {GradientMethod::Prb, GradientMethod::Rb}) {
    INFO("method " << method_name(m));
    Image img1, img2;
    auto g1 = gradients(*scene, target, m, 1, &img1);
    auto g2 = gradients(*scene, target, m, 2, &img2);
    // The image rendered on the way (fused primal) is the primal render, bit for bit.
    CHECK(bitwise_equal(img1, img2));
    CHECK(bitwise_equal(img1, render(*scene, {0, 4, 7, false})));
    for (size_t i = 0; i < g1.size(); ++i) {
      const Param& p = scene->params.all()[i];
      if (!p.requires_grad) continue;  // geometry parameters: not in "all"
      double norm = 0, diff = 0, max_abs = 0;
      size_t differing = 0;
      for (size_t k = 0; k < p.size(); ++k) {
        norm += double(g1[i][k]) * g1[i][k];
        diff += double(g1[i][k] - g2[i][k]) * double(g1[i][k] - g2[i][k]);
        max_abs = std::max(max_abs, double(std::abs(g1[i][k])));
        differing += g1[i][k] != g2[i][k];
      }
      norm = std::sqrt(norm), diff = std::sqrt(diff);
      INFO(p.name << " (" << p.size() << " values, " << (p.small ? "per-thread double sums" : "atomic float adds")
                  << "): |g| = " << norm << ", |g1 − g2| = " << diff << ", " << differing << " elements differ");
      CHECK(norm > 0);
      // Both kinds: the difference is rounding only, far below 1e-5 of the gradient's norm
      // (measured on this scene: 0 for small parameters, ~5e-8 relative for atomic ones, where
      // a few dozen of the 384/768 elements differ in their last bits from run to run).
      CHECK(diff <= 1e-5 * norm);
      if (p.small) {
        // Double sums rounded once to float: measured bitwise equal in every run, but a
        // different grouping of the double partial sums may in rare cases round to the
        // neighbouring float, so one float ulp is allowed.
        for (size_t k = 0; k < p.size(); ++k)
          CHECK(std::abs(g1[i][k] - g2[i][k]) <= 1.2e-7f * std::abs(g1[i][k]) + 1e-30f);
      } else {
        // Atomic float adds in varying order: each element agrees to float-sum precision.
        for (size_t k = 0; k < p.size(); ++k)
          if (std::abs(g1[i][k] - g2[i][k]) > 1e-5 * std::abs(g1[i][k]) + 1e-7 * max_abs) {
            FAIL_CHECK("element " << k << ": " << g1[i][k] << " vs " << g2[i][k]);
            break;
          }
      }
    }
  }
}

TEST_CASE("PathSampler streams regenerate identically on any thread", "[determinism][sampler]") {
  constexpr int kPixels = 64, kSamples = 16, kDims = 40;
  auto index = [](int px, int s, int d) { return (size_t(px) * kSamples + size_t(s)) * kDims + size_t(d); };
  std::vector<float> sequential(size_t(kPixels) * kSamples * kDims);
  for (int px = 0; px < kPixels; ++px)
    for (int s = 0; s < kSamples; ++s) {
      PathSampler sampler(42, uint64_t(px), uint64_t(s));
      for (int d = 0; d < kDims; ++d) sequential[index(px, s, d)] = sampler.get(uint32_t(d));
    }
  // Regenerated in parallel, in reverse dimension order, from fresh samplers.
  std::vector<float> parallel(sequential.size());
  with_threads(2, [&] {
    tbb::parallel_for(0, kPixels * kSamples, [&](int t) {
      int px = t / kSamples, s = t % kSamples;
      for (int d = kDims - 1; d >= 0; --d)
        parallel[index(px, s, d)] = PathSampler(42, uint64_t(px), uint64_t(s)).get(uint32_t(d));
    });
    return 0;
  });
  CHECK(std::memcmp(sequential.data(), parallel.data(), sequential.size() * sizeof(float)) == 0);
  CHECK(std::count_if(sequential.begin(), sequential.end(), [](float v) { return !(v >= 0.f && v < 1.f); }) == 0);
  // Seed, pixel and sample index all change the stream; keys do not collide on a small grid.
  std::vector<uint64_t> keys;
  for (uint64_t seed : {0ull, 1ull, 42ull})
    for (uint64_t px = 0; px < 64; ++px)
      for (uint64_t s = 0; s < 64; ++s) keys.push_back(PathSampler(seed, px, s).key());
  std::sort(keys.begin(), keys.end());
  CHECK(std::adjacent_find(keys.begin(), keys.end()) == keys.end());
  // The mean of the numbers is 1/2 (a cheap sanity check of the mapping to [0, 1)).
  double mean = 0;
  for (float v : sequential) mean += v;
  mean /= double(sequential.size());
  CHECK(std::abs(mean - 0.5) < 4 * std::sqrt(1.0 / 12.0 / double(sequential.size())));
}
