// Determinism across thread counts. The primal render sums each pixel's samples in a fixed order
// inside one task, so images must be bitwise identical for 1 and 2 worker threads. Gradients are
// accumulated by several threads: small parameters (≤ kSmallParamLimit floats), and larger ones
// while their per-thread copies fit the local gradient budget, in per-thread double sums reduced
// once, the rest by atomic float adds whose order varies. The tests below pin down what holds
// (measured, see the comments at each check).
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

// Puts the local gradient budget back when a test case that changes it ends.
struct RestoreBudget {
  size_t budget;
  ~RestoreBudget() { set_local_gradient_budget(budget); }
};

// A bundled scene with every camera at res × res pixels.
std::unique_ptr<Scene> bundled(const std::string& name, int res) {
  auto scene = load_scene(std::string(BL_SOURCE_DIR) + "/scenes/" + name + "/scene.json");
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
                                          Image* image, const std::vector<std::string>& names = {}) {
  return with_threads(threads, [&] {
    GradientRequest rq;
    rq.method = m;
    rq.target = &target;
    rq.pass = {0, 4, 7, false};
    rq.adjoint_seed = 7;
    scene.params.require_grad(names);
    GradientResult r = compute_gradient(scene, rq);
    if (image) *image = r.image;
    std::vector<std::vector<float>> g;
    for (const auto& p : scene.params.all()) g.push_back(p.grad);
    return g;
  });
}

// The gradients of one run on 1 thread and one on 2 (`gradients` above), parameter by parameter:
// rounding only. Per-thread double sums agree to a float ulp, atomic float adds to float-sum
// precision.
void compare_across_threads(const Scene& scene, const std::vector<std::vector<float>>& g1,
                            const std::vector<std::vector<float>>& g2) {
  for (size_t i = 0; i < g1.size(); ++i) {
    const Param& p = scene.params.all()[i];
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
    // How the two runs accumulated this parameter (engine/core/params.h).
    const bool local = GradientLayout(scene.params, 1).local(int(i)) && GradientLayout(scene.params, 2).local(int(i));
    INFO(p.name << " (" << p.size() << " values, " << (local ? "per-thread double sums" : "atomic float adds")
                << "): |g| = " << norm << ", |g1 − g2| = " << diff << ", " << differing << " elements differ");
    CHECK(norm > 0);
    // Both kinds: the difference is rounding only, far below 1e-5 of the gradient's norm
    // (measured on the open scene: 0 for small parameters, ~5e-8 relative for atomic ones, where
    // a few dozen of the 384/768 elements differ in their last bits from run to run).
    CHECK(diff <= 1e-5 * norm);
    if (local) {
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

}  // namespace

TEST_CASE("primal renders are bitwise identical for 1 and 2 threads", "[determinism]") {
  SECTION("scenes/cornell, 64x64, 4 spp") {
    auto scene = bundled("cornell", 64);
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
  SECTION("scenes/mitsuba-volume: a 64³ density grid behind a null box (delta and ratio tracking)") {
    // Tracking draws a variable number of random numbers per segment, from per-(path, segment)
    // streams, so the image does not depend on which thread ran which pixel.
    auto scene = bundled("mitsuba-volume", 48);
    Image one = with_threads(1, [&] { return render(*scene, {0, 4, 3, false}); });
    Image two = with_threads(2, [&] { return render(*scene, {0, 4, 3, false}); });
    INFO(count_differences(one, two) << " of " << one.data.size() << " values differ");
    CHECK(bitwise_equal(one, two));
  }
}

TEST_CASE("a render counts its rays by kind, the same on any thread count", "[determinism][stats]") {
  // The mix bench/primal hands its bare Embree loop: every camera ray goes through a packet (12
  // spp: a packet of 8 and one of 4 per pixel), shadow rays are counted apart.
  auto scene = bundled("cornell", 16);
  PassStats one, two;
  const Image a = with_threads(1, [&] { return render(*scene, {0, 12, 3, false}, &one); });
  const Image b = with_threads(2, [&] { return render(*scene, {0, 12, 3, false}, &two); });
  CHECK(bitwise_equal(a, b));
  CHECK(one.packet_rays == 16u * 16u * 12u);
  CHECK(one.shadow_rays > one.packet_rays / 2);         // about one light sample per surface vertex
  CHECK(one.rays > one.packet_rays + one.shadow_rays);  // and bounce rays
  CHECK(one.rays == two.rays);
  CHECK(one.shadow_rays == two.shadow_rays);
  CHECK(one.packet_rays == two.packet_rays);
  // Through media, shadow rays walk across null surfaces with closest-hit queries: counted as
  // shadow rays all the same.
  auto volume = bundled("mitsuba-volume", 16);
  PassStats media;
  render(*volume, {0, 4, 3, false}, &media);
  CHECK(media.packet_rays == 16u * 16u * 4u);
  CHECK(media.shadow_rays > media.packet_rays / 4);
  CHECK(media.rays > media.packet_rays + media.shadow_rays);
}

TEST_CASE("prb gradients across thread counts", "[determinism][gradient]") {
  auto scene = open_scene();
  Image target = render(*scene, {0, 16, 99, false});
  for (auto& v : target.data) v *= 0.7f;
  // Both ways of accumulating (engine/core/params.h): with the default budget the scene's
  // textures (384 and 768 values) take per-thread double sums, with none atomic float adds.
  const size_t default_budget = local_gradient_budget();
  const RestoreBudget restore{default_budget};
  for (auto [m, budget] : {std::pair{GradientMethod::Prb, default_budget}, std::pair{GradientMethod::Prb, size_t(0)},
                           std::pair{GradientMethod::Rb, default_budget}}) {
    INFO("method " << method_name(m) << ", local gradient budget " << budget << " bytes");
    set_local_gradient_budget(budget);
    Image img1, img2;
    auto g1 = gradients(*scene, target, m, 1, &img1);
    auto g2 = gradients(*scene, target, m, 2, &img2);
    // The image rendered on the way (fused primal) is the primal render, bit for bit.
    CHECK(bitwise_equal(img1, img2));
    CHECK(bitwise_equal(img1, render(*scene, {0, 4, 7, false})));
    compare_across_threads(*scene, g1, g2);
  }
}

TEST_CASE("prb gradients of a density grid across thread counts", "[determinism][gradient][media]") {
  // The 64³ grid (2 MB of doubles per thread) sums per thread; scale, albedo and g are small
  // parameters. With no local budget the grid takes atomic float adds instead.
  auto scene = bundled("mitsuba-volume", 32);
  Image target = render(*scene, {0, 16, 99, false});
  for (auto& v : target.data) v *= 0.7f;
  const std::vector<std::string> names = {"smoke.density", "smoke.scale", "smoke.albedo", "smoke.g"};
  const size_t default_budget = local_gradient_budget();
  const RestoreBudget restore{default_budget};
  for (size_t budget : {default_budget, size_t(0)}) {
    INFO("local gradient budget " << budget << " bytes");
    set_local_gradient_budget(budget);
    Image img1, img2;
    auto g1 = gradients(*scene, target, GradientMethod::Prb, 1, &img1, names);
    auto g2 = gradients(*scene, target, GradientMethod::Prb, 2, &img2, names);
    CHECK(bitwise_equal(img1, img2));
    compare_across_threads(*scene, g1, g2);
  }
}

TEST_CASE("the gradient layout: which buffers sum per thread, within the budget", "[determinism][gradient]") {
  const size_t default_budget = local_gradient_budget();
  const RestoreBudget restore{default_budget};
  ParamStore store;
  auto add = [&](const std::string& name, size_t n) {
    Param p;
    p.name = name;
    p.shape = {int(n)};
    p.value.assign(n, 1.f);
    return store.add(p);
  };
  const int tiny = add("a.tiny", 3), unused = add("a.unused", 3), big = add("a.big", 1000),
            bigger = add("a.bigger", 3000);
  store.require_grad({"a.tiny", "a.big", "a.bigger"});
  // 1000 doubles on 2 threads take 16 000 bytes: a budget of 40 000 holds a.big (handle order),
  // not a.bigger after it (48 000 more); small buffers take no budget.
  set_local_gradient_budget(40000);
  GradientLayout two(store, 2);
  CHECK(two.local(tiny));
  CHECK_FALSE(two.local(unused));  // no gradient asked: no space
  CHECK(two.local(big));
  CHECK_FALSE(two.local(bigger));
  CHECK(two.total == 3 + 1000);
  // On one thread both fit (8 000 + 24 000 bytes); with no budget only the small one is local.
  CHECK(GradientLayout(store, 1).local(bigger));
  set_local_gradient_budget(0);
  CHECK(GradientLayout(store, 2).local(tiny));
  CHECK_FALSE(GradientLayout(store, 2).local(big));

  // The same adds through both ways give the same sums (up to float rounding of the atomics).
  std::vector<std::vector<float>> sums;
  for (size_t budget : {size_t(0), size_t(1) << 20}) {
    set_local_gradient_budget(budget);
    store.zero_grad();
    GradientSink sink(store);
    with_threads(2, [&] {
      tbb::parallel_for(0, 64, [&](int i) {
        GradientAccumulator& g = sink.local();
        for (int k = 0; k < 3000; ++k) g.add(bigger, size_t(k), 0.25f * float((i + k) % 7));
        g.add_each(big, [&](auto&& emit) {
          for (int k = 0; k < 1000; k += 3) emit(size_t(k), 1.f / float(1 + i));
        });
      });
      return 0;
    });
    sink.reduce();
    std::vector<float> all = store[bigger].grad;
    all.insert(all.end(), store[big].grad.begin(), store[big].grad.end());
    sums.push_back(all);
  }
  for (size_t k = 0; k < sums[0].size(); ++k) REQUIRE(sums[0][k] == Approx(sums[1][k]).epsilon(1e-6));
  CHECK(sums[1][3000] == Approx(4.7438909).epsilon(1e-6));  // Σ_{i<64} 1/(1+i), element 0 of a.big
  CHECK(sums[1][3001] == 0.f);                              // not added to
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

// Every pass starts its paths from a pixel's camera rays traced as one Embree packet
// (CameraPacket, engine/integrators/path.h), so all passes follow the same paths whatever the
// packet returns; what is checked here is that it returns the single-ray answer: the same mesh
// and distance, bitwise, and the same triangle and barycentrics except where the ray meets an edge
// shared by two triangles at one distance, a tie the two traversals may break differently (5 of
// 14.2 M jittered camera rays of the volume job's 24 views, 2026-11-26: the other triangle, the
// same point). On bundled scenes, jittered camera rays on a grid of about 96 × 96 pixels, packets
// of 1 to 8 rays (a pixel's last packet when spp is not a multiple of 8).
TEST_CASE("camera ray packets hit what single rays hit", "[determinism]") {
  auto on_edge = [](const Hit& h) {
    return std::min({h.b1, h.b2, 1.f - h.b1 - h.b2}) <= 1e-6f;  // a barycentric at 0: on an edge
  };
  // The bundled scenes in the repository (scenes/smoke's grid is generated): boxes, a sphere mesh
  // of shared edges everywhere (deform), a glTF scene.
  for (const char* name : {"scenes/cornell/scene.json", "scenes/mitsuba-cornell/scene.json", "scenes/deform/scene.json",
                           "scenes/gltf/scene.gltf"}) {
    auto scene = load_scene(std::string(BL_SOURCE_DIR) + "/" + name);
    const Camera& cam = scene->cameras[0];
    long traced = 0, hits = 0, ties = 0, wrong = 0;
    const int step = std::max(1, cam.width / 96);  // about 96 pixels across
    for (int y = 0; y < cam.height; y += step)
      for (int x = 0; x < cam.width; x += step) {
        Ray rays[Geometry::kPacket];
        Hit packet[Geometry::kPacket];
        const PathSampler s(1, uint64_t(y) * uint64_t(cam.width) + uint64_t(x), 0);
        for (int k = 0; k < Geometry::kPacket; ++k)
          rays[k] = cam.generate(float(x) + s.get(2 * k), float(y) + s.get(2 * k + 1));
        const int count = 1 + (x / step + y / step) % Geometry::kPacket;  // 1 to 8 rays
        scene->geometry->intersect_packet(rays, count, packet);
        for (int k = 0; k < count; ++k) {
          const Hit single = scene->geometry->intersect(rays[k]), p = packet[k];
          ++traced;
          hits += single.mesh >= 0;
          if (std::memcmp(&single, &p, sizeof(Hit)) == 0) continue;
          const bool tie =
              single.mesh == p.mesh && single.t == p.t && single.mesh >= 0 && on_edge(single) && on_edge(p);
          (tie ? ties : wrong) += 1;
        }
      }
    INFO(name << ": " << traced << " rays, " << ties << " edge ties, " << wrong << " other differences");
    CHECK(wrong == 0);
    CHECK(double(ties) <= 1e-4 * double(traced));
    CHECK(hits > traced / 4);  // the rays do hit the scene (not a comparison of misses only)
  }
}
