// Regression test of the bundled scenes against tests/data/bundled/*.exr (4096 spp, seed 1000,
// written by tools/make-test-references). We render 4 batches of 64 spp with other seeds and
// compare:
//  - per channel, the image mean: relative difference < 1.5 %. The Monte Carlo error of a 256 spp
//    image mean is ~0.3 % here, so this catches any global energy change of a few percent;
//  - per pixel, z = (ours − ref) / sqrt(se_ours² + se_ref²), se_ours from the scatter of the 4
//    batch means, se_ref = se_ours / 4 (16× the samples). With 4 batches z follows roughly a
//    Student t with 3 dof: median |z| ≈ 0.77 when nothing changed. We require median |z| < 1.2
//    and fewer than 5 % of pixels with |z| > 6 (t₃: P(|t| > 6) ≈ 1 %). A local change — a wrong
//    texture lookup, a lost lobe, a moved object — pushes both up.
// Regenerate the references only for intended changes of the output (see the script).
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <sstream>

#include "engine/integrators/render.h"
#include "engine/scene/scene_load.h"

using namespace bl;

namespace {

struct Comparison {
  double mean_ours[3] = {}, mean_ref[3] = {};
  double max_rel_mean = 0;  // max over channels of |mean_ours − mean_ref| / mean_ref
  double median_abs_z = 0;
  double frac_z_above_6 = 0;
  std::string text() const {
    std::ostringstream o;
    o << "means ours " << mean_ours[0] << " " << mean_ours[1] << " " << mean_ours[2] << ", reference " << mean_ref[0]
      << " " << mean_ref[1] << " " << mean_ref[2] << "; max relative mean difference " << max_rel_mean
      << "; median |z| " << median_abs_z << "; fraction |z| > 6: " << frac_z_above_6;
    return o.str();
  }
};

Comparison compare(const Scene& scene, const Image& ref, int batches, int spp) {
  std::vector<Image> imgs;
  for (int b = 0; b < batches; ++b) imgs.push_back(render(scene, {0, spp, 1 + uint64_t(b), false}));
  Comparison c;
  std::vector<double> abs_z;
  size_t above = 0;
  for (size_t i = 0; i < ref.data.size(); ++i) {
    double m = 0, v = 0;
    for (const auto& im : imgs) m += im.data[i];
    m /= batches;
    for (const auto& im : imgs) v += (im.data[i] - m) * (im.data[i] - m);
    const double se_ours = std::sqrt(v / (batches - 1) / batches), se_ref = se_ours / 4;
    const double diff = m - ref.data[i];
    c.mean_ours[i % 3] += m;
    c.mean_ref[i % 3] += ref.data[i];
    const double se = std::sqrt(se_ours * se_ours + se_ref * se_ref);
    if (se > 0) {
      abs_z.push_back(std::abs(diff) / se);
    } else if (std::abs(diff) > 1e-4 * std::abs(ref.data[i]) + 1e-7) {
      abs_z.push_back(1e30);  // noiseless here but different from the reference
    } else {
      // A noiseless pixel that agrees, e.g. the directly seen constant background. Pixel means
      // are float sums of the samples, which drift with spp: 4096 × 0.1 / 4096 = 0.1000039 but
      // 64 × 0.1 / 64 = 0.1000002, hence the relative 1e-4 above.
      continue;
    }
    above += abs_z.back() > 6;
  }
  for (int k = 0; k < 3; ++k)
    c.max_rel_mean = std::max(c.max_rel_mean, std::abs(c.mean_ours[k] - c.mean_ref[k]) / c.mean_ref[k]);
  for (int k = 0; k < 3; ++k) c.mean_ours[k] /= double(ref.pixel_count()), c.mean_ref[k] /= double(ref.pixel_count());
  if (!abs_z.empty()) {
    std::nth_element(abs_z.begin(), abs_z.begin() + long(abs_z.size() / 2), abs_z.end());
    c.median_abs_z = abs_z[abs_z.size() / 2];
    c.frac_z_above_6 = double(above) / double(abs_z.size());
  }
  return c;
}

std::unique_ptr<Scene> load_at(const std::string& scene_file, int width, int height) {
  auto scene = load_scene(std::string(BL_SOURCE_DIR) + "/" + scene_file);
  for (auto& cam : scene->cameras) cam.width = width, cam.height = height, cam.update();
  return scene;
}

Image reference(const std::string& name) {
  return read_image(std::string(BL_SOURCE_DIR) + "/tests/data/bundled/" + name, false);
}

constexpr int kBatches = 4, kSpp = 64;

}  // namespace

TEST_CASE("bundled scenes match their references", "[bundled][regression]") {
  struct Case {
    const char* scene;
    const char* reference;
    int width, height;
  };
  for (const Case& k : {Case{"scenes/cornell/scene.json", "cornell_64x64.exr", 64, 64},
                        Case{"scenes/gltf/scene.gltf", "gltf_64x48.exr", 64, 48}}) {
    INFO(k.scene << " vs tests/data/bundled/" << k.reference);
    auto scene = load_at(k.scene, k.width, k.height);
    Image ref = reference(k.reference);
    REQUIRE(ref.width == k.width);
    REQUIRE(ref.height == k.height);
    REQUIRE(ref.channels == 3);
    Comparison c = compare(*scene, ref, kBatches, kSpp);
    INFO(c.text());
    CHECK(c.max_rel_mean < 0.015);
    CHECK(c.median_abs_z < 1.2);
    CHECK(c.frac_z_above_6 < 0.05);
  }
}

TEST_CASE("the bundled-scene comparison detects small changes", "[bundled][regression]") {
  // Power check of the tolerances above: 3 % less light fails the mean test, and a 15 % darker
  // back-wall texture (a region, not the whole image) fails the per-pixel test.
  auto scene = load_at("scenes/cornell/scene.json", 64, 64);
  Image ref = reference("cornell_64x64.exr");
  auto& light = scene->params[scene->params.find("light.radiance")];
  for (auto& v : light.value) v *= 0.97f;
  Comparison dimmer = compare(*scene, ref, kBatches, kSpp);
  INFO("light × 0.97: " << dimmer.text());
  CHECK(dimmer.max_rel_mean > 0.015);
  for (auto& v : light.value) v /= 0.97f;
  auto& wall = scene->params[scene->params.find("wall.albedo")];
  for (auto& v : wall.value) v *= 0.85f;
  Comparison darker_wall = compare(*scene, ref, kBatches, kSpp);
  INFO("wall texture × 0.85: " << darker_wall.text());
  CHECK(darker_wall.median_abs_z > 1.2);
}
