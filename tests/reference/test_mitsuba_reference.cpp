// Statistical comparison of backlight with the Mitsuba 3.8 references in
// tests/data/mitsuba3-cornell/ (see the README there and tests/reference/README.md for the
// metrics, their thresholds and measured values).
//
// Both sides are Monte Carlo estimates. Ours is rendered as B independent batches (different
// seeds), which gives our per-element mean and standard error; the reference ships its mean and
// standard error (32 batches, 16 for ref_textured_depth2). Every test is deterministic (fixed
// seeds), so a pass or failure reproduces exactly.
//
// Budget: the environment variables BL_REF_IMAGE_BATCHES/SPP and BL_REF_GRAD_BATCHES/SPP (the
// defaults below are CI's fast budget), BL_REF_SEED_OFFSET shifts all seeds (ctest's
// test_mitsuba_reference_slow sets a larger budget and other seeds: tests/reference/CMakeLists.txt),
// and BL_REF_DUMP=<dir> writes our mean, our standard error and the z-map of every product as EXR
// files.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/io/image_io.h"
#include "engine/scene/scene_load.h"

#ifndef BL_REF_IMAGE_BATCHES
#define BL_REF_IMAGE_BATCHES 128
#endif
#ifndef BL_REF_IMAGE_SPP
#define BL_REF_IMAGE_SPP 1
#endif
#ifndef BL_REF_GRAD_BATCHES
#define BL_REF_GRAD_BATCHES 32
#endif
#ifndef BL_REF_GRAD_SPP
#define BL_REF_GRAD_SPP 4
#endif

namespace {

using namespace bl;

const std::string kRoot = BL_SOURCE_DIR;
const std::string kData = kRoot + "/tests/data/mitsuba3-cornell/";
const std::string kScene = kRoot + "/scenes/mitsuba-cornell/scene.json";
const std::string kTextured = kRoot + "/scenes/mitsuba-cornell/textured/scene.json";
const std::string kVolumeData = kRoot + "/tests/data/mitsuba3-volume/";
const std::string kVolumeScene = kRoot + "/scenes/mitsuba-volume/scene.json";
const std::string kWallParam = "back-textured.albedo";

// Thresholds (README.md, "Metrics").
constexpr double kMaxBiasZ = 4.0;
constexpr double kMaxRelBias = 0.005;
constexpr double kZStdLow = 0.85, kZStdHigh = 1.25;
constexpr double kMaxMadRatio = 3.0;

int budget(const char* name, int fallback) {
  const char* v = std::getenv(name);
  return v && *v ? std::max(1, std::atoi(v)) : fallback;
}

// Added to every batch seed: BL_REF_SEED_OFFSET from the environment (the slow run; experiments:
// other noise realisations).
uint64_t seed_offset() {
  const char* v = std::getenv("BL_REF_SEED_OFFSET");
  return v && *v ? std::strtoull(v, nullptr, 10) : 0;
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Running mean and sum of squared deviations per element over independent batches (Welford).
struct BatchStats {
  int n = 0;
  std::vector<double> mean, m2;
  void add(const std::vector<float>& x) { add(std::vector<double>(x.begin(), x.end())); }
  void add(const std::vector<double>& x) {
    if (n == 0) mean.assign(x.size(), 0.0), m2.assign(x.size(), 0.0);
    ++n;
    for (size_t i = 0; i < x.size(); ++i) {
      double d = x[i] - mean[i];
      mean[i] += d / n;
      m2[i] += d * (x[i] - mean[i]);
    }
  }
  // Standard error of the mean: sample standard deviation of the batch values / √n.
  double se(size_t i) const { return n > 1 ? std::sqrt(m2[i] / (n - 1) / n) : 0.0; }
};

struct Metrics {
  size_t count = 0;      // elements compared
  double mean_ref = 0;   // mean reference value
  double mean_diff = 0;  // mean(ours − ref)
  double bias_se = 0;    // standard error of mean_diff (elements independent)
  double bias_z = 0;     // mean_diff / bias_se
  double rel_bias = 0;   // |mean_diff| / |mean_ref|
  double z_mean = 0, z_std = 0;
  double z_std_expected = 0;                   // E[z²]^½ under H0 from the Welch–Satterthwaite degrees of freedom
  double mad = 0, mean_se = 0, mad_ratio = 0;  // mean |ours − ref|, mean combined se, their ratio
  double frac_z4 = 0, max_abs_z = 0;
  // Per-sample variance ratio ours / Mitsuba, Σ(N_o·se_o²) / Σ(N_r·se_r²): ≈ 1 when both use the
  // same sampling strategies (NEE + BSDF sampling, MIS, roulette). Reported, not checked.
  double var_ratio = 0;
};

struct Comparison {
  Metrics channel[3], all;
  size_t zero_se = 0;          // elements where both standard errors are exactly 0 (excluded)
  double zero_se_max_abs = 0;  // max |ours − ref| there
  double zero_se_max_rel = 0;  // max |ours − ref| / |ref| there (ref ≠ 0)
  std::vector<float> z;        // z per element (0 where excluded)
};

// Compares our batch statistics with a reference mean and standard error (3 interleaved
// channels). ref_batches is the number of batches behind ref_se (its degrees of freedom + 1).
// ours_samples / ref_samples: samples per pixel behind each mean (for var_ratio only).
Comparison compare(const BatchStats& ours, const std::vector<float>& ref, const std::vector<float>& ref_se,
                   int ref_batches, double ours_samples, double ref_samples) {
  REQUIRE(ours.mean.size() == ref.size());
  REQUIRE(ref_se.size() == ref.size());
  Comparison c;
  c.z.assign(ref.size(), 0.f);
  struct Acc {
    size_t n = 0;
    double ref = 0, diff = 0, var = 0, z = 0, z2 = 0, ez2 = 0, abs_diff = 0, se = 0, z4 = 0, max_z = 0, vo = 0, vr = 0;
  } acc[4];
  const double nu_o = ours.n - 1, nu_r = ref_batches - 1;
  for (size_t i = 0; i < ref.size(); ++i) {
    const double so = ours.se(i), sr = ref_se[i], d = ours.mean[i] - ref[i];
    if (so == 0 && sr == 0) {
      ++c.zero_se;
      c.zero_se_max_abs = std::max(c.zero_se_max_abs, std::abs(d));
      if (ref[i] != 0) c.zero_se_max_rel = std::max(c.zero_se_max_rel, std::abs(d / ref[i]));
      continue;
    }
    const double var = so * so + sr * sr, z = d / std::sqrt(var);
    // Welch–Satterthwaite: z is approximately Student-t with nu degrees of freedom, E[z²] = nu/(nu−2).
    const double nu = var * var / (std::pow(so, 4) / nu_o + std::pow(sr, 4) / nu_r);
    c.z[i] = float(z);
    for (Acc* a : {&acc[i % 3], &acc[3]}) {
      ++a->n;
      a->ref += ref[i];
      a->diff += d;
      a->var += var;
      a->z += z;
      a->z2 += z * z;
      a->ez2 += nu > 2 ? nu / (nu - 2) : 3.0;
      a->abs_diff += std::abs(d);
      a->se += std::sqrt(var);
      a->z4 += std::abs(z) > 4 ? 1 : 0;
      a->max_z = std::max(a->max_z, std::abs(z));
      a->vo += ours_samples * so * so;
      a->vr += ref_samples * sr * sr;
    }
  }
  for (int k = 0; k < 4; ++k) {
    const Acc& a = acc[k];
    Metrics& m = k < 3 ? c.channel[k] : c.all;
    const double n = double(a.n);
    m.count = a.n;
    if (a.n == 0) continue;
    m.mean_ref = a.ref / n;
    m.mean_diff = a.diff / n;
    m.bias_se = std::sqrt(a.var) / n;
    m.bias_z = m.mean_diff / m.bias_se;
    m.rel_bias = std::abs(m.mean_diff) / std::abs(m.mean_ref);
    m.z_mean = a.z / n;
    m.z_std = std::sqrt(std::max(0.0, a.z2 / n - m.z_mean * m.z_mean));
    m.z_std_expected = std::sqrt(a.ez2 / n);
    m.mad = a.abs_diff / n;
    m.mean_se = a.se / n;
    m.mad_ratio = m.mad / m.mean_se;
    m.frac_z4 = a.z4 / n;
    m.max_abs_z = a.max_z;
    m.var_ratio = a.vo / a.vr;
  }
  return c;
}

void print(const std::string& name, const Comparison& c) {
  std::printf("%s: %zu elements compared, %zu excluded (both se = 0; there max |diff| %.3g, max rel %.3g)\n",
              name.c_str(), c.all.count, c.zero_se, c.zero_se_max_abs, c.zero_se_max_rel);
  std::printf("  %-3s %11s %11s %10s %8s %9s %7s %7s %7s %7s %8s %7s %7s\n", "ch", "mean_ref", "mean_diff", "bias_se",
              "bias_z", "rel_bias", "z_mean", "z_std", "z_exp", "mad/se", "|z|>4", "max|z|", "var_o/r");
  const char* names[4] = {"R", "G", "B", "all"};
  for (int k = 0; k < 4; ++k) {
    const Metrics& m = k < 3 ? c.channel[k] : c.all;
    // The pooled row has no bias z: the channels of one pixel are correlated, so bias_se would
    // be too small there.
    if (k < 3)
      std::printf("  %-3s %11.4e %11.3e %10.3e %8.2f %8.4f%%", names[k], m.mean_ref, m.mean_diff, m.bias_se, m.bias_z,
                  100 * m.rel_bias);
    else
      std::printf("  %-3s %11.4e %11.3e %10s %8s %9s", names[k], m.mean_ref, m.mean_diff, "-", "-", "-");
    std::printf(" %7.3f %7.3f %7.3f %7.3f %7.4f%% %7.1f %7.3f\n", m.z_mean, m.z_std, m.z_std_expected, m.mad_ratio,
                100 * m.frac_z4, m.max_abs_z, m.var_ratio);
  }
  std::fflush(stdout);
}

// The per-element checks shared by images and gradients. `check_rel_bias`: images only (see
// README: for the gradient the relative bias is reported, the z-test decides).
void check(const std::string& name, const Comparison& c, bool check_rel_bias) {
  const char* names[3] = {"R", "G", "B"};
  for (int k = 0; k < 3; ++k) {
    const Metrics& m = c.channel[k];
    INFO(name << " channel " << names[k]);
    CHECK(m.count > 0);
    CHECK(std::abs(m.bias_z) < kMaxBiasZ);
    if (check_rel_bias) CHECK(m.rel_bias < kMaxRelBias);
    CHECK(m.z_std > kZStdLow);
    CHECK(m.z_std < kZStdHigh);
    CHECK(m.mad_ratio < kMaxMadRatio);
  }
  INFO(name << " all channels");
  CHECK(c.all.z_std > kZStdLow);
  CHECK(c.all.z_std < kZStdHigh);
}

void dump(const std::string& name, int width, int height, const BatchStats& ours, const Comparison& c) {
  const char* dir = std::getenv("BL_REF_DUMP");
  if (!dir || !*dir) return;
  std::filesystem::create_directories(dir);
  Image mean(width, height), se(width, height), z(width, height);
  for (size_t i = 0; i < ours.mean.size(); ++i) {
    mean.data[i] = float(ours.mean[i]);
    se.data[i] = float(ours.se(i));
    z.data[i] = c.z[i];
  }
  write_image(std::string(dir) + "/" + name + "_ours.exr", mean);
  write_image(std::string(dir) + "/" + name + "_ours_stderr.exr", se);
  write_image(std::string(dir) + "/" + name + "_z.exr", z);
}

nlohmann::json metadata(const std::string& dir = kData) {
  std::ifstream in(dir + "metadata.json");
  REQUIRE(in.good());
  return nlohmann::json::parse(in);
}

void compare_image(const std::string& scene_path, int max_depth, const std::string& product, uint64_t seed0,
                   const std::string& data = kData) {
  const auto t0 = std::chrono::steady_clock::now();
  const int batches = budget("BL_REF_IMAGE_BATCHES", BL_REF_IMAGE_BATCHES);
  const int spp = budget("BL_REF_IMAGE_SPP", BL_REF_IMAGE_SPP);
  const nlohmann::json pmeta = metadata(data)["products"][product];
  const int ref_batches = pmeta["batches"].get<int>();
  const double ref_spp = pmeta["spp_total"].get<double>();
  // The surface references nest the integrator's settings; the volume references list them flat.
  const auto& settings = pmeta["integrator"].is_object() ? pmeta["integrator"] : pmeta;
  REQUIRE(settings["max_depth"].get<int>() == max_depth);
  Image ref = read_image(data + product + ".exr", false);
  Image ref_se = read_image(data + product + "_stderr.exr", false);

  auto scene = load_scene(scene_path);
  scene->settings.max_depth = max_depth;
  scene->settings.rr_depth = 5;
  REQUIRE(scene->cameras.at(0).width == ref.width);
  REQUIRE(scene->cameras.at(0).height == ref.height);
  REQUIRE(ref.channels == 3);
  BatchStats ours;
  for (int b = 0; b < batches; ++b) {
    PassOptions o;
    o.spp = spp;
    o.seed = seed0 + seed_offset() + uint64_t(b);
    o.progress = false;
    ours.add(render(*scene, o).data);
  }
  const Comparison c = compare(ours, ref.data, ref_se.data, ref_batches, double(batches) * spp, ref_spp);
  std::printf("\n%s (max_depth %d): ours %d batches x %d spp, %.1f s\n", product.c_str(), max_depth, batches, spp,
              seconds_since(t0));
  print(product, c);
  dump(product, ref.width, ref.height, ours, c);
  check(product, c, true);
  // Excluded pixels see a constant on both sides (black outside the box, pure emission at depth
  // 2): they must agree to float rounding.
  CHECK(c.zero_se_max_abs < 1e-4);
}

}  // namespace

TEST_CASE("mitsuba3 cornell: ref_depth2", "[reference]") { compare_image(kScene, 2, "ref_depth2", 1000); }
TEST_CASE("mitsuba3 cornell: ref_depth6", "[reference]") { compare_image(kScene, 6, "ref_depth6", 2000); }
TEST_CASE("mitsuba3 cornell: ref_textured_depth2", "[reference]") {
  compare_image(kTextured, 2, "ref_textured_depth2", 3000);
}
TEST_CASE("mitsuba3 cornell: ref_textured_depth6", "[reference]") {
  compare_image(kTextured, 6, "ref_textured_depth6", 4000);
}

// A 64³ density grid inside an index-matched (null) box in the Cornell room, Mitsuba's volpath:
// delta tracking, ratio-tracked shadow rays, NEE + MIS at medium vertices, HG g = 0.4.
TEST_CASE("mitsuba3 volume: ref_depth2", "[reference][volume]") {
  compare_image(kVolumeScene, 2, "ref_depth2", 5000, kVolumeData);
}
TEST_CASE("mitsuba3 volume: ref_depth8", "[reference][volume]") {
  compare_image(kVolumeScene, 8, "ref_depth8", 6000, kVolumeData);
}

TEST_CASE("mitsuba3 cornell: prb gradient wrt the back-wall texture", "[reference]") {
  const auto t0 = std::chrono::steady_clock::now();
  const int batches = budget("BL_REF_GRAD_BATCHES", BL_REF_GRAD_BATCHES);
  const int spp = budget("BL_REF_GRAD_SPP", BL_REF_GRAD_SPP);
  const nlohmann::json meta = metadata();
  const nlohmann::json& gmeta = meta["products"]["grad_wall_texture"];
  const int ref_batches = gmeta["batches"].get<int>();
  REQUIRE(gmeta["integrator"]["max_depth"].get<int>() == 6);
  const Image adjoint = read_image(kData + "adjoint.exr", false);
  const Image ref = read_image(kData + "grad_wall_texture_64.exr", false);
  const Image ref_se = read_image(kData + "grad_wall_texture_64_stderr.exr", false);
  REQUIRE(ref.width == 64);
  REQUIRE(ref.height == 64);

  auto scene = load_scene(kTextured);
  scene->settings.max_depth = 6;
  scene->settings.rr_depth = 5;
  const int h = scene->params.find(kWallParam);
  REQUIRE(h >= 0);
  const int tw = scene->params[h].width(), th = scene->params[h].height();
  REQUIRE(tw == 512);
  REQUIRE(th == 512);
  REQUIRE(scene->params[h].channels() == 3);
  constexpr int kBlock = 8;

  BatchStats blocks, sums, functional;
  for (int b = 0; b < batches; ++b) {
    scene->params.require_grad({kWallParam});
    GradientRequest rq;
    rq.method = GradientMethod::Prb;
    rq.adjoint_image = &adjoint;
    rq.pass.spp = spp;
    rq.pass.seed = 5000 + seed_offset() + uint64_t(b);
    rq.pass.progress = false;
    rq.adjoint_seed = rq.pass.seed;  // fused: the exact derivative of this batch's estimate of F
    const GradientResult r = compute_gradient(*scene, rq);
    const std::vector<float>& g = scene->params[h].grad;
    // Block means: block (I, J) covers texel rows 8I..8I+7 and columns 8J..8J+7 (our texel
    // layout is the reference's: row 0 at v ≈ 0, the bottom of the wall).
    std::vector<double> block(64 * 64 * 3, 0.0), sum(3, 0.0), f(3, 0.0);
    for (int i = 0; i < th; ++i)
      for (int j = 0; j < tw; ++j)
        for (int ch = 0; ch < 3; ++ch) {
          const double v = g[(size_t(i) * tw + j) * 3 + ch];
          block[((i / kBlock) * 64 + j / kBlock) * 3 + ch] += v / (kBlock * kBlock);
          sum[ch] += v;
        }
    for (size_t i = 0; i < r.image.data.size(); ++i) f[i % 3] += double(adjoint.data[i]) * r.image.data[i];
    blocks.add(block);
    sums.add(sum);
    functional.add(f);
  }
  const double elapsed = seconds_since(t0);

  const Comparison c =
      compare(blocks, ref.data, ref_se.data, ref_batches, double(batches) * spp, gmeta["spp_total"].get<double>());
  std::printf("\ngrad_wall_texture_64 (prb, max_depth 6): ours %d batches x %d spp, %.1f s\n", batches, spp, elapsed);
  print("grad_wall_texture_64", c);
  dump("grad_wall_texture_64", 64, 64, blocks, c);
  check("grad_wall_texture_64", c, false);
  CHECK(c.zero_se == 0);

  // Σ over texels and F = Σ a·I per channel, against metadata.json. Their standard errors come
  // from per-batch totals on both sides, so correlations between texels are accounted for.
  const char* names[3] = {"R", "G", "B"};
  std::printf("  %-22s %3s %13s %13s %13s %11s %8s\n", "total", "ch", "ours", "ref", "diff", "se", "z");
  for (int ch = 0; ch < 3; ++ch) {
    for (int which = 0; which < 2; ++which) {
      const BatchStats& s = which == 0 ? sums : functional;
      const double ref_v = which == 0 ? gmeta["sum_over_texels"][ch].get<double>()
                                      : meta["F_textured_depth6"]["per_channel"][ch].get<double>();
      const double ref_e = which == 0 ? gmeta["sum_over_texels_stderr"][ch].get<double>()
                                      : meta["F_textured_depth6"]["per_channel_stderr"][ch].get<double>();
      const double se = std::hypot(s.se(size_t(ch)), ref_e), d = s.mean[size_t(ch)] - ref_v, z = d / se;
      const char* label = which == 0 ? "sum over texels dF/dθ" : "F = sum(a*I)";
      std::printf("  %-22s %3s %13.6e %13.6e %13.3e %11.3e %8.2f (rel %.4f%%)\n", label, names[ch], s.mean[size_t(ch)],
                  ref_v, d, se, z, 100 * std::abs(d / ref_v));
      INFO(label << " channel " << names[ch]);
      CHECK(std::abs(z) < kMaxBiasZ);
    }
  }
  std::fflush(stdout);
}
