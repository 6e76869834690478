// Participating media through the whole engine: Beer–Lambert through a null-bounded slab, the
// white furnace, prb against the taped oracle on the same random numbers, and gradients against
// finite differences in expectation over seeds (free-flight sampling depends on the density, so
// same-seed differences jump; both sides are averaged over seeds and compared with |z| < 4),
// with negative controls, majorant independence and exact zeros where no path reaches.
#include <tbb/global_control.h>
#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <tuple>
#include <vector>

#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/optimize/large_steps.h"
#include "engine/optimize/optimizer.h"
#include "engine/optimize/resample.h"
#include "engine/scene/mesh_io.h"
#include "engine/scene/scene_load.h"
#include "engine/scene/volume_io.h"
#include "test_scenes.h"

using namespace bl;

namespace {

struct FogOptions {
  int resolution = 24;
  int max_depth = 6;
  int rr_depth = 4;
  float headroom = 1.25f;
  bool albedo_grid = false;
  bool surfaces = true;     // floor, back wall and area light (else: only a constant environment)
  float environment = 0.f;  // constant environment radiance (0: none)
  float albedo = -1.f;      // grey albedo override (< 0: coloured (0.8, 0.6, 0.4))
  float g = 0.3f;
  float scale = 1.5f;
  bool dense_constant = false;    // density 1 everywhere (furnace)
  bool blob = false;              // a smooth off-centre blob instead of random voxels
  float light_derivatives = 0.f;  // the medium's light_derivatives (0: off)
  float homogeneous = 0.f;        // > 0: a homogeneous medium of this density instead of the grid
};

// A fog box ([-0.6, 0.6]³, 8³ random density, null boundary) over a floor, in front of a back
// wall, under a small area light; the camera looks at it from +z.
std::string write_fog_scene(const std::string& dir, const FogOptions& o) {
  VolumeGrid density;
  density.x = density.y = density.z = 8;
  density.bbox_min = {-0.6f, -0.6f, -0.6f};
  density.bbox_max = {0.6f, 0.6f, 0.6f};
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  for (int i = 0; i < 512; ++i) {
    const float x = (float(i % 8) + 0.5f) / 8.f - 0.35f, y = (float(i / 8 % 8) + 0.5f) / 8.f - 0.6f,
                z = (float(i / 64) + 0.5f) / 8.f - 0.5f;
    density.data.push_back(o.dense_constant ? 1.f
                           : o.blob         ? 3.f * std::exp(-(x * x + y * y + z * z) / 0.04f)
                                            : 2.f * u(rng) * u(rng));
  }
  write_vol(dir + "/density.vol", density);
  if (o.albedo_grid) {
    VolumeGrid albedo = density;
    albedo.x = albedo.y = albedo.z = 4;
    albedo.channels = 3;
    albedo.data.clear();
    for (int i = 0; i < 64 * 3; ++i) albedo.data.push_back(0.3f + 0.6f * u(rng));
    write_vol(dir + "/albedo.vol", albedo);
  }
  const std::string albedo = o.albedo_grid     ? R"({"type": "vol", "file": "albedo.vol"})"
                             : o.albedo >= 0.f ? std::to_string(o.albedo)
                                               : "[0.8, 0.6, 0.4]";
  std::string json =
      R"({
  "integrator": {"spp": 4, "max_depth": )" +
      std::to_string(o.max_depth) + R"(, "rr_depth": )" + std::to_string(o.rr_depth) + R"(},
  "cameras": [{"origin": [0, 0.3, 3.5], "target": [0, 0, 0], "fov": 40, "resolution": [)" +
      std::to_string(o.resolution) + ", " + std::to_string(o.resolution) + R"(]}],
  "media": {"fog": {"type": )" +
      (o.homogeneous > 0.f ? R"("homogeneous", "density": )" + std::to_string(o.homogeneous)
                           : std::string(R"("grid", "density": {"type": "vol", "file": "density.vol"})")) +
      R"(, "albedo": )" + albedo + R"(, "scale": )" + std::to_string(o.scale) + R"(, "phase": {"type": "hg", "g": )" +
      std::to_string(o.g) + R"(}, "majorant_headroom": )" + std::to_string(o.headroom) + R"(, "light_derivatives": )" +
      std::to_string(o.light_derivatives) + R"(}},
  "materials": {"wall": {"type": "diffuse", "albedo": [0.6, 0.5, 0.4]},
                "boundary": {"type": "null"},
                "lamp": {"type": "diffuse", "albedo": 0.0}},
  "shapes": [
    {"name": "box", "type": "cube", "material": "boundary", "interior": "fog", "transform": {"scale": 0.6}})";
  if (o.surfaces)
    json += R"(,
    {"name": "floor", "type": "rectangle", "material": "wall",
     "transform": {"scale": 3, "rotate": {"axis": [1, 0, 0], "angle": -90}, "translate": [0, -0.8, 0]}},
    {"name": "back", "type": "rectangle", "material": "wall", "transform": {"scale": 3, "translate": [0, 0, -1.5]}},
    {"name": "light", "type": "rectangle", "material": "lamp", "emitter": {"radiance": [12, 11, 9]},
     "transform": {"scale": 0.4, "rotate": {"axis": [1, 0, 0], "angle": 90}, "translate": [0.3, 1.6, 0.2]}})";
  json += "\n  ]";
  if (o.environment > 0.f)
    json += R"(,
  "environment": {"type": "constant", "radiance": )" +
            std::to_string(o.environment) + "}";
  json += "\n}\n";
  std::ofstream(dir + "/scene.json") << json;
  return dir + "/scene.json";
}

std::unique_ptr<Scene> fog_scene(const FogOptions& o = {}) {
  static int counter = 0;
  return load_scene(write_fog_scene(test::temp_dir("media" + std::to_string(counter++)), o));
}

// A fixed positive weight image: F = Σ a·I.
Image weights(int w, int h) {
  Image a(w, h, 3);
  std::mt19937 rng(17);
  std::uniform_real_distribution<float> u(0.2f, 1.f);
  for (float& v : a.data) v = u(rng);
  return a;
}

double functional(const Image& a, const Image& img) {
  double f = 0;
  for (size_t i = 0; i < img.data.size(); ++i) f += double(a.data[i]) * img.data[i];
  return f;
}

struct MeanSe {
  double mean = 0, se = 0;
};
MeanSe stats(const std::vector<double>& x) {
  double m = 0, v = 0;
  for (double e : x) m += e;
  m /= double(x.size());
  for (double e : x) v += (e - m) * (e - m);
  return {m, std::sqrt(v / double(x.size() - 1) / double(x.size()))};
}

// The mean pixel value of `batches` renders (seeds seed0, seed0 + 1, ...) with its standard error
// from the spread of the batch means.
MeanSe batch_mean(const Scene& scene, int batches, int spp, uint64_t seed0) {
  std::vector<double> means;
  for (int b = 0; b < batches; ++b) {
    const Image img = render(scene, {0, spp, seed0 + uint64_t(b), false});
    double m = 0;
    for (float v : img.data) m += v;
    means.push_back(m / double(img.data.size()));
  }
  return stats(means);
}

GradientRequest functional_request(const Image& a, GradientMethod method, int spp, uint64_t seed) {
  GradientRequest rq;
  rq.method = method;
  rq.adjoint_image = &a;
  rq.pass = {0, spp, seed, false};
  rq.adjoint_seed = seed;
  return rq;
}

// ⟨∇F, v⟩ for parameter `name` (prb), one value per seed.
std::vector<double> adjoint_directional(Scene& scene, const Image& a, const std::string& name,
                                        const std::vector<float>& v, int spp, int seeds, uint64_t seed0) {
  scene.params.require_grad({name});
  const Param& p = scene.params[scene.params.find(name)];
  std::vector<double> out;
  for (int s = 0; s < seeds; ++s) {
    compute_gradient(scene, functional_request(a, GradientMethod::Prb, spp, seed0 + uint64_t(s)));
    double d = 0;
    for (size_t i = 0; i < v.size(); ++i) d += double(p.grad[i]) * v[i];
    out.push_back(d);
  }
  return out;
}

// (F(θ + hv) − F(θ − hv)) / 2h per seed (the same seed on both sides). Majorants stay those of θ
// (a sampling decision, valid while σ_t stays under them).
std::vector<double> finite_differences(Scene& scene, const Image& a, const std::string& name,
                                       const std::vector<float>& v, double h, int spp, int seeds, uint64_t seed0) {
  Param& p = scene.params[scene.params.find(name)];
  const std::vector<float> base = p.value;
  std::vector<double> out;
  for (int s = 0; s < seeds; ++s) {
    double f[2];
    for (int side = 0; side < 2; ++side) {
      for (size_t i = 0; i < base.size(); ++i) p.value[i] = base[i] + float((side ? -h : h) * v[i]);
      f[side] = functional(a, render(scene, {0, spp, seed0 + uint64_t(s), false}));
    }
    out.push_back((f[0] - f[1]) / (2 * h));
  }
  p.value = base;
  return out;
}

double z_score(const MeanSe& a, const MeanSe& b, double scale_a = 1.0) {
  return (scale_a * a.mean - b.mean) / std::sqrt(scale_a * scale_a * a.se * a.se + b.se * b.se);
}

// A fresh folder holding the fog scene with a blob density (the optimizer jobs' ground truth),
// rendered at `resolution`² pixels.
std::string blob_fog_dir(const std::string& name, int resolution) {
  const std::string dir = test::temp_dir(name);
  FogOptions o;
  o.resolution = resolution;
  o.blob = true;
  write_fog_scene(dir, o);
  return dir;
}

}  // namespace

TEST_CASE("Beer-Lambert: light through an absorbing slab behind a null boundary", "[media]") {
  const std::string dir = test::temp_dir("slab");
  const float sigma = 0.7f, depth = 1.f;
  std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"max_depth": 3, "rr_depth": 0},
  "cameras": [{"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 0.5, "resolution": [4, 4]}],
  "media": {"ink": {"type": "homogeneous", "density": 0.7, "albedo": 0, "scale": 1}},
  "materials": {"boundary": {"type": "null"}, "black": {"type": "diffuse", "albedo": 0}},
  "shapes": [
    {"name": "slab", "type": "cube", "material": "boundary", "interior": "ink", "transform": {"scale": 0.5}},
    {"name": "light", "type": "rectangle", "material": "black", "emitter": {"radiance": [1, 1, 1]},
     "transform": {"translate": [0, 0, -2]}}
  ]
})";
  auto scene = load_scene(dir + "/scene.json");
  const double expected = std::exp(-double(sigma) * depth);
  // Each sample is 1 (no collision) or 0: a Bernoulli mean.
  const int spp = 4096;
  const Image img = render(*scene, {0, spp, 1, false});
  double mean = 0;
  for (size_t i = 0; i < img.data.size(); i += 3) mean += img.data[i];
  mean /= double(img.pixel_count());
  const double se = std::sqrt(expected * (1 - expected) / (double(spp) * double(img.pixel_count())));
  INFO("mean " << mean << " expected " << expected << " se " << se);
  CHECK(std::abs(mean - expected) < 4 * se);

  // dT/dσ = −d·T, in expectation over seeds (prb through the null-collision terms).
  scene->params.require_grad({"ink.density"});
  Image a(4, 4, 3);
  for (float& v : a.data) v = 1.f / 48.f;  // F = mean over pixels and channels
  std::vector<double> g;
  for (int s = 0; s < 32; ++s) {
    compute_gradient(*scene, functional_request(a, GradientMethod::Prb, 256, 100 + uint64_t(s)));
    g.push_back(scene->params[scene->params.find("ink.density")].grad[0]);
  }
  const MeanSe m = stats(g);
  INFO("dT/dsigma " << m.mean << " +- " << m.se << ", exact " << -depth * expected);
  CHECK(std::abs(m.mean + depth * expected) < 4 * m.se);
  CHECK(m.se < 0.05 * depth * expected);  // the check has power
}

// Single scattering in a homogeneous sphere (radius 1, σ_t = 1, albedo 0.8, under a constant sky of
// radiance 1; max depth 2: the sky seen through the medium plus light scattered once) against a
// quadrature of the same integral, written independently of the renderer: along the camera ray,
// ∫ e^{−σ_t t} σ_s ∫ p_HG(ω_out, ω') e^{−σ_t ℓ(x_t, ω')} dω' dt + e^{−σ_t chord}, ℓ the distance to
// the sphere's surface. HG with g > 0 scatters forward (light travelling along the camera ray's
// direction, from behind the sphere). The camera, far away with a narrow field of view, sees one
// ray's neighbourhood at impact parameter b (the footprint's curvature and the tessellated sphere,
// 512 segments, each move the expectation by < 1e-4, against a standard error of ~8e-4; with 64×
// the samples the render agreed with a finer quadrature to 1σ). A camera at the centre, inside
// the medium (the camera's "medium"), sees the radius instead: rays that start in a medium.
// Negative controls: the mirrored phase function (−g) or a 10% lower albedo must fail the same
// comparison.
TEST_CASE("single scattering in a homogeneous sphere matches quadrature", "[media][expectation]") {
  const double sigma_t = 1.0, albedo = 0.8;
  // The quadrature along a ray parallel to −z at impact parameter b, unit sphere at the origin:
  // from outside, the ray crosses the whole chord; from a camera at the centre (inside: b = 0), it
  // starts in the medium and crosses the radius.
  auto quadrature = [&](double g, double b, double alb, bool inside) {
    const double z0 = inside ? 0.0 : std::sqrt(1 - b * b), length = inside ? 1.0 : 2 * z0;
    const int nt = 100, nmu = 400, nphi = 200;
    const double pi = 3.14159265358979323846;
    double single = 0;
    for (int it = 0; it < nt; ++it) {
      const double t = (it + 0.5) / nt * length;  // depth in the medium
      const double x[3] = {b, 0, z0 - t};
      double inscatter = 0;
      for (int im = 0; im < nmu; ++im) {
        // μ = cos of the angle between ω' (towards the light's origin) and the ray direction −z:
        // light arriving along −z (from behind, ω' = −z, μ = 1) scatters forward into the camera.
        const double mu = -1 + (im + 0.5) / nmu * 2, s = std::sqrt(1 - mu * mu);
        const double phase = (1 - g * g) / (4 * pi * std::pow(1 + g * g - 2 * g * mu, 1.5));
        for (int ip = 0; ip < nphi; ++ip) {
          const double phi = (ip + 0.5) / nphi * 2 * pi;
          const double w[3] = {s * std::cos(phi), s * std::sin(phi), -mu};
          const double xw = x[0] * w[0] + x[1] * w[1] + x[2] * w[2];
          const double xx = x[0] * x[0] + x[1] * x[1] + x[2] * x[2];
          const double l = -xw + std::sqrt(xw * xw - xx + 1);
          inscatter += phase * std::exp(-sigma_t * l);
        }
      }
      inscatter *= (2.0 / nmu) * (2 * pi / nphi);
      single += std::exp(-sigma_t * t) * alb * sigma_t * inscatter * (length / nt);
    }
    return single + std::exp(-sigma_t * length);
  };
  struct Case {
    double g, b;
    bool inside;
  };
  for (auto [g, b, inside] :
       {Case{0.0, 0.0, false}, Case{0.6, 0.5, false}, Case{-0.4, 0.3, false}, Case{0.6, 0.0, true}}) {
    const std::string dir = test::temp_dir("sphere_ss");
    std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"max_depth": 2, "rr_depth": 0},
  "cameras": [{"origin": [)" << b << ", 0, "
                                       << (inside ? 0 : 5) << R"(], "target": [)" << b << ", 0, " << (inside ? -1 : 0)
                                       << R"(], "fov": 0.1, "resolution": [4, 4])"
                                       << (inside ? R"(, "medium": "fog")" : "") << R"(}],
  "media": {"fog": {"type": "homogeneous", "density": 1, "scale": 1, "albedo": 0.8, "phase": {"type": "hg", "g": )"
                                       << g << R"(}}},
  "materials": {"boundary": {"type": "null"}},
  "shapes": [{"name": "ball", "type": "sphere", "segments": 512, "material": "boundary", "interior": "fog"}],
  "environment": {"type": "constant", "radiance": 1}
})";
    auto scene = load_scene(dir + "/scene.json");
    const MeanSe m = batch_mean(*scene, 16, 1024, 700);
    const double expected = quadrature(g, b, albedo, inside);
    INFO("g " << g << ", b " << b << (inside ? ", camera inside" : "") << ": render " << m.mean << " +- " << m.se
              << ", quadrature " << expected);
    CHECK(std::abs(m.mean - expected) < 4 * m.se);
    CHECK(m.se < 2e-3 * expected);  // the check has power
    // Negative controls: the same render against a wrong reference fails.
    const double lower_albedo = quadrature(g, b, 0.9 * albedo, inside);
    INFO("albedo 0.72: " << lower_albedo);
    CHECK(std::abs(m.mean - lower_albedo) > 4 * m.se);
    if (g != 0.0) {
      const double mirrored = quadrature(-g, b, albedo, inside);
      INFO("mirrored phase: " << mirrored);
      CHECK(std::abs(m.mean - mirrored) > 4 * m.se);
    }
  }
}

TEST_CASE("white furnace: an albedo-1 medium under a uniform sky renders the sky", "[media]") {
  for (float g : {-0.5f, 0.f, 0.7f}) {
    FogOptions o;
    o.surfaces = false;
    o.environment = 1.f;
    o.albedo = 1.f;
    o.g = g;
    o.max_depth = -1;
    o.rr_depth = 5;
    o.resolution = 16;
    auto scene = fog_scene(o);
    const MeanSe m = batch_mean(*scene, 16, 8, 300);
    INFO("g = " << g << ": mean " << m.mean << " +- " << m.se);
    CHECK(std::abs(m.mean - 1.0) < 4 * m.se);
    CHECK(m.se < 0.01);
  }
}

TEST_CASE("prb equals the taped oracle on the same random numbers, media and surfaces together", "[media]") {
  // Also with light derivatives (medium_light_derivative, engine/integrators/path.h): both modes
  // take the same derivative-only light samples and leave them out of the real collisions' terms.
  // Variants: 0 grid density, 1 with an albedo grid, 2 with light derivatives (f = 0.3), 3 a
  // homogeneous medium, 4 the same with light derivatives (f = 0.9: σ_t is σ̄ / 1.25 everywhere,
  // so only f > 0.8 takes them), 5 the grid with colour channels at exactly 0 in the medium's
  // albedo (green) and the wall's (red): prb's replay divided by the albedo and dropped those
  // channels' terms (35% of a green albedo gradient; ZeroChannels, path.h).
  std::vector<float> density_without_light;  // variant 0's (3's) prb density gradient
  for (int variant = 0; variant < 6; ++variant) {
    FogOptions o;
    o.albedo_grid = variant == 1;
    o.light_derivatives = variant == 2 ? 0.3f : variant == 4 ? 0.9f : 0.f;
    o.homogeneous = variant == 3 || variant == 4 ? 0.8f : 0.f;
    o.resolution = 16;
    auto scene = fog_scene(o);
    if (variant == 5) {
      scene->params[scene->params.find("fog.albedo")].value = {0.8f, 0.f, 0.4f};
      scene->params[scene->params.find("wall.albedo")].value = {0.f, 0.5f, 0.6f};
    }
    const Image a = weights(16, 16);
    const std::vector<std::string> names = {"fog.density", "fog.albedo",  "fog.scale",
                                            "fog.g",       "wall.albedo", "light.radiance"};
    scene->params.require_grad(names);
    compute_gradient(*scene, functional_request(a, GradientMethod::Prb, 4, 11));
    std::vector<std::vector<float>> prb;
    for (const auto& n : names) prb.push_back(scene->params[scene->params.find(n)].grad);
    // The light derivatives are in use: another estimate of the same density gradient.
    if (variant == 0 || variant == 3) density_without_light = prb[0];
    if (variant == 2 || variant == 4) CHECK(prb[0] != density_without_light);
    compute_gradient(*scene, functional_request(a, GradientMethod::Taped, 4, 11));
    for (size_t k = 0; k < names.size(); ++k) {
      const auto& taped = scene->params[scene->params.find(names[k])].grad;
      double diff = 0, norm = 0;
      for (size_t i = 0; i < taped.size(); ++i) {
        diff += (double(prb[k][i]) - taped[i]) * (double(prb[k][i]) - taped[i]);
        norm += double(taped[i]) * taped[i];
      }
      INFO(names[k] << " (variant " << variant << ")"
                    << ": |prb - taped| / |taped| = " << std::sqrt(diff / norm) << ", |taped| = " << std::sqrt(norm));
      CHECK(norm > 0);
      CHECK(std::sqrt(diff) <= 1e-4 * std::sqrt(norm));
    }
  }
}

// An albedo grid (4³ RGB voxels over the fog's box, trilinear): free-flight sampling reads the
// density only, and a real collision multiplies its light sample and the throughput by the
// albedo there, so without roulette same-seed differences differentiate prb's estimator. (prb
// equals the taped oracle for the grid: variant 1 of the case above.)
TEST_CASE("an albedo grid: prb matches same-seed differences without roulette", "[media]") {
  FogOptions o;
  o.albedo_grid = true;
  o.rr_depth = 0;
  o.resolution = 16;
  auto scene = fog_scene(o);
  REQUIRE(scene->params[scene->params.find("fog.albedo")].shape == std::vector<int>{4, 4, 4, 3});
  const Image a = weights(16, 16);
  // Steps of 0.02 standard-normal elements keep the texels (0.3 to 0.9) inside [0, 1].
  for (const auto& r :
       directional_check(*scene, "fog.albedo", functional_request(a, GradientMethod::Prb, 4, 11), 3, 0.02, 5)) {
    INFO("adjoint " << r.adjoint << ", finite difference " << r.finite_difference);
    CHECK(r.relative_error < 1e-3);
    CHECK(std::abs(r.finite_difference) > 0);
  }
}

// [expectation]: not under the sanitizers; the cases above run the same albedo-grid gradients.
TEST_CASE("an albedo grid with roulette: gradients match finite differences in expectation", "[media][expectation]") {
  // Roulette from the first vertex: its continuation probability reads the throughput, hence the
  // albedo, so same-seed differences jump where a decision flips and only the expectations
  // agree (the harness of "medium gradients match finite differences in expectation").
  FogOptions o;
  o.albedo_grid = true;
  o.rr_depth = 1;
  auto scene = fog_scene(o);
  const Image a = weights(24, 24);
  std::mt19937 rng(31);
  std::normal_distribution<float> normal;
  std::vector<float> v(64 * 3);
  for (float& e : v) e = std::abs(normal(rng));  // every voxel brighter: the texels' gradients add up
  const int seeds = 96, spp = 8;
  const MeanSe fd = stats(finite_differences(*scene, a, "fog.albedo", v, 0.05, spp, seeds, 5000));
  const MeanSe adjoint = stats(adjoint_directional(*scene, a, "fog.albedo", v, spp, seeds, 1000));
  const double z = z_score(adjoint, fd), z_wrong = z_score(adjoint, fd, 0.7);
  const double relative_se = std::sqrt(adjoint.se * adjoint.se + fd.se * fd.se) / std::abs(adjoint.mean);
  INFO("fog.albedo (grid): adjoint " << adjoint.mean << " +- " << adjoint.se << ", finite differences " << fd.mean
                                     << " +- " << fd.se << ", z = " << z << ", relative SE " << relative_se
                                     << "; 0.7 x adjoint: z = " << z_wrong);
  std::printf(
      "albedo grid, in expectation: adjoint %.6g ± %.2g, finite differences %.6g ± %.2g, z = %.2f, "
      "relative SE %.3f; 0.7 x adjoint: z = %.1f\n",
      adjoint.mean, adjoint.se, fd.mean, fd.se, z, relative_se, z_wrong);
  CHECK(std::abs(z) < 4);
  CHECK(relative_se < 0.05);
  CHECK(std::abs(z_wrong) > 4);
}

TEST_CASE("pruned replays through media give the same gradient", "[media][replay]") {
  // As for surfaces (test_gradients): one thread, bitwise equal gradients with and without
  // stopping replays after the last vertex that can produce a derivative. A surface parameter
  // alone leaves medium vertices out of the sites (shorter replays); a medium parameter makes
  // every iteration that tracks the fog a site (its null collisions, medium vertex and shadow rays
  // through the fog carry derivatives), so paths whose tail never meets the fog again are cut
  // short there too.
  tbb::global_control one_thread(tbb::global_control::max_allowed_parallelism, 1);
  FogOptions o;
  o.resolution = 16;
  auto fog = fog_scene(o);
  const Image a = weights(16, 16);
  const PixelAdjoint adjoint = [&](size_t pixel, const Vec3f&) {
    return Vec3f(a.data[pixel * 3], a.data[pixel * 3 + 1], a.data[pixel * 3 + 2]);
  };
  FogOptions with_light = o;
  with_light.light_derivatives = 0.3f;
  auto light_scene = fog_scene(with_light);
  for (const char* name :
       {"wall.albedo", "light.radiance", "fog.density", "fog.albedo", "fog.g", "light:fog.density"}) {
    INFO(name);
    // "light:": the same with light derivatives (derivative-only light samples in the replay).
    const bool light = std::string(name).rfind("light:", 0) == 0;
    if (light) name += 6;
    Scene* scene = light ? light_scene.get() : fog.get();
    scene->params.require_grad({name});
    const Param& p = scene->params[scene->params.find(name)];
    PassOptions po{0, 4, 11, false};
    po.replay_whole_paths = true;
    scene->params.zero_grad();
    const PassStats whole = backward(*scene, po, AdjointMethod::Prb, adjoint);
    const std::vector<float> expected = p.grad;
    po.replay_whole_paths = false;
    scene->params.zero_grad();
    const PassStats pruned = backward(*scene, po, AdjointMethod::Prb, adjoint);
    double n = 0;
    for (float g : expected) n += double(g) * g;
    CHECK(n > 0);
    CHECK(p.grad == expected);
    INFO("rays: whole paths " << whole.rays << ", pruned " << pruned.rays);
    if (std::string(name) == "wall.albedo")
      CHECK(double(pruned.rays) < 0.9 * double(whole.rays));
    else if (std::string(name).rfind("fog.", 0) == 0)
      CHECK(double(pruned.rays) < 0.95 * double(whole.rays));  // 11468 against 13292 rays
    else
      CHECK(pruned.rays <= whole.rays);
  }
}

// [expectation]: not under the sanitizers; the prb == taped and pruned-replay cases run the same
// medium gradients.
TEST_CASE("medium gradients match finite differences in expectation", "[media][expectation]") {
  auto scene = fog_scene();
  // Finite differences render the same scene with majorants 3x the block maxima, so that θ ± hv
  // stays under them (majorants change the noise, not the expectation).
  FogOptions loose;
  loose.headroom = 3.f;
  auto fd_scene = fog_scene(loose);
  const Image a = weights(24, 24);
  // Random per-voxel directions: |N(0, 1)| (a zero-mean direction mostly cancels, leaving a
  // derivative too small to test) and a signed one with a positive bias.
  std::mt19937 rng(23);
  std::normal_distribution<float> normal;
  std::vector<float> density_direction(512), signed_direction(512);
  for (float& v : density_direction) v = std::abs(normal(rng));
  for (float& v : signed_direction) v = 0.7f + normal(rng);
  struct Case {
    std::string name;
    std::vector<float> v;
    double h;
  };
  const Case cases[] = {{"fog.scale", {1.f}, 0.1},
                        {"fog.density", density_direction, 0.1},
                        {"fog.density", signed_direction, 0.1},
                        {"fog.albedo", {1.f, -0.5f, 0.3f}, 0.05},
                        {"fog.g", {1.f}, 0.05}};
  // The same σ_t derivatives with light derivatives (medium_light_derivative in
  // engine/integrators/path.h: derivative-only light samples at tentative collisions, left out
  // of the real collisions' score terms) must have the same expectation.
  FogOptions with_light;
  with_light.light_derivatives = 0.3f;
  auto light_scene = fog_scene(with_light);
  const int seeds = 96, spp = 8;
  for (const auto& c : cases) {
    const MeanSe fd = stats(finite_differences(*fd_scene, a, c.name, c.v, c.h, spp, seeds, 5000));
    const bool sigma_t = c.name == "fog.scale" || c.name == "fog.density";
    for (Scene* s : {scene.get(), sigma_t ? light_scene.get() : nullptr}) {
      if (!s) continue;
      const MeanSe adjoint = stats(adjoint_directional(*s, a, c.name, c.v, spp, seeds, 1000));
      const double z = z_score(adjoint, fd);
      INFO(c.name << (s == light_scene.get() ? " (light derivatives)" : "") << ": adjoint " << adjoint.mean << " +- "
                  << adjoint.se << ", finite differences " << fd.mean << " +- " << fd.se << ", z = " << z);
      CHECK(std::abs(z) < 4);
      // Negative control: a gradient 30% too small (Mitsuba 3's prbvolpath once had g's 10x off,
      // and its density gradient moved by 10% with the majorant) must fail the same test.
      const double z_wrong = z_score(adjoint, fd, 0.7);
      INFO("0.7 x adjoint: z = " << z_wrong);
      CHECK(std::abs(z_wrong) > 4);
    }
  }
}

// Light derivatives where the fog test above rarely goes: (1) max depth 2 — a real collision at
// the last allowed vertex takes no light sample (max depth ends the path there), so no
// derivative-only light sample may stand in for one (the max-depth condition of trace_path's
// light derivatives; taking them anyway moves the scale and density derivatives by 27% and 33%);
// (2) two emitters (the area light and a constant sky, each light sample choosing one) with
// Russian roulette from the first vertex; (3) a homogeneous medium (σ_t = σ̄ / 1.25 everywhere:
// with f = 0.9 every tentative collision takes the derivative-only light sample).
TEST_CASE("light derivatives stay unbiased at max depth, with two emitters and roulette, in homogeneous media",
          "[media][expectation]") {
  FogOptions shallow;
  shallow.max_depth = 2;
  FogOptions two_emitters;
  two_emitters.environment = 0.5f;
  two_emitters.rr_depth = 1;
  two_emitters.max_depth = 5;
  const Image a = weights(24, 24);
  std::mt19937 rng(29);
  std::normal_distribution<float> normal;
  std::vector<float> density_direction(512);
  for (float& v : density_direction) v = std::abs(normal(rng));
  FogOptions homogeneous;
  homogeneous.homogeneous = 0.8f;
  homogeneous.light_derivatives = 0.9f;
  const int seeds = 96, spp = 8;
  for (FogOptions o : {shallow, two_emitters, homogeneous}) {
    if (o.light_derivatives == 0.f) o.light_derivatives = 0.3f;
    auto scene = fog_scene(o);
    FogOptions loose = o;
    loose.headroom = 3.f;
    auto fd_scene = fog_scene(loose);
    const std::string setting = o.homogeneous > 0.f   ? "homogeneous, f = 0.9"
                                : o.environment > 0.f ? "two emitters, roulette from vertex 1"
                                                      : "max depth 2";
    const std::vector<float> density_v = o.homogeneous > 0.f ? std::vector<float>{1.f} : density_direction;
    for (const auto& [name, v] :
         {std::pair<std::string, std::vector<float>>{"fog.scale", {1.f}}, {"fog.density", density_v}}) {
      const MeanSe fd = stats(finite_differences(*fd_scene, a, name, v, 0.1, spp, seeds, 7000));
      const MeanSe adjoint = stats(adjoint_directional(*scene, a, name, v, spp, seeds, 3000));
      const double z = z_score(adjoint, fd), z_wrong = z_score(adjoint, fd, 0.7);
      INFO(name << " (" << setting << "): adjoint " << adjoint.mean << " +- " << adjoint.se << ", finite differences "
                << fd.mean << " +- " << fd.se << ", z = " << z << "; 0.7 x adjoint: z = " << z_wrong);
      CHECK(std::abs(z) < 4);
      CHECK(std::abs(z_wrong) > 4);
    }
  }
}

TEST_CASE("the density gradient does not depend on the majorant", "[media]") {
  // Majorants are sampling decisions: 1.25x and 3x the block maxima give the same expectation.
  FogOptions tight, loose;
  loose.headroom = 3.f;
  auto a_scene = fog_scene(tight);
  auto b_scene = fog_scene(loose);
  const Image a = weights(24, 24);
  std::vector<float> v(512);
  std::mt19937 rng(29);
  std::normal_distribution<float> normal;
  for (float& e : v) e = std::abs(normal(rng));
  const MeanSe ga = stats(adjoint_directional(*a_scene, a, "fog.density", v, 8, 64, 2000));
  const MeanSe gb = stats(adjoint_directional(*b_scene, a, "fog.density", v, 8, 64, 3000));
  INFO("headroom 1.25: " << ga.mean << " +- " << ga.se << "; headroom 3: " << gb.mean << " +- " << gb.se);
  CHECK(std::abs(z_score(ga, gb)) < 4);
  // Power: a 10% shift (what Mitsuba 3's prbvolpath showed between two majorants) is resolved.
  CHECK(std::abs(z_score(ga, gb, 0.9)) > 4);
}

TEST_CASE("voxels no path reaches get exactly zero gradient", "[media]") {
  // The camera sees only the left part of a wide, purely absorbing fog slab (albedo 0: nothing
  // scatters into the rest) lit from behind; voxels beyond the footprint of the visible rays
  // must get exactly 0.
  const std::string dir = test::temp_dir("unreached");
  VolumeGrid density;
  density.x = 16;
  density.y = density.z = 4;
  density.bbox_min = {-2.f, -0.5f, -0.5f};
  density.bbox_max = {6.f, 0.5f, 0.5f};
  density.data.assign(size_t(16 * 4 * 4), 0.5f);
  write_vol(dir + "/density.vol", density);
  std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"max_depth": 4},
  "cameras": [{"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 10, "resolution": [8, 8]}],
  "media": {"ink": {"type": "grid", "density": {"type": "vol", "file": "density.vol"}, "albedo": 0}},
  "materials": {"boundary": {"type": "null"}, "black": {"type": "diffuse", "albedo": 0}},
  "shapes": [
    {"name": "slab", "type": "cube", "material": "boundary", "interior": "ink",
     "transform": {"scale": [4, 0.5, 0.5], "translate": [2, 0, 0]}},
    {"name": "light", "type": "rectangle", "material": "black", "emitter": {"radiance": [1, 1, 1]},
     "transform": {"translate": [0, 0, -2]}}
  ]
})";
  auto scene = load_scene(dir + "/scene.json");
  scene->params.require_grad({"ink.density"});
  Image a(8, 8, 3);
  for (float& v : a.data) v = 1.f;
  compute_gradient(*scene, functional_request(a, GradientMethod::Prb, 16, 1));
  const auto& g = scene->params[scene->params.find("ink.density")].grad;
  // Visible rays cross x ∈ [−0.45, 0.45] (voxels 3..4, 0.5 wide, from x = −2); the trilinear
  // footprint reaches one voxel further.
  double seen = 0, unseen = 0;
  for (int z = 0; z < 4; ++z)
    for (int y = 0; y < 4; ++y)
      for (int x = 0; x < 16; ++x) {
        const float v = g[size_t((z * 4 + y) * 16 + x)];
        (x >= 2 && x <= 5 ? seen : unseen) += std::abs(double(v));
        if (x >= 7) CHECK(v == 0.f);
      }
  CHECK(seen > 0);
  CHECK(unseen < 0.05 * seen);
}

TEST_CASE("grid resampling: constants stay, linear ramps upsample exactly, downsampling averages",
          "[media][optimize]") {
  std::vector<float> ramp;
  for (int z = 0; z < 4; ++z)
    for (int y = 0; y < 2; ++y)
      for (int x = 0; x < 4; ++x) ramp.push_back(float(x) + 10.f * float(z));
  // 4×2×4 → 8×2×8: interior samples of a linear function are exact (the clamped borders hold).
  const auto up = resample_grid(ramp, 4, 2, 4, 1, 8, 2, 8);
  REQUIRE(up.size() == 128);
  for (int z = 1; z < 7; ++z)
    for (int x = 1; x < 7; ++x) {
      const float expected = ((x + 0.5f) / 2.f - 0.5f) + 10.f * ((z + 0.5f) / 2.f - 0.5f);
      CHECK(std::abs(up[size_t((z * 2 + 1) * 8 + x)] - expected) < 1e-5f);
    }
  const auto down = resample_grid(up, 8, 2, 8, 1, 4, 2, 4);
  double sum_up = 0, sum_down = 0;
  for (float v : up) sum_up += v;
  for (float v : down) sum_down += v;
  CHECK(std::abs(sum_up / 128 - sum_down / 32) < 1e-4);
  const auto constant = resample_grid(std::vector<float>(27 * 3, 0.25f), 3, 3, 3, 3, 5, 7, 2);
  REQUIRE(constant.size() == size_t(5 * 7 * 2 * 3));
  for (float v : constant) CHECK(v == Approx(0.25f));
}

// [expectation]: not under the sanitizers; the schedule-stages case runs the same grid optimization.
TEST_CASE("optimize recovers a density grid coarse to fine from a constant start", "[media][optimize][expectation]") {
  const std::string dir = blob_fog_dir("gridopt", 24);
  std::ofstream(dir + "/opt.json") << R"({
  "scene": "scene.json", "output": "out",
  "parameters": {"fog.density": {"lr": 0.1, "bounds": [0, 4], "init": 0.5,
    "schedule": [{"until": 30, "resolution": [4, 4, 4]}, {"until": 150, "resolution": [8, 8, 8]}],
    "regularizer": {"type": "tv", "weight": 0.001}}},
  "views": {"ring": {"count": 4, "radius": 3.5, "height": 0.5, "fov": 40},
            "reference": {"set": {"fog.density": "density.vol"}, "spp": 32}},
  "resolution": [24, 24], "spp": 8, "adjoint_spp": 8, "iterations": 150, "seed": 2,
  "checkpoint_every": 20, "snapshot_every": 20
})";
  REQUIRE(run_optimize(dir + "/opt.json", "", 0, true) == 0);
  std::ifstream in(dir + "/out/summary.json");
  const auto summary = nlohmann::json::parse(in);
  const auto& p = summary["parameters"]["fog.density"];
  INFO("RMSE " << p["rmse_initial"] << " -> " << p["rmse_final"]);
  CHECK(p["rmse_final"].get<double>() < 0.6 * p["rmse_initial"].get<double>());
  CHECK(p["rmse_resolution"] == nlohmann::json({8, 8, 8}));
  for (const char* f :
       {"slices.png", "final/fog.density.vol", "final/fog.density.png", "snapshots/fog.density_00020.vol"})
    CHECK(std::filesystem::exists(dir + "/out/" + f));
  const VolumeGrid final_grid = read_vol(dir + "/out/final/fog.density.vol");
  CHECK(final_grid.x == 8);
  CHECK(final_grid.bbox_min.x == -0.6f);
}

namespace {

// One optimizer iteration on the blob fog of `dir` (blob_fog_dir) from a constant `init`: Adam
// with lr 0.1 and bounds [0, 4], `extra` adding keys to the parameter's entry; the grid it ends with.
VolumeGrid one_density_step(const std::string& dir, const std::string& name, double init, const std::string& extra) {
  std::ofstream(dir + "/" + name + ".json") << R"({
  "scene": "scene.json", "output": ")" + name + R"(",
  "parameters": {"fog.density": {"lr": 0.1, "bounds": [0, 4], "init": )" +
                                                   std::to_string(init) + extra + R"(}},
  "views": {"ring": {"count": 2, "radius": 3.5, "height": 0.5, "fov": 40},
            "reference": {"set": {"fog.density": "density.vol"}, "spp": 4}},
  "resolution": [12, 12], "spp": 2, "adjoint_spp": 2, "iterations": 1, "seed": 3
})";
  REQUIRE(run_optimize(dir + "/" + name + ".json", "", 0, true) == 0);
  return read_vol(dir + "/" + name + "/final/fog.density.vol");
}

}  // namespace

// Large steps on a density grid (engine/optimize/large_steps.h): Adam steps on u = (I + λL) x.
// Its first step moves each element of u by lr·ĝ/(|ĝ| + ε) (±lr, a little less where the gradient
// is tiny), so M = I + λL applied to the change of x is bounded by lr and mostly ±lr; the same
// first step on x itself (plain Adam) changes x by ±lr with sign changes between neighbours, so
// M times its change exceeds lr (the check's teeth). Bounds hold for x.
TEST_CASE("large steps on a density grid step on u = (I + lambda L) x, and bounds hold for x", "[media][optimize]") {
  const std::string dir = blob_fog_dir("gridls", 8);
  const double lr = 0.1, lambda = 3;
  auto run = [&](const std::string& name, double init, const std::string& extra) {
    return one_density_step(dir, name, init, extra);
  };
  const GridDims d{8, 8, 8, 1};
  const std::vector<float> x0(size_t(8 * 8 * 8), 0.5f);
  const std::vector<float> m_x0 = grid_apply_m(d, lambda, x0);
  // Largest |M Δx| and the share of voxels with |M Δx| ≥ 0.95 lr among those that moved.
  auto u_steps = [&](const VolumeGrid& x) {
    REQUIRE(x.data.size() == x0.size());
    const std::vector<float> m_x = grid_apply_m(d, lambda, x.data);
    double largest = 0;
    int moved = 0, full = 0;
    for (size_t i = 0; i < m_x.size(); ++i) {
      const double step = std::abs(double(m_x[i]) - double(m_x0[i]));
      largest = std::max(largest, step);
      moved += step > 1e-5;
      full += step >= 0.95 * lr;
    }
    return std::make_tuple(largest, moved, full);
  };
  const std::string large_steps = R"(, "large_steps": {"lambda": 3, "uniform_adam": false})";
  const auto [largest, moved, full] = u_steps(run("ls", 0.5, large_steps));
  INFO("large steps: largest |M dx| " << largest << ", " << full << " of " << moved << " moved voxels at >= 0.95 lr");
  CHECK(largest <= lr * (1 + 1e-4));
  CHECK(moved > 100);
  CHECK(full >= 0.8 * moved);
  const auto [plain_largest, plain_moved, plain_full] = u_steps(run("plain", 0.5, ""));
  INFO("plain Adam: largest |M dx| " << plain_largest);
  CHECK(plain_largest > 1.5 * lr);
  // A schedule stage's large_steps_lambda is the λ of its iterations: the same step, bit for bit;
  // 0 turns large steps off for the stage (plain Adam's step, bit for bit).
  const VolumeGrid ls = read_vol(dir + "/ls/final/fog.density.vol"),
                   plain = read_vol(dir + "/plain/final/fog.density.vol");
  CHECK(run("stage", 0.5, R"(, "schedule": [{"until": 1, "resolution": [8, 8, 8], "large_steps_lambda": 3}])").data ==
        ls.data);
  CHECK(
      run("off", 0.5, large_steps + R"(, "schedule": [{"until": 1, "resolution": [8, 8, 8], "large_steps_lambda": 0}])")
          .data == plain.data);
  // From 0.02 a step of ±0.1 would leave [0, 4]: x is clamped to the bounds.
  const VolumeGrid low = run("low", 0.02, large_steps);
  CHECK(*std::min_element(low.data.begin(), low.data.end()) == 0.f);
}

// A schedule stage's own learning rate replaces the parameter's from that stage on: with a
// negligible rate in the second stage, the final 8³ grid is the trilinear upsampling of the 4³
// grid reached at the switch (a stage without "lr" would keep moving it).
TEST_CASE("optimize schedule stages take their own learning rate", "[media][optimize]") {
  const std::string dir = blob_fog_dir("stagelr", 8);
  auto config = [&](const std::string& name, const std::string& second_stage) {
    std::ofstream(dir + "/" + name + ".json") << R"({
  "scene": "scene.json", "output": ")" + name + R"(",
  "parameters": {"fog.density": {"lr": 0.1, "bounds": [0, 4], "init": 0.5,
    "schedule": [{"until": 3, "resolution": [4, 4, 4]}, )" +
                                                     second_stage + R"(]}},
  "views": {"ring": {"count": 2, "radius": 3.5, "height": 0.5, "fov": 40},
            "reference": {"set": {"fog.density": "density.vol"}, "spp": 4}},
  "resolution": [12, 12], "spp": 2, "adjoint_spp": 2, "iterations": 6, "seed": 3,
  "checkpoint_every": 3, "snapshot_every": 3
})";
    REQUIRE(run_optimize(dir + "/" + name + ".json", "", 0, true) == 0);
    const VolumeGrid at_switch = read_vol(dir + "/" + name + "/snapshots/fog.density_00003.vol");
    const VolumeGrid final_grid = read_vol(dir + "/" + name + "/final/fog.density.vol");
    REQUIRE(at_switch.x == 4);
    REQUIRE(final_grid.x == 8);
    const auto up = resample_grid(at_switch.data, 4, 4, 4, 1, 8, 8, 8);
    double moved = 0;
    for (size_t i = 0; i < up.size(); ++i) moved = std::max(moved, double(std::abs(up[i] - final_grid.data[i])));
    return moved;
  };
  CHECK(config("frozen", R"({"until": 6, "resolution": [8, 8, 8], "lr": 1e-12})") < 1e-6);
  CHECK(config("moving", R"({"until": 6, "resolution": [8, 8, 8]})") > 0.05);
}

// "parametrization": "log": Adam steps on u = ln x. Its first step moves each element of u by
// about ±lr (less where the gradient is tiny), so x changes by a factor e^(±lr), not by ±lr as
// in plain Adam (the check's teeth: the plain run's ratios are not factors of e^(±lr)). With
// large steps the smoothed quantity is u: |M Δu| ≤ lr. Values under the floor enter log space at
// 1e-6; bounds hold for x.
TEST_CASE("a log parametrization steps by factors, with and without large steps", "[media][optimize]") {
  const std::string dir = blob_fog_dir("gridlog", 8);
  const double lr = 0.1;
  auto run = [&](const std::string& name, double init, const std::string& extra) {
    return one_density_step(dir, name, init, extra).data;
  };
  // Per voxel that moved: |ln(x1 / x0)|, the step in u.
  auto log_steps = [&](const std::vector<float>& x1, double x0) {
    REQUIRE(x1.size() == size_t(8 * 8 * 8));
    std::vector<double> s;
    for (float v : x1)
      if (std::abs(double(v) - x0) > 1e-7 * x0) s.push_back(std::abs(std::log(double(v) / x0)));
    return s;
  };
  const std::string log = R"(, "parametrization": "log")";
  for (const double x0 : {0.5, 0.05}) {
    const std::vector<double> s = log_steps(run("log", x0, log), x0);
    INFO("x0 " << x0 << ": " << s.size() << " voxels moved");
    CHECK(s.size() > 100);
    int full = 0;
    for (double v : s) {
      CHECK(v <= lr * (1 + 1e-5));
      full += v >= 0.95 * lr;
    }
    CHECK(full >= int(0.8 * double(s.size())));
  }
  // Plain Adam from 0.05: steps of ±0.1 leave [0, 4] downwards (clamped to 0) or triple x; only
  // voxels with a gradient near Adam's ε would step by less.
  const std::vector<double> plain = log_steps(run("plain", 0.05, ""), 0.05);
  int plain_factors = 0;
  for (double v : plain) plain_factors += v <= lr * (1 + 1e-5);
  INFO(plain_factors << " of " << plain.size() << " plain steps within a factor e^(+-lr)");
  CHECK(plain.size() > 100);
  CHECK(plain_factors <= int(0.05 * double(plain.size())));
  // With large steps, M = I + λL acts on u = ln x.
  const double lambda = 3;
  const GridDims d{8, 8, 8, 1};
  const std::vector<float> x1 = run("logls", 0.5, log + R"(, "large_steps": {"lambda": 3, "uniform_adam": false})");
  std::vector<float> du(x1.size());
  for (size_t i = 0; i < x1.size(); ++i) du[i] = float(std::log(double(x1[i]) / 0.5));
  const std::vector<float> m_du = grid_apply_m(d, lambda, du);
  double largest = 0;
  int moved = 0, full = 0;
  for (float v : m_du) {
    largest = std::max(largest, double(std::abs(v)));
    moved += std::abs(v) > 1e-5f;
    full += std::abs(v) >= 0.95 * lr;
  }
  INFO("largest |M du| " << largest << ", " << full << " of " << moved);
  CHECK(largest <= lr * (1 + 1e-4));
  CHECK(full >= 0.8 * moved);
  CHECK(moved > 100);
  // Under the floor: x = 0 enters log space as 1e-6 and leaves it as 1e-6 · e^(±lr) or so.
  for (float v : run("zero", 0, log)) CHECK((v >= 0.9e-6f && v <= 1.12e-6f));
  // Bounds hold for x: 3.9 · e^0.1 = 4.31 is clamped to 4.
  const std::vector<float> high = run("high", 3.9, log);
  CHECK(*std::max_element(high.begin(), high.end()) == 4.f);
}

// A medium's inside must be closed: a ray leaving through a gap in its boundary carries the medium on
// to infinity. The fog's cube (24 vertices with split normals, welded to 8 by position: 12
// triangles, 18 edges) is closed; one triangle less leaves 3 edges with one triangle each; the
// same box as six separate rectangles (one shape per face) is closed again.
TEST_CASE("a medium whose inside is not closed is warned about", "[media]") {
  auto scene = fog_scene();
  CHECK(scene->open_medium_warnings().empty());
  Mesh* box = nullptr;
  for (Mesh& m : scene->meshes)
    if (m.name == "box") box = &m;
  REQUIRE(box);
  REQUIRE(box->triangle_count() == 12);
  const std::vector<uint32_t> closed = box->indices;
  box->indices.resize(box->indices.size() - 3);
  auto warnings = scene->open_medium_warnings();
  REQUIRE(warnings.size() == 1);
  CHECK_THAT(warnings[0], Catch::Contains("warning: the inside of medium 'fog' (shape 'box') is not closed: 3 of 18 "
                                          "edges belong to one triangle only"));
  // Six shapes, two triangles each, together closed.
  box->indices = closed;
  const Mesh whole = *box;
  scene->meshes.erase(scene->meshes.begin() + (box - scene->meshes.data()));
  for (int face = 0; face < 6; ++face) {
    Mesh part = whole;
    part.name = "face" + std::to_string(face);
    part.indices.assign(closed.begin() + 6 * face, closed.begin() + 6 * face + 6);
    scene->meshes.push_back(part);
  }
  CHECK(scene->open_medium_warnings().empty());
  scene->meshes.pop_back();
  warnings = scene->open_medium_warnings();
  REQUIRE(warnings.size() == 1);
  CHECK_THAT(warnings[0],
             Catch::Contains("(shapes 'face0', 'face1', 'face2', 'face3', 'face4') is not closed: 4 of 17"));
}

// The built-in sphere as a medium's boundary is closed: its seam column and pole rows were computed
// with float sin(2π) and sin(π), not 0, so they did not weld with the points they repeat ("not
// closed: 190 of 6047 edges" at 64 segments). Also at odd segment counts.
TEST_CASE("the built-in sphere is closed", "[media]") {
  for (int segments : {4, 7, 64, 512}) {
    auto scene = fog_scene();
    for (Mesh& m : scene->meshes)
      if (m.name == "box") {
        const Mesh sphere = make_sphere(segments);
        m.positions = sphere.positions;
        m.positions.push_back(Vec3f(0.f));  // Embree's padding element
        m.normals = sphere.normals;
        m.uvs = sphere.uvs;
        m.indices = sphere.indices;
      }
    INFO(segments << " segments");
    CHECK(scene->open_medium_warnings() == std::vector<std::string>{});
  }
}

// A camera's declared medium against the geometry: declared in the fog while outside its box (the
// whole view fogged), or inside the box while declared in no medium (no fog near it), is one
// warning line; a consistent camera none.
TEST_CASE("cameras whose declared medium contradicts the boundaries they look through are warned about", "[media]") {
  auto scene = fog_scene();  // outside the box, no medium: consistent
  CHECK(scene->camera_medium_warnings().empty());
  Camera& cam = scene->cameras[0];
  cam.medium = 0;
  auto warnings = scene->camera_medium_warnings();
  REQUIRE(warnings.size() == 1);
  CHECK_THAT(warnings[0], Catch::Contains("warning: camera") && Catch::Contains("is in medium 'fog'") &&
                              Catch::Contains("shape 'box' from the side of no medium"));
  // Inside the box, looking at its far wall.
  cam.origin = {0.f, 0.f, 0.2f};
  cam.target = {0.f, 0.f, -1.f};
  cam.update();
  CHECK(scene->camera_medium_warnings().empty());
  cam.medium = -1;
  warnings = scene->camera_medium_warnings();
  REQUIRE(warnings.size() == 1);
  CHECK_THAT(warnings[0], Catch::Contains("is in no medium") && Catch::Contains("from the side of medium 'fog'"));
}

// An optically thick homogeneous medium is not refused and renders quickly: its collisions are
// real with probability 1 / headroom and its shadow rays' ratio tracking reaches 0 in a few
// hundred steps (only an infinite majorant, or a grid block with thin parts, would not end).
TEST_CASE("a homogeneous medium of density 1e12 renders (opaque smoke, no refusal)", "[media]") {
  FogOptions o;
  o.homogeneous = 1e12f;
  o.resolution = 16;
  auto scene = fog_scene(o);
  const Image img = render(*scene, {0, 4, 1, false});
  for (float v : img.data) REQUIRE(std::isfinite(v));
}
