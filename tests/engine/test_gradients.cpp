// Whole-image gradient tests: adjoint vs same-seed central differences of the primal renderer
// (through the code `backlight check` runs), prb vs the taped oracle, rb vs prb and rb vs
// finite differences in expectation, parameters that move sampling (roughness, metallic, their
// bitmaps) in expectation with negative controls, exactness for emitter radiance, and gradient
// shape (zeros where unseen, signs); the same for the metallic-roughness blend, textured lights,
// a constant sky and meshes with vertex colours.
#include <tbb/global_control.h>
#include <unistd.h>
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <numeric>
#include <random>
#include <tuple>

#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/integrators/taped.h"
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

// prb against same-seed central differences of `name` along 3 random directions (the code
// `backlight check` runs): each direction's relative error within `tolerance` — stricter than the
// check's verdict, which measures errors against the RMS over the directions — and the
// differences not trivially zero.
void check_same_seed(Scene& scene, const std::string& name, const Image& target, double eps, uint64_t direction_seed,
                     double tolerance) {
  INFO("parameter " << name);
  for (const auto& r :
       directional_check(scene, name, request(target, GradientMethod::Prb, 4), 3, eps, direction_seed)) {
    INFO("adjoint " << r.adjoint << " finite difference " << r.finite_difference);
    std::printf("%s: adjoint %.6g, finite difference %.6g, relative error %.2g\n", name.c_str(), r.adjoint,
                r.finite_difference, r.relative_error);
    CHECK(r.relative_error < tolerance);
    CHECK(std::abs(r.finite_difference) > 0);
  }
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

double mean_of(const std::vector<double>& x) { return std::accumulate(x.begin(), x.end(), 0.0) / double(x.size()); }
double standard_error(const std::vector<double>& x) {
  const double m = mean_of(x);
  double s = 0;
  for (double e : x) s += (e - m) * (e - m);
  return std::sqrt(s / double(x.size() - 1) / double(x.size()));
}

// The adjoint's directional derivative ⟨∇F, v⟩ of F = mean radiance against same-seed central
// differences (F(θ + εv) − F(θ − εv)) / 2ε, one pair per seed over `batches` seeds. Only the
// expectations agree when the parameter moves sampling (roughness, metallic: same-seed
// differences then differentiate another estimator of the same integral) or for rb (its incident
// radiance comes from paths of its own). A pair shares its seed (common random numbers), so
// their difference varies far less than either; the pairs are independent over seeds, and z is
// the mean difference over its standard error. The comparison has power only if that standard
// error is small next to the gradient (`max_relative_se`), and the same test must reject the
// adjoint scaled by 0.7 and by 2 (negative controls).
struct ExpectationOptions {
  float eps = 0.02f;
  std::vector<float> direction;  // v (empty: 1 in every element)
  int batches = 24, spp = 32;
  GradientMethod method = GradientMethod::Prb;
  double max_relative_se = 0.05;
};
struct ExpectationCheck {
  double adjoint = 0, finite_difference = 0;  // means over seeds
  double z = 0, relative_se = 0;              // of the paired difference adjoint − differences
  double z_low = 0, z_high = 0;               // the same with the adjoint × 0.7 and × 2
};
ExpectationCheck check_in_expectation(Scene& scene, const std::string& name, const ExpectationOptions& o = {}) {
  const Camera& cam = scene.cameras[0];
  Image a(cam.width, cam.height, 3);
  for (auto& v : a.data) v = 1.f / float(a.data.size());  // F = mean radiance
  const int h = scene.params.find(name);
  REQUIRE(h >= 0);
  const std::vector<float> theta = scene.params[h].value;
  const std::vector<float> v = o.direction.empty() ? std::vector<float>(theta.size(), 1.f) : o.direction;
  REQUIRE(v.size() == theta.size());
  for (size_t i = 0; i < v.size(); ++i) {  // both steps stay where the scene is valid
    REQUIRE(theta[i] - o.eps * std::abs(v[i]) >= scene.params[h].lower);
    REQUIRE(theta[i] + o.eps * std::abs(v[i]) <= scene.params[h].upper);
  }
  auto F = [&](const PassOptions& pass, float step) {
    for (size_t i = 0; i < v.size(); ++i) scene.params[h].value[i] = theta[i] + step * v[i];
    const Image img = render(scene, pass);
    scene.params[h].value = theta;
    double f = 0;
    for (size_t i = 0; i < img.data.size(); ++i) f += double(a.data[i]) * img.data[i];
    return f;
  };
  std::vector<double> adjoint, fd;
  for (int b = 0; b < o.batches; ++b) {
    GradientRequest rq;
    rq.method = o.method;
    rq.adjoint_image = &a;
    rq.pass = {0, o.spp, 300 + uint64_t(b), false};
    rq.adjoint_seed = rq.pass.seed;
    scene.params.require_grad({name});
    compute_gradient(scene, rq);
    double g = 0;
    for (size_t i = 0; i < v.size(); ++i) g += double(scene.params[h].grad[i]) * v[i];
    adjoint.push_back(g);
    fd.push_back((F(rq.pass, o.eps) - F(rq.pass, -o.eps)) / (2 * double(o.eps)));
  }
  auto paired_z = [&](double scale) {
    std::vector<double> d;
    for (size_t b = 0; b < fd.size(); ++b) d.push_back(scale * adjoint[b] - fd[b]);
    return std::pair{mean_of(d) / standard_error(d), standard_error(d)};
  };
  ExpectationCheck c;
  c.adjoint = mean_of(adjoint);
  c.finite_difference = mean_of(fd);
  double se = 0;
  std::tie(c.z, se) = paired_z(1.0);
  c.relative_se = se / std::abs(c.adjoint);
  c.z_low = paired_z(0.7).first;
  c.z_high = paired_z(2.0).first;
  const char* method = method_name(o.method);
  INFO(name << ": " << method << " " << c.adjoint << " ± " << standard_error(adjoint) << ", finite differences "
            << c.finite_difference << " ± " << standard_error(fd) << "; paired: z = " << c.z << ", relative SE "
            << c.relative_se << "; 0.7 x " << method << ": z = " << c.z_low << ", 2 x: z = " << c.z_high);
  std::printf(
      "in expectation, %s: %s %.6g ± %.2g, finite differences %.6g ± %.2g; paired z = %.2f, relative SE %.3f; "
      "0.7 x: z = %.1f, 2 x: z = %.1f\n",
      name.c_str(), method, c.adjoint, standard_error(adjoint), c.finite_difference, standard_error(fd), c.z,
      c.relative_se, c.z_low, c.z_high);
  CHECK(c.adjoint != 0.0);
  CHECK(std::abs(c.z) < 4.0);
  CHECK(c.relative_se < o.max_relative_se);
  CHECK(std::abs(c.z_low) > 4.0);
  CHECK(std::abs(c.z_high) > 4.0);
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

// A smooth 32×16 sky with one broad bright region: no small, bright source (like the open scene's
// 20× "sun" texel) whose edges a sample can cross, which would make same-seed differences
// heavy-tailed when roughness moves the sampled directions.
void write_smooth_sky(const std::string& path) {
  Image sky(32, 16, 3);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 32; ++x) {
      const float dx = float(x - 8) / 6.f, dy = float(y - 5) / 3.f;
      for (int c = 0; c < 3; ++c) sky.at(x, y, c) = 0.2f + 0.05f * float(c) + 3.f * std::exp(-dx * dx - dy * dy);
    }
  write_image(path, sky);
}

// A grey w×h bitmap with texels in [lo, hi] (a fixed pseudo-random pattern).
void write_pattern(const std::string& path, int w, int h, float lo, float hi, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(lo, hi);
  Image img(w, h, 3);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const float t = u(rng);
      for (int c = 0; c < 3; ++c) img.at(x, y, c) = t;
    }
  write_image(path, img);
}

// A glossy floor filling the view with a glossy cube on it, under the smooth sky (no roulette,
// up to three bounces): every pixel carries the BSDF gradients, and light reaches the camera
// over floor → cube → floor. Plain: a rough-conductor floor ("metal") and a rough-plastic cube
// ("plastic"). Textured: a metallic-roughness floor ("alloy") with roughness and metallic
// bitmaps, and the plastic cube with a roughness bitmap.
std::unique_ptr<Scene> glossy_scene(bool textured = false) {
  static int counter = 0;
  const std::string dir = test::temp_dir("glossy" + std::to_string(counter++));
  write_smooth_sky(dir + "/sky.exr");
  std::string floor = R"("metal")",
              materials = R"("metal": {"type": "roughconductor", "specular": [0.9, 0.7, 0.4], "roughness": 0.25},
                "plastic": {"type": "roughplastic", "albedo": [0.2, 0.4, 0.7], "roughness": 0.3})";
  if (textured) {
    write_pattern(dir + "/roughness.exr", 8, 8, 0.15f, 0.4f, 1);
    write_pattern(dir + "/metallic.exr", 8, 8, 0.3f, 0.7f, 2);
    write_pattern(dir + "/cube_roughness.exr", 4, 4, 0.2f, 0.4f, 3);
    floor = R"("alloy")";
    materials = R"("alloy": {"type": "metallic_roughness", "base_color": [0.9, 0.6, 0.3],
                          "roughness": {"type": "bitmap", "file": "roughness.exr"},
                          "metallic": {"type": "bitmap", "file": "metallic.exr"}},
                "plastic": {"type": "roughplastic", "albedo": [0.2, 0.4, 0.7],
                            "roughness": {"type": "bitmap", "file": "cube_roughness.exr"}})";
  }
  std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"spp": 4, "max_depth": 4, "rr_depth": 0, "seed": 1},
  "cameras": [{"origin": [0, 1.2, 2.2], "target": [0, 0.2, 0], "fov": 40, "resolution": [24, 24]}],
  "materials": {)" << materials << R"(},
  "shapes": [{"name": "floor", "type": "rectangle", "material": )"
                                     << floor << R"(,
              "transform": {"scale": 4, "rotate": {"axis": [1, 0, 0], "angle": -90}}},
             {"name": "box", "type": "cube", "material": "plastic",
              "transform": {"scale": 0.4, "rotate": {"axis": [0, 1, 0], "angle": 30}, "translate": [0, 0.4, 0]}}],
  "environment": {"type": "envmap", "file": "sky.exr", "scale": 1}
})";
  return load_scene(dir + "/scene.json");
}

// The open scene (test_scenes.h) with its scene file edited before loading.
std::unique_ptr<Scene> edited_open_scene(const test::OpenSceneOptions& o,
                                         const std::function<void(nlohmann::json&, const std::string& dir)>& edit) {
  static int counter = 0;
  const std::string dir = test::temp_dir("edited" + std::to_string(counter++));
  const std::string file = test::write_open_scene(dir, o);
  nlohmann::json j = nlohmann::json::parse(std::ifstream(file));
  edit(j, dir);
  std::ofstream(file) << j.dump(2);
  return load_scene(file);
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
       {"floor.albedo", "light.radiance", "environment.radiance", "plastic.albedo", "metal.specular"})
    check_same_seed(*scene, name, target, 1e-2, 11, 1e-2);
}

TEST_CASE("taped AD and prb agree to float precision on the same random numbers", "[gradient][taped]") {
  auto scene = open_scene();
  Image target = target_for(*scene);
  check_prb_matches_taped(*scene, target);
}

// prb's replay took a vertex's derivative as δ · (radiance still to come) / f per channel and
// dropped it where f is 0 in a channel: a colour channel at exactly 0 (an 8-bit texture, a bound
// the optimizer projected onto) lost its bounce term (25% of a Cornell wall's gradient; taped AD
// and finite differences had it). The first run now carries that channel's radiance as if its
// first zero were 1 (ZeroChannels, path.h). Zeros in different channels of two diffuse
// materials (the floor's texture, the white object's colour), with roulette on (it divides the
// throughput by q). Fails without the fix: |taped − prb| / |prb| 0.8% and 2%, a white red of 0.
TEST_CASE("taped AD and prb agree with colour channels at exactly 0", "[gradient][taped]") {
  test::OpenSceneOptions o;
  o.rr_depth = 2;
  auto scene = open_scene(o);
  // Channel `c` of every element (texel) of a colour parameter set to 0.
  auto zero_channel = [&](const char* name, size_t c) {
    Param& p = scene->params[scene->params.find(name)];
    REQUIRE(p.channels() == 3);
    for (size_t i = c; i < p.value.size(); i += 3) p.value[i] = 0.f;
  };
  zero_channel("floor.albedo", 1);  // the floor texture's green
  zero_channel("white.albedo", 0);  // the white diffuse object's red
  Image target = target_for(*scene);
  check_prb_matches_taped(*scene, target);
  // The same channel at 0 in two materials, only one of them differentiated: the replay must note
  // a zero at a material that wants no gradient too (otherwise a later zero in that channel is
  // taken for the first and gets the radiance L̃ belongs to the earlier one: 48% off in a review).
  zero_channel("white.albedo", 1);
  {
    scene->params.require_grad({"white.albedo"});
    compute_gradient(*scene, request(target, GradientMethod::Prb, 4));
    const std::vector<float> prb = scene->params[scene->params.find("white.albedo")].grad;
    compute_gradient(*scene, request(target, GradientMethod::Taped, 4));
    const std::vector<float>& taped = scene->params[scene->params.find("white.albedo")].grad;
    std::vector<float> diff(taped.size());
    for (size_t k = 0; k < diff.size(); ++k) diff[k] = taped[k] - prb[k];
    INFO("white.albedo alone: prb " << prb[0] << ", " << prb[1] << ", " << prb[2] << "; taped " << taped[0] << ", "
                                    << taped[1] << ", " << taped[2]);
    CHECK(norm(prb) > 0);
    CHECK(norm(diff) <= 1e-4 * norm(prb));
  }
  // The zero channels' own gradients are not 0: their bounce term is what was lost.
  for (auto [name, c] : {std::pair{"floor.albedo", size_t(1)}, std::pair{"white.albedo", size_t(0)}}) {
    scene->params.require_grad({name});
    compute_gradient(*scene, request(target, GradientMethod::Prb, 4));
    const Param& p = scene->params[scene->params.find(name)];
    double sum = 0;
    for (size_t i = c; i < p.grad.size(); i += 3) sum += std::abs(double(p.grad[i]));
    INFO(name << " channel " << c << ": sum of |gradient| " << sum);
    CHECK(sum > 0);
  }
}

TEST_CASE("the taped mode's default budget follows a cgroup memory limit", "[taped]") {
  // A fake /proc/self/cgroup and /sys/fs/cgroup: the default budget (80% of memory) took the
  // machine's RAM in a container limited to less, whose kernel kills the process instead.
  namespace fs = std::filesystem;
  const fs::path dir = fs::temp_directory_path() / ("backlight-cgroup-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  auto write = [&](const std::string& rel, const std::string& text) {
    fs::create_directories((dir / rel).parent_path());
    std::ofstream(dir / rel) << text;
  };
  const std::string root = (dir / "sys").string(), proc = (dir / "cgroup").string();
  // cgroup v2: the process's own cgroup's memory.max.
  write("cgroup", "0::/job/step\n");
  write("sys/job/step/memory.max", "536870912\n");
  CHECK(cgroup_memory_limit(proc, root) == 536870912u);
  write("sys/job/step/memory.max", "max\n");
  CHECK(cgroup_memory_limit(proc, root) == 0u);
  // cgroup v1 (a hybrid system also lists "0::/"): the memory controller's path, then its root.
  write("cgroup", "9:pids:/\n4:memory:/docker/abc\n0::/\n");
  write("sys/memory/docker/abc/memory.limit_in_bytes", "1073741824\n");
  CHECK(cgroup_memory_limit(proc, root) == 1073741824u);
  write("sys/memory/docker/abc/memory.limit_in_bytes", "9223372036854771712\n");  // no limit
  CHECK(cgroup_memory_limit(proc, root) == 0u);
  write("cgroup", "4:cpu,memory:/other\n");
  write("sys/memory/memory.limit_in_bytes", "2147483648\n");
  CHECK(cgroup_memory_limit(proc, root) == 2147483648u);
  CHECK(cgroup_memory_limit((dir / "missing").string(), root) == 2147483648u);
  fs::remove_all(dir);
  CHECK(cgroup_memory_limit(proc, root) == 0u);
  CHECK(physical_memory_bytes() > 0u);
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

// [expectation]: not under the sanitizers; the pruned-replay case runs rb on the same BSDFs.
TEST_CASE("rb matches finite differences in expectation for BSDF parameters", "[gradient][rb][expectation]") {
  // rb's own code is its estimate of the incident radiance at each BSDF sample, on an independent
  // path (RadiativeObserver::scatter); its emission and light-sample terms are prb's. So BSDF
  // parameters at every vertex of multi-bounce paths test it, and emitter radiances would not.
  // Its independent paths make the same-seed estimates differ: in expectation only. Colours are
  // stepped along themselves (θ ± εθ stays in [0, 1]).
  auto along_itself = [](const Scene& scene, const std::string& name) {
    return scene.params[scene.params.find(name)].value;
  };
  const ExpectationOptions rb{.method = GradientMethod::Rb};
  // Under the smooth sky: incident radiance from the environment (MIS against its sampling),
  // through up to two further glossy bounces.
  auto glossy = glossy_scene();
  for (const char* name : {"metal.specular", "plastic.albedo"}) {
    ExpectationOptions o = rb;
    o.direction = along_itself(*glossy, name);
    o.batches = 12;  // without sampling moved, the pairs differ by rb's incident estimates only
    check_in_expectation(*glossy, name, o);
  }
  for (const char* name : {"metal.roughness", "plastic.roughness"}) check_in_expectation(*glossy, name, rb);
  // The open scene without roulette: the area light and the sharp sky, a textured floor.
  test::OpenSceneOptions o;
  o.rr_depth = 0;
  auto open = open_scene(o);
  for (const char* name : {"floor.albedo", "metal.specular", "plastic.albedo"}) {
    ExpectationOptions eo = rb;
    eo.direction = along_itself(*open, name);
    eo.batches = 12;
    eo.spp = 16;
    check_in_expectation(*open, name, eo);
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
  check_same_seed(*scene, "alloy.base_color", target, 1e-2, 11, 1e-2);
}

// [expectation]: not under the sanitizers; the prb == taped case above runs the same BSDF.
TEST_CASE("metallic_roughness: roughness and metallic gradients agree with finite differences in expectation",
          "[gradient][metallic_roughness][expectation]") {
  // Metallic picks the lobe a BSDF sample comes from and roughness shapes both lobes' sampling,
  // so only the expectations agree (see the roughness test below).
  // An alloy floor filling the view under a smooth sky with one broad bright region: every pixel
  // carries the gradients, and no small, bright source makes the estimates noisy.
  const std::string dir = test::temp_dir("alloy-floor");
  write_smooth_sky(dir + "/sky.exr");
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
  // The comparison must be able to see a 10% error in the gradient: relative SE < 0.025.
  for (const auto& [name, eps] : {std::pair{"alloy.roughness", 0.05f}, std::pair{"alloy.metallic", 0.3f}})
    check_in_expectation(*scene, name, {.eps = eps, .batches = 16, .spp = 64, .max_relative_se = 0.025});
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
  for (const char* name : {"floor.albedo", "plastic.albedo", "metal.specular", "alloy.base_color"})
    check_same_seed(*scene, name, target, 1e-2, 11, 1e-2);
}

TEST_CASE("a textured area light and a constant environment: prb matches taped AD and same-seed differences",
          "[gradient][emitter]") {
  // The open scene (NEE, MIS and roulette on) with a bitmap radiance on its area light and a
  // constant sky instead of the map.
  auto scene = edited_open_scene({}, [](nlohmann::json& j, const std::string& dir) {
    Image pattern(8, 4, 3);
    for (int y = 0; y < 4; ++y)
      for (int x = 0; x < 8; ++x)
        for (int c = 0; c < 3; ++c) pattern.at(x, y, c) = 2.f + 1.5f * float((x + 2 * y + c) % 5);
    write_image(dir + "/light.exr", pattern);
    for (auto& shape : j["shapes"])
      if (shape["name"] == "light") shape["emitter"]["radiance"] = {{"type", "bitmap"}, {"file", "light.exr"}};
    j["environment"] = {{"type", "constant"}, {"radiance", {0.3, 0.4, 0.5}}};
  });
  const Param& light = scene->params[scene->params.find("light.radiance")];
  REQUIRE(light.shape == std::vector<int>{4, 8, 3});
  REQUIRE(scene->params[scene->params.find("environment.radiance")].shape == std::vector<int>{3});
  Image target = target_for(*scene);
  check_prb_matches_taped(*scene, target);
  // No sampling decision reads an emitted radiance (lights are picked uniformly, points on them
  // by area, directions to the constant sky uniformly; roulette reads the path throughput only),
  // so same-seed differences are exact even with roulette on.
  for (const auto& [name, eps] : {std::pair{"light.radiance", 0.05}, std::pair{"environment.radiance", 0.01}})
    check_same_seed(*scene, name, target, eps, 13, 1e-3);
}

TEST_CASE("roughness and metallic bitmaps: prb matches taped AD on the same random numbers",
          "[gradient][taped][texture]") {
  auto scene = glossy_scene(true);
  for (const char* name : {"alloy.roughness", "alloy.metallic", "plastic.roughness"})
    REQUIRE(scene->params[scene->params.find(name)].shape.size() == 3);
  Image target = target_for(*scene);
  check_prb_matches_taped(*scene, target);
}

// [expectation]: not under the sanitizers; the case above runs the same texel gradients.
TEST_CASE("roughness and metallic bitmaps: texel gradients agree with finite differences in expectation",
          "[gradient][texture][expectation]") {
  // Both move sampling (see the roughness test for the step). The direction moves every texel
  // the same way, by a random 0.5–1.5 of the step, so the texels' gradients add up instead of
  // cancelling. Metallic picks the lobe a sample comes from: same-seed renders jump where a
  // sample changes lobe, by ~1/ε. The blend is linear in metallic and a path meets the flat
  // floor at most twice, so the expected image is at most quadratic in the metallic texels and
  // central differences have no bias at any step: a wider one only divides that noise.
  auto scene = glossy_scene(true);
  std::mt19937 rng(19);
  std::uniform_real_distribution<float> u(0.5f, 1.5f);
  for (const auto& [name, eps] : {std::pair{"alloy.roughness", 0.02f}, std::pair{"alloy.metallic", 0.1f},
                                  std::pair{"plastic.roughness", 0.02f}}) {
    std::vector<float> direction(scene->params[scene->params.find(name)].size());
    for (float& v : direction) v = u(rng);
    check_in_expectation(*scene, name, {.eps = eps, .direction = direction});
  }
}

// [expectation]: not under the sanitizers; the prb == taped cases run the same roughness gradients.
TEST_CASE("roughness gradients agree with finite differences in expectation", "[gradient][roughness][expectation]") {
  // Sampling depends on roughness, so same-seed differences are not the derivative of a fixed
  // estimator: check_in_expectation compares means over seeds. The step: central differences
  // carry a bias ε²F‴/6, which Richardson extrapolation (ε and ε/2 on the same 256 seeds)
  // measured on the glossy scene at 2–4% for ε = 0.1, 0.7–1.3% for ε = 0.05 and under 0.2% for
  // ε = 0.02, while the noise of the differences grows only ~1.4× from 0.05 to 0.02 (same-seed
  // renders jump only where a moving sample crosses an edge). At ε = 0.02 the bias is under a
  // fifth of the standard errors measured here (1.4–1.8%). No roulette: its decisions read the
  // throughput, so it adds jumps to the differences.
  // Not the open scene's sky: its 20× "sun" texel makes the differences heavy-tailed (a sample
  // crossing the texel's edge jumps by ~20 / 2ε), so a standard error from tens of seeds is
  // unreliable (metal.roughness at ε = 0.01: z = −2.9 over seeds 300–499, z = 0.2 over 1200
  // others), and a relative SE of 0.05 takes several hundred seeds of 64 samples per pixel.
  auto glossy = glossy_scene();
  for (const char* name : {"metal.roughness", "plastic.roughness"}) check_in_expectation(*glossy, name);
  // The open scene under its area light alone: light samples of a small emitter, MIS against
  // BSDF sampling, and the cubes lit by each other.
  test::OpenSceneOptions o;
  o.environment = false;
  o.rr_depth = 0;
  auto open = open_scene(o);
  check_in_expectation(*open, "metal.roughness", {.spp = 16});  // the plastic's barely changes F here
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

// check --seeds N accepts |z| below Student's t quantile of the normal's two-sided 4σ tail for
// N − 1 degrees of freedom: the tail function against a quadrature of the t density written out
// here, and the thresholds' tails against the 4σ normal tail.
TEST_CASE("check's z threshold: Student's t quantile of the 4-sigma tail", "[gradient][check]") {
  auto quadrature_tail = [](double t, double dof) {
    // 2 ∫_t^∞ f(x) dx with x = t / s, s in (0, 1]: dx = t / s² ds; Simpson on 20000 intervals.
    const double norm = std::exp(std::lgamma((dof + 1) / 2) - std::lgamma(dof / 2)) / std::sqrt(dof * M_PI);
    auto g = [&](double s) {
      if (s <= 0) return 0.0;
      const double x = t / s;
      return norm * std::pow(1 + x * x / dof, -(dof + 1) / 2) * t / (s * s);
    };
    const int n = 20000;
    double sum = g(0) + g(1);
    for (int i = 1; i < n; ++i) sum += g(double(i) / n) * (i % 2 ? 4 : 2);
    return 2 * sum / (3.0 * n);
  };
  for (double t : {0.5, 2.0, 4.0, 9.0})  // one degree of freedom: Cauchy, 1 − (2/π) atan t
    CHECK(student_t_two_sided_tail(t, 1.0) == Approx(1 - 2 / M_PI * std::atan(t)).epsilon(1e-9));
  for (double dof : {2.0, 3.0, 7.0, 15.0, 63.0})
    for (double t : {0.5, 2.0, 4.0, 9.0}) {
      INFO("dof " << dof << ", t " << t);
      CHECK(student_t_two_sided_tail(t, dof) == Approx(quadrature_tail(t, dof)).epsilon(1e-6));
    }
  const double normal_tail = std::erfc(4 / std::sqrt(2.0));
  for (int seeds : {2, 3, 4, 8, 16, 64, 1000}) {
    const double t = check_z_threshold(seeds);
    INFO("seeds " << seeds << ": threshold " << t);
    CHECK(student_t_two_sided_tail(t, seeds - 1) == Approx(normal_tail).epsilon(1e-6));
    CHECK(t > 4);
  }
  CHECK(check_z_threshold(2) == Approx(1 / std::tan(M_PI * normal_tail / 2)).epsilon(1e-6));  // Cauchy: 10050
  CHECK(check_z_threshold(1000) == Approx(4.0).epsilon(0.01));
  CHECK(check_z_threshold(1) == 4.0);
}

// The check's verdict measures each direction's error against the RMS of the finite differences
// over the directions (the typical ⟨∇, v⟩): a direction nearly orthogonal to the gradient no longer
// fails on the finite difference's own truncation error, and an adjoint off by a factor beyond the
// tolerance still fails (the largest |fd| is at least the RMS). Over seeds, a pass is conclusive
// when every direction resolves an error of 25% of the RMS in its derivative.
TEST_CASE("check's verdict: errors against the RMS of the directional derivatives", "[gradient][check]") {
  auto row = [](double adjoint, double fd) {
    CheckRow r;
    r.adjoint = adjoint, r.finite_difference = fd;
    r.relative_error = std::abs(adjoint - fd) / std::abs(fd);
    return r;
  };
  // One seed, the truncation error of central differences seen on the Cornell wall texture
  // (|adjoint − fd| up to ~0.01 at an RMS of ~4), one direction nearly orthogonal to the gradient.
  std::vector<CheckRow> rows = {row(4.7234, 4.7215), row(0.6978, 0.6994), row(2.4137, 2.4149), row(0.004, 0.001)};
  CHECK(rows[3].relative_error > 1);  // what the old verdict failed on
  CheckSummary s = summarize_check(rows, 1, 0.01);
  CHECK(s.passed);
  CHECK(std::isnan(s.resolution[0]));
  // The same rows with the adjoint off by a factor 1.011, or negated in one direction: fail.
  for (CheckRow& r : rows) r.adjoint = 1.011 * r.finite_difference;
  CHECK_FALSE(summarize_check(rows, 1, 0.01).passed);
  CHECK_FALSE(summarize_check(rows, 1, 0.011).passed);  // 1.1% of the largest direction, 1.9% of the RMS
  rows = {row(4.7234, 4.7215), row(-0.6978, 0.6994), row(2.4137, 2.4149), row(0.004, 0.001)};
  s = summarize_check(rows, 1, 0.01);
  CHECK_FALSE(s.passed);
  CHECK_FALSE(s.ok[1]);
  CHECK(s.ok[0]);
  // Any factor error above the tolerance fails, whatever the directions: the largest |fd| ≥ RMS.
  std::mt19937_64 rng(5);
  std::normal_distribution<double> normal;
  for (int trial = 0; trial < 1000; ++trial) {
    const double r = 0.01 * (1.001 + std::abs(normal(rng)));
    std::vector<CheckRow> random_rows;
    for (int d = 0; d < 1 + trial % 6; ++d) {
      const double fd = normal(rng);
      random_rows.push_back(row((trial % 2 ? 1 + r : 1 - r) * fd, fd));
    }
    INFO("trial " << trial << ", r " << r);
    CHECK_FALSE(summarize_check(random_rows, 1, 0.01).passed);
  }

  // Over 512 seeds, means as in a run on the pose scene's box.translate (48², 64 spp, --eps 0.01;
  // standard errors about that run's): direction 2 is nearly orthogonal to the gradient. Each
  // direction resolves an error of max(4.03 · SE, 0.01 · RMS) of its derivative, RMS = 13.0: the
  // worst, direction 2, 4.03 · 0.69 / 13.0 = 21.4%, so the check is conclusive (the old verdict
  // divided by the direction's own |fd|: 307%).
  auto seeded = [](double adjoint, double fd, double se) {
    CheckRow r;
    r.adjoint = adjoint, r.finite_difference = fd, r.difference_stderr = se;
    r.z = (adjoint - fd) / se;
    return r;
  };
  rows = {seeded(-13.14, -13.52, 0.42), seeded(-9.68, -9.70, 0.60), seeded(-0.10, 0.907, 0.69),
          seeded(-19.27, -19.96, 0.66)};
  s = summarize_check(rows, 512, 0.01);
  const double t = check_z_threshold(512);
  const double rms = std::sqrt((13.52 * 13.52 + 9.70 * 9.70 + 0.907 * 0.907 + 19.96 * 19.96) / 4);
  CHECK(s.threshold == t);
  CHECK(s.passed);
  CHECK_FALSE(s.inconclusive);
  CHECK(s.resolution[0] == Approx(t * 0.42 / rms));
  CHECK(s.resolution[2] == Approx(t * 0.69 / rms));
  CHECK(s.resolution_overall == Approx(s.resolution[2]));
  CHECK(s.resolution_overall == Approx(0.214).margin(0.001));
  // Where the directions resolve no error of 25% of the RMS: a pass is inconclusive.
  for (CheckRow& r : rows) r.difference_stderr *= 10, r.z /= 10;
  s = summarize_check(rows, 512, 0.01);
  CHECK(s.passed);
  CHECK(s.inconclusive);
  CHECK(s.resolution_overall > 0.25);
  // A direction whose paired differences are off by more than the threshold fails.
  rows[3] = seeded(-19.27, -21.46, 0.44);
  s = summarize_check(rows, 512, 0.01);
  CHECK_FALSE(s.passed);
  CHECK_FALSE(s.ok[3]);
  CHECK_FALSE(s.inconclusive);
  // A sign error in one element of two whose steps make the finite differences noisy (helper-40):
  // the direction that barely moves that element resolves 10.7% of its own derivative, the one
  // that moves it sees the error within its noise (z −3 < 4.29). No direction may decide alone:
  // inconclusive (taking the best direction said ok).
  rows = {seeded(20.5, 20.0, 0.5), seeded(-3.0, 3.0, 2.0)};
  s = summarize_check(rows, 64, 0.01);
  CHECK(s.passed);
  CHECK(s.inconclusive);
  CHECK(s.resolution_overall == Approx(check_z_threshold(64) * 2.0 / std::sqrt((400.0 + 9.0) / 2)));
  // Where both sides agree seed by seed (z large from rounding alone), the tolerance passes.
  rows = {seeded(2.0000001, 2.0, 1e-9), seeded(-1.0, -1.0000001, 1e-9)};
  s = summarize_check(rows, 4, 0.01);
  CHECK(s.passed);
  CHECK(s.resolution_overall == Approx(0.01));  // the tolerance, where the noise is below it
  // Nothing compared (both sides exactly 0 in every direction, a parameter that does not reach the
  // image): no row passes.
  rows = {seeded(0.0, 0.0, 0.0), seeded(0.0, 0.0, 0.0)};
  s = summarize_check(rows, 1, 0.01);
  CHECK(s.nothing_compared);
  CHECK_FALSE(s.passed);
  CHECK_FALSE(s.ok[0]);
  rows[1].adjoint = 1e-30;
  CHECK_FALSE(summarize_check(rows, 1, 0.01).nothing_compared);
  // Finite differences near the float range: the RMS does not overflow (an infinite RMS passed every
  // error).
  rows = {row(2e300, 1e300), row(1e300, 1e300)};
  CHECK_FALSE(summarize_check(rows, 1, 0.01).passed);
}
