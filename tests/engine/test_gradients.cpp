// Whole-image gradient tests: adjoint vs same-seed central differences of the primal renderer
// (through the code `backlight check` runs), prb vs the taped oracle, rb vs prb in expectation,
// exactness for emitter radiance, and gradient shape (zeros where unseen, signs); the same for the
// metallic-roughness blend and for meshes with vertex colours.
#include <tbb/global_control.h>
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <numeric>

#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/scene/scene_load.h"
#include "test_scenes.h"

using namespace bl;

namespace {

std::unique_ptr<Scene> open_scene(const test::OpenSceneOptions& o = {}) {
  static int counter = 0;
  return load_scene(test::write_open_scene(test::temp_dir("grad" + std::to_string(counter++)), o));
}

// A target that differs from the scene everywhere: the same scene with other parameter values.
Image target_for(Scene& scene, int spp = 16) {
  std::vector<std::vector<float>> saved;
  for (auto& p : scene.params.all()) {
    saved.push_back(p.value);
    if (p.geometry) continue;  // appearance only: the meshes are not re-posed here
    for (auto& v : p.value) v *= 0.8f;
  }
  Image t = render(scene, {0, spp, 99, false});
  for (size_t i = 0; i < saved.size(); ++i) scene.params.all()[i].value = saved[i];
  return t;
}

GradientRequest request(const Image& target, GradientMethod m, int spp, uint64_t seed = 7) {
  GradientRequest rq;
  rq.method = m;
  rq.target = &target;
  rq.pass = {0, spp, seed, false};
  rq.adjoint_seed = seed;
  return rq;
}

double norm(const std::vector<float>& v) {
  double s = 0;
  for (float x : v) s += double(x) * x;
  return std::sqrt(s);
}

// prb against the taped oracle on the same random numbers, for every parameter of the scene.
void check_prb_matches_taped(Scene& scene, const Image& target) {
  scene.params.require_grad({});
  compute_gradient(scene, request(target, GradientMethod::Prb, 4));
  std::vector<std::vector<float>> prb;
  for (auto& p : scene.params.all()) prb.push_back(p.grad);
  GradientResult taped = compute_gradient(scene, request(target, GradientMethod::Taped, 4));
  CHECK(taped.tape_entries > 0);
  for (size_t i = 0; i < prb.size(); ++i) {
    const Param& p = scene.params.all()[i];
    if (!p.requires_grad) continue;  // geometry parameters (not in "all", and not taped)
    std::vector<float> diff(p.grad.size());
    for (size_t k = 0; k < diff.size(); ++k) diff[k] = p.grad[k] - prb[i][k];
    INFO(p.name << ": |prb| = " << norm(prb[i]) << ", |taped - prb| = " << norm(diff));
    std::printf("prb vs taped, %s: |prb| = %.6g, |taped - prb| / |prb| = %.3g\n", p.name.c_str(), norm(prb[i]),
                norm(diff) / norm(prb[i]));
    CHECK(norm(prb[i]) > 0);
    CHECK(norm(diff) <= 1e-4 * norm(prb[i]));
  }
}

// The prb gradient of F = mean radiance with respect to the scalar parameter `name` against wide
// central differences, both averaged over `batches` seeds: for parameters that move sampling,
// same-seed differences do not differentiate a fixed estimator. Returns the z-score and the
// standard error of the prb mean relative to it (how small an error the comparison can see).
struct ExpectationCheck {
  double z = 0, relative_se = 0;
};
ExpectationCheck check_in_expectation(Scene& scene, const std::string& name, float eps, int batches = 6, int spp = 64) {
  const Camera& cam = scene.cameras[0];
  Image a(cam.width, cam.height, 3);
  for (auto& v : a.data) v = 1.f / float(a.data.size());  // F = mean radiance
  const int h = scene.params.find(name);
  REQUIRE(h >= 0);
  scene.params.require_grad({name});
  const float theta = scene.params[h].value[0];
  std::vector<double> grad, fd;
  for (int b = 0; b < batches; ++b) {
    GradientRequest rq;
    rq.adjoint_image = &a;
    rq.pass = {0, spp, 300 + uint64_t(b), false};
    rq.adjoint_seed = rq.pass.seed;
    compute_gradient(scene, rq);
    grad.push_back(scene.params[h].grad[0]);
    auto F = [&](float v) {
      scene.params[h].value[0] = v;
      Image img = render(scene, rq.pass);
      double f = 0;
      for (size_t i = 0; i < img.data.size(); ++i) f += double(a.data[i]) * img.data[i];
      return f;
    };
    fd.push_back((F(theta + eps) - F(theta - eps)) / (2 * eps));
    scene.params[h].value[0] = theta;
  }
  auto mean = [](const std::vector<double>& v) { return std::accumulate(v.begin(), v.end(), 0.0) / double(v.size()); };
  auto se = [&](const std::vector<double>& v) {
    double m = mean(v), s = 0;
    for (double x : v) s += (x - m) * (x - m);
    return std::sqrt(s / double(v.size() - 1) / double(v.size()));
  };
  ExpectationCheck c;
  c.z = (mean(grad) - mean(fd)) / std::sqrt(se(grad) * se(grad) + se(fd) * se(fd));
  c.relative_se = std::sqrt(se(grad) * se(grad) + se(fd) * se(fd)) / std::abs(mean(grad));
  INFO(name << ": prb " << mean(grad) << " ± " << se(grad) << ", finite differences " << mean(fd) << " ± " << se(fd));
  std::printf("in expectation, %s: prb %.6g ± %.2g, finite differences %.6g ± %.2g, z = %.2f\n", name.c_str(),
              mean(grad), se(grad), mean(fd), se(fd), c.z);
  CHECK(std::abs(c.z) < 4.0);
  CHECK(mean(grad) != 0.0);
  return c;
}

// Saturated vertex colours (each vertex mostly red, green or blue) on every mesh but the light.
void paint_vertex_colours(Scene& scene) {
  for (Mesh& m : scene.meshes) {
    if (m.emitter >= 0) continue;
    m.colors.resize(m.vertex_count());
    for (size_t v = 0; v < m.colors.size(); ++v)
      m.colors[v] = Vec3f(v % 3 == 0 ? 1.f : 0.15f, v % 3 == 1 ? 1.f : 0.15f, v % 3 == 2 ? 1.f : 0.15f);
  }
}

}  // namespace

TEST_CASE("prb matches same-seed central differences for parameters that do not move sampling", "[gradient]") {
  // Russian roulette's continuation probability depends on the throughput, hence on albedos:
  // same-seed differences would see ∂q/∂θ, which the detached estimator (like Mitsuba's) leaves
  // out because it vanishes in expectation. Roulette is therefore off here (still 4 bounces);
  // the tests below cover it in expectation.
  test::OpenSceneOptions o;
  o.rr_depth = 0;
  auto scene = open_scene(o);
  Image target = target_for(*scene);
  // The environment map moves its own importance sampling; the check holds sampling fixed, as
  // the detached-sampling estimator prb differentiates does.
  for (const char* name :
       {"floor.albedo", "light.radiance", "environment.radiance", "plastic.albedo", "metal.specular"}) {
    INFO("parameter " << name);
    auto rows = directional_check(*scene, name, request(target, GradientMethod::Prb, 4), 3, 1e-2, 11);
    for (const auto& r : rows) {
      INFO("adjoint " << r.adjoint << " finite difference " << r.finite_difference);
      CHECK(r.relative_error < 1e-2);
      CHECK(std::abs(r.finite_difference) > 0);
    }
  }
}

TEST_CASE("taped AD and prb agree to float precision on the same random numbers", "[gradient][taped]") {
  auto scene = open_scene();
  Image target = target_for(*scene);
  check_prb_matches_taped(*scene, target);
}

TEST_CASE("emitter radiance gradient is exact: dF/dL = sum(dI * I) / L", "[gradient][precision]") {
  // Only the area light emits, so the image is linear in its radiance and F = Σ a·I has the exact
  // derivative Σ_c-pixels a·I / L per channel, at the same seed. Every path touches the radiance,
  // the case where float32 summation over all samples drifts.
  test::OpenSceneOptions o;
  o.environment = false;
  o.resolution = 48;
  auto scene = open_scene(o);
  Image a(48, 48, 3);
  for (size_t i = 0; i < a.data.size(); ++i) a.data[i] = 1e-3f * float(1 + (i * 7919) % 13);
  GradientRequest rq;
  rq.adjoint_image = &a;
  rq.pass = {0, 64, 5, false};
  rq.adjoint_seed = 5;
  scene->params.require_grad({"light.radiance"});
  GradientResult r = compute_gradient(*scene, rq);
  const Param& L = scene->params[scene->params.find("light.radiance")];
  for (int c = 0; c < 3; ++c) {
    double exact = 0;
    for (size_t p = 0; p < r.image.pixel_count(); ++p)
      exact += double(a.data[p * 3 + size_t(c)]) * r.image.data[p * 3 + size_t(c)];
    exact /= double(L.value[size_t(c)]);
    INFO("channel " << c << ": prb " << L.grad[size_t(c)] << " exact " << exact);
    CHECK(std::abs(L.grad[size_t(c)] - exact) <= 2e-6 * std::abs(exact));
  }
}

TEST_CASE("rb agrees with prb in expectation on a multi-bounce scene", "[gradient][rb]") {
  test::OpenSceneOptions o;
  o.max_depth = 5;  // up to 4 scattering vertices: rb's independent estimates matter
  o.rr_depth = 3;
  auto scene = open_scene(o);
  Image target = target_for(*scene);
  const std::vector<std::string> names{"floor.albedo", "plastic.albedo", "light.radiance"};
  scene->params.require_grad(names);
  // Project each gradient on fixed random directions; compare batch means.
  const int batches = 8;
  std::vector<std::vector<double>> prb(names.size()), rb(names.size());
  for (int b = 0; b < batches; ++b)
    for (GradientMethod m : {GradientMethod::Prb, GradientMethod::Rb}) {
      compute_gradient(*scene, request(target, m, 8, 100 + uint64_t(b)));
      for (size_t i = 0; i < names.size(); ++i) {
        const Param& p = scene->params[scene->params.find(names[i])];
        double s = 0;
        for (size_t k = 0; k < p.grad.size(); ++k) s += p.grad[k] * (1.0 + 0.5 * std::sin(double(k)));
        (m == GradientMethod::Prb ? prb : rb)[i].push_back(s);
      }
    }
  for (size_t i = 0; i < names.size(); ++i) {
    auto stats = [&](const std::vector<double>& v) {
      double mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size()), var = 0;
      for (double x : v) var += (x - mean) * (x - mean);
      return std::pair{mean, std::sqrt(var / double(v.size() - 1) / double(v.size()))};
    };
    auto [mp, sp] = stats(prb[i]);
    auto [mr, sr] = stats(rb[i]);
    double z = (mr - mp) / std::sqrt(sp * sp + sr * sr);
    INFO(names[i] << ": prb " << mp << " ± " << sp << ", rb " << mr << " ± " << sr << ", z = " << z);
    CHECK(std::abs(z) < 4.0);
    CHECK(std::abs(mr - mp) < 0.1 * std::abs(mp));
  }
}

TEST_CASE("metallic_roughness: prb matches same-seed differences for its base colour and taped AD for all",
          "[gradient][metallic_roughness]") {
  test::OpenSceneOptions o;
  o.alloy = true;
  {
    auto scene = open_scene(o);
    Image target = target_for(*scene);
    check_prb_matches_taped(*scene, target);
  }
  // Base colour does not move sampling (the lobe choice reads metallic and the coat's Fresnel):
  // same-seed differences, with roulette off as above.
  o.rr_depth = 0;
  auto scene = open_scene(o);
  Image target = target_for(*scene);
  auto rows = directional_check(*scene, "alloy.base_color", request(target, GradientMethod::Prb, 4), 3, 1e-2, 11);
  for (const auto& r : rows) {
    INFO("adjoint " << r.adjoint << " finite difference " << r.finite_difference);
    std::printf("alloy.base_color: adjoint %.6g, finite difference %.6g, relative error %.2g\n", r.adjoint,
                r.finite_difference, r.relative_error);
    CHECK(r.relative_error < 1e-2);
    CHECK(std::abs(r.finite_difference) > 0);
  }
}

TEST_CASE("metallic_roughness: roughness and metallic gradients agree with finite differences in expectation",
          "[gradient][metallic_roughness]") {
  // Metallic picks the lobe a BSDF sample comes from and roughness shapes both lobes' sampling,
  // so only the expectations agree (see the roughness test below).
  // An alloy floor filling the view under a smooth sky with one broad bright region: every pixel
  // carries the gradients, and no small, bright source makes the estimates noisy.
  const std::string dir = test::temp_dir("alloy-floor");
  Image sky(32, 16, 3);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 32; ++x) {
      const float dx = float(x - 8) / 6.f, dy = float(y - 5) / 3.f;
      for (int c = 0; c < 3; ++c) sky.at(x, y, c) = 0.2f + 0.05f * float(c) + 3.f * std::exp(-dx * dx - dy * dy);
    }
  write_image(dir + "/sky.exr", sky);
  std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"spp": 4, "max_depth": 3, "rr_depth": 0, "seed": 1},
  "cameras": [{"origin": [0, 1.2, 2.2], "target": [0, 0, 0], "fov": 40, "resolution": [24, 24]}],
  "materials": {"alloy": {"type": "metallic_roughness", "base_color": [0.9, 0.6, 0.3], "roughness": 0.3,
                          "metallic": 0.4}},
  "shapes": [{"name": "floor", "type": "rectangle", "material": "alloy",
              "transform": {"scale": 4, "rotate": {"axis": [1, 0, 0], "angle": -90}}}],
  "environment": {"type": "envmap", "file": "sky.exr", "scale": 1}
})";
  auto scene = load_scene(dir + "/scene.json");
  // The floor is seen once per path, so the expected image is linear in metallic: a wide step
  // costs no accuracy and divides the differences' noise (from samples changing lobe).
  for (const auto& [name, eps] : {std::pair{"alloy.roughness", 0.05f}, std::pair{"alloy.metallic", 0.3f}}) {
    const ExpectationCheck c = check_in_expectation(*scene, name, eps, 8, 128);
    // The comparison must be able to see a 10% error in the gradient.
    CHECK(c.relative_se < 0.025);
  }
}

TEST_CASE("vertex colours: gradients of the tinted textures match same-seed differences and taped AD",
          "[gradient][vertex_colors]") {
  // Every colour parameter (bitmap and constant albedo, specular, base colour) is read through a
  // vertex colour; the texture's gradient must be the adjoint times that colour.
  test::OpenSceneOptions o;
  o.alloy = true;
  {
    auto scene = open_scene(o);
    paint_vertex_colours(*scene);
    Image target = target_for(*scene);
    check_prb_matches_taped(*scene, target);
  }
  o.rr_depth = 0;
  auto scene = open_scene(o);
  paint_vertex_colours(*scene);
  Image target = target_for(*scene);
  for (const char* name : {"floor.albedo", "plastic.albedo", "metal.specular", "alloy.base_color"}) {
    INFO("parameter " << name);
    auto rows = directional_check(*scene, name, request(target, GradientMethod::Prb, 4), 3, 1e-2, 11);
    for (const auto& r : rows) {
      INFO("adjoint " << r.adjoint << " finite difference " << r.finite_difference);
      std::printf("vertex colours, %s: adjoint %.6g, finite difference %.6g, relative error %.2g\n", name, r.adjoint,
                  r.finite_difference, r.relative_error);
      CHECK(r.relative_error < 1e-2);
      CHECK(std::abs(r.finite_difference) > 0);
    }
  }
}

TEST_CASE("roughness gradients agree with finite differences in expectation", "[gradient][roughness]") {
  // Sampling depends on roughness, so same-seed differences are not the derivative of a fixed
  // estimator; compare the prb gradient with wide central differences, both averaged over seeds.
  auto scene = open_scene();
  for (const char* name : {"plastic.roughness", "metal.roughness"}) check_in_expectation(*scene, name, 0.05f);
}

TEST_CASE("gradient is zero for texels the camera cannot see and has the right sign", "[gradient][shape]") {
  test::OpenSceneOptions o;
  o.max_depth = 2;  // direct illumination only: a texel matters only if the camera sees it
  o.environment = false;
  auto scene = open_scene(o);
  // Look at the left half of the floor only (the texture repeats once over the floor).
  scene->cameras[0].target = {-1.0f, 0.f, 0.f};
  scene->cameras[0].origin = {-1.0f, 1.2f, 1.2f};
  scene->cameras[0].fov_degrees = 30.f;
  scene->cameras[0].update();
  const int h = scene->params.find("floor.albedo");
  const Param& floor = scene->params[h];
  scene->params.require_grad({"floor.albedo"});
  for (float factor : {1.5f, 0.5f}) {
    // Target: the same scene with a brighter (darker) floor.
    std::vector<float> saved = floor.value;
    for (auto& v : scene->params[h].value) v *= factor;
    // Same seed and spp as the gradient run: floor pixels then differ by exactly that factor,
    // so every visible texel's gradient sign is determined.
    Image target = render(*scene, {0, 4, 7, false});
    scene->params[h].value = saved;
    compute_gradient(*scene, request(target, GradientMethod::Prb, 4, 7));
    // Texel column j covers floor x ∈ [-2 + 4j/16, -2 + 4(j+1)/16]. The camera sees about
    // x ∈ [-1.5, -0.5] (columns 2-6); columns ≥ 13 (x > 1.25) are far outside the view.
    int zeros = 0, visible_nonzero = 0, right_sign = 0, counted = 0;
    for (int row = 0; row < 16; ++row)
      for (int col = 0; col < 16; ++col)
        for (int c = 0; c < 3; ++c) {
          float g = floor.grad[(size_t(row) * 16 + size_t(col)) * 3 + size_t(c)];
          if (col >= 13) {
            zeros += g == 0.f;
          } else if (col <= 5 && g != 0.f) {
            ++visible_nonzero;
            ++counted;
            right_sign += factor > 1 ? g < 0 : g > 0;
          }
        }
    INFO("factor " << factor << ": zeros " << zeros << "/144, visible nonzero " << visible_nonzero << ", right sign "
                   << right_sign << "/" << counted);
    CHECK(zeros == 16 * 3 * 3);
    CHECK(visible_nonzero >= 30);
    CHECK(right_sign == counted);
  }
}

TEST_CASE("replays stop after a path's last vertex that can produce a derivative, with the same gradient",
          "[gradient][replay]") {
  // One worker thread: texel gradients are float atomics, whose sum depends on the order of adds.
  // With one thread both runs make the same adds in the same order, so the gradients must be
  // bitwise equal: what the pruned replay skips adds nothing.
  tbb::global_control one_thread(tbb::global_control::max_allowed_parallelism, 1);
  auto scene = open_scene();
  const PixelAdjoint adjoint = [](size_t pixel, const Vec3f&) {
    return Vec3f(1e-3f * float(1 + pixel % 5), -1e-3f * float(pixel % 3), 2e-3f);
  };
  struct Case {
    const char* param;
    bool material;  // only one material wants a gradient: replays must get shorter
  };
  for (AdjointMethod method : {AdjointMethod::Prb, AdjointMethod::Rb})
    for (const Case& c : {Case{"floor.albedo", true}, Case{"plastic.albedo", true}, Case{"metal.roughness", true},
                          Case{"light.radiance", false}, Case{"environment.radiance", false}}) {
      INFO((method == AdjointMethod::Prb ? "prb" : "rb") << ", " << c.param);
      scene->params.require_grad({c.param});
      const Param& p = scene->params[scene->params.find(c.param)];
      PassOptions o{0, 4, 7, false};
      o.replay_whole_paths = true;
      scene->params.zero_grad();
      const PassStats whole = backward(*scene, o, method, adjoint);
      const std::vector<float> expected = p.grad;
      o.replay_whole_paths = false;
      scene->params.zero_grad();
      const PassStats pruned = backward(*scene, o, method, adjoint);
      CHECK(norm(expected) > 0);
      CHECK(p.grad == expected);
      INFO("rays: whole paths " << whole.rays << ", pruned " << pruned.rays);
      CHECK(pruned.rays <= whole.rays);
      if (c.material) CHECK(double(pruned.rays) < 0.9 * double(whole.rays));
    }
}
