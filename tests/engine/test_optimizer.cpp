// Optimizer tests: Adam against hand-computed steps, a tiny end-to-end texture recovery, resume
// equivalence, and config errors.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/integrators/loss.h"
#include "engine/integrators/render.h"
#include "engine/io/image_io.h"
#include "engine/optimize/large_steps.h"
#include "engine/optimize/mesh_distance.h"
#include "engine/optimize/optimizer.h"
#include "engine/optimize/regularizers.h"
#include "engine/optimize/resample.h"
#include "engine/scene/scene_load.h"
#include "test_scenes.h"

using namespace bl;
namespace fs = std::filesystem;

TEST_CASE("a log parametrization's gradient is the chain rule df/du = x df/dx", "[optimizer]") {
  // Against central differences of f(exp(u)) at varied x (a factor dropped or squared left the
  // media test's first Adam step unchanged: every voxel starts at the same x and Adam's first step
  // sees only signs). Below the floor, x enters as 1e-6.
  const std::vector<double> c{0.3, -2.0, 1.5, 4.0, -0.7};
  auto f = [&](const std::vector<double>& x) {
    double sum = 0;
    for (size_t i = 0; i < x.size(); ++i) sum += c[i] * x[i] * x[i] * x[i] + std::sin(x[i]);
    return sum;
  };
  std::vector<float> value{0.02f, 0.5f, 3.0f, 1e-7f, 0.0f}, grad(value.size());
  for (size_t i = 0; i < value.size(); ++i)
    grad[i] = float(3 * c[i] * double(value[i]) * value[i] + std::cos(double(value[i])));
  std::vector<float> u = value, du = grad;
  to_log_space(u, du);
  for (size_t i = 0; i < value.size(); ++i) {
    const double x = std::max(double(value[i]), double(kLogFloor));
    CHECK(u[i] == Approx(std::log(x)).epsilon(1e-6));
    std::vector<double> plus(value.size()), minus(value.size());
    for (size_t j = 0; j < value.size(); ++j) plus[j] = minus[j] = std::exp(double(u[j]));
    const double h = 1e-5;
    plus[i] = std::exp(double(u[i]) + h), minus[i] = std::exp(double(u[i]) - h);
    // f's derivative taken at x (the floored value) times dx/du = x
    const double fd = (f(plus) - f(minus)) / (2 * h);
    INFO("element " << i << " x " << x);
    CHECK(double(du[i]) == Approx(fd).epsilon(1e-4).margin(1e-9));
  }
}

TEST_CASE("Adam matches hand-computed steps", "[optimizer]") {
  AdamSettings s;
  s.learning_rate = 0.1;
  s.lower = -10, s.upper = 0.75;
  Adam adam(s);
  std::vector<float> x{1.0f, 0.5f}, g1{2.0f, -1.0f}, g2{1.0f, 0.5f};
  adam.step(x, g1);
  // Step 1: m = 0.1 g, v = 0.001 g², bias-corrected m̂ = g, v̂ = g², update = lr·g/(|g| + ε) = ±0.1.
  CHECK(x[0] == Approx(0.75f).margin(1e-6));  // 1.0 − 0.1 = 0.9, projected onto the upper bound 0.75
  CHECK(x[1] == Approx(0.6f).margin(1e-6));
  adam.step(x, g2);
  // Step 2, element 0: m = 0.9·0.2 + 0.1·1 = 0.28, v = 0.999·0.004 + 0.001·1 = 0.004996,
  // m̂ = 0.28/0.19, v̂ = 0.004996/0.001999, update = 0.1·m̂/√v̂.
  double m0 = 0.28 / (1 - 0.81), v0 = 0.004996 / (1 - 0.998001);
  CHECK(x[0] == Approx(0.75 - 0.1 * m0 / (std::sqrt(v0) + 1e-8)).margin(1e-6));
  // Element 1: m = 0.9·(−0.1) + 0.1·0.5 = −0.04, v = 0.999·0.001 + 0.001·0.25 = 0.001249.
  double m1 = -0.04 / (1 - 0.81), v1 = 0.001249 / (1 - 0.998001);
  CHECK(x[1] == Approx(0.6 - 0.1 * m1 / (std::sqrt(v1) + 1e-8)).margin(1e-6));

  // Other betas (the config's "betas"): β1 = 0.5, β2 = 0.9. Step 1 is ±lr whatever the betas; step
  // 2 with g = 2 then 1: m = 0.5·1 + 0.5·1 = 1 (m̂ = 1/0.75), v = 0.9·0.4 + 0.1·1 = 0.46
  // (v̂ = 0.46/0.19).
  AdamSettings b;
  b.learning_rate = 0.1;
  b.beta1 = 0.5, b.beta2 = 0.9;
  Adam betas(b);
  std::vector<float> z{0.f}, z1{2.f}, z2{1.f};
  betas.step(z, z1);
  CHECK(z[0] == Approx(-0.1f).margin(1e-6));
  betas.step(z, z2);
  CHECK(z[0] == Approx(-0.1 - 0.1 * (1.0 / 0.75) / (std::sqrt(0.46 / 0.19) + 1e-8)).margin(1e-6));

  AdamSettings d;
  d.learning_rate = 0.1;
  d.decay = "exponential";
  d.decay_rate = 0.5;
  Adam decayed(d);
  std::vector<float> y{0.f}, g{1.f};
  decayed.step(y, g);
  decayed.step(y, g);
  CHECK(decayed.current_learning_rate() == Approx(0.025));
  CHECK(y[0] == Approx(-0.1 - 0.05).margin(1e-6));
}

namespace {

// A floor seen from above under a uniform sky, direct lighting only: the image is a blurred copy
// of the texture, so recovering it is well posed and quick.
// `extra` adds top-level keys to the job, `param_extra` keys to the texture's parameter entry.
std::string write_tiny_job(const std::string& dir, int iterations, const std::string& extra = "",
                           const std::string& param_extra = "") {
  Image checker(64, 64, 3);
  for (int y = 0; y < 64; ++y)
    for (int x = 0; x < 64; ++x)
      for (int c = 0; c < 3; ++c)
        checker.at(x, y, c) = ((x / 16 + y / 16) % 2) ? 0.85f - 0.2f * float(c) : 0.08f + 0.1f * float(c);
  write_image(dir + "/truth.exr", checker);
  Image start(64, 64, 3);
  for (auto& v : start.data) v = 0.5f;
  write_image(dir + "/start.exr", start);
  std::ofstream(dir + "/scene.json") << R"({
  "integrator": {"spp": 4, "max_depth": 2, "rr_depth": 0},
  "cameras": [{"name": "top", "origin": [0, 3, 0.01], "target": [0, 0, 0], "fov": 45, "resolution": [32, 32]},
              {"name": "side", "origin": [1.5, 2.5, 1.5], "target": [0, 0, 0], "fov": 50, "resolution": [32, 32]}],
  "materials": {"floor": {"type": "diffuse", "albedo": {"type": "bitmap", "file": "start.exr"}}},
  "shapes": [{"name": "floor", "type": "rectangle", "material": "floor",
              "transform": {"rotate": {"axis": [1, 0, 0], "angle": -90}}}],
  "environment": {"type": "constant", "radiance": [1, 1, 1]}
})";
  std::ofstream(dir + "/job.json") << R"({
  "scene": "scene.json",
  "output": "out",
  "parameters": {"floor.albedo": {"lr": 0.05, "bounds": [0, 1])" +
                                          param_extra + R"(}},
  "views": {"cameras": ["top", "side", {"name": "extra", "origin": [-1.2, 2.2, 1.6], "target": [0, 0, 0], "fov": 50,
                                         "resolution": [32, 32]}],
            "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 64}},
  "spp": 8,
  "iterations": )" + std::to_string(iterations) +
                                          R"(,
  "checkpoint_every": 2,
  "snapshot_every": 50)" + extra + R"(
})";
  return dir + "/job.json";
}

// The tiny job's config text, started at the ground truth with a learning rate too small to move
// it: the loss of each iteration is then the renders' own Monte Carlo noise.
std::string tiny_job_at_truth(const std::string& dir, int iterations, const std::string& extra = "") {
  std::string text;
  {
    std::ifstream f(write_tiny_job(dir, iterations, extra));
    text.assign(std::istreambuf_iterator<char>(f), {});
  }
  const std::string from = R"("lr": 0.05, "bounds": [0, 1]})",
                    to = R"("lr": 1e-9, "bounds": [0, 1], "init": "truth.exr"})";
  REQUIRE(text.find(from) != std::string::npos);
  text.replace(text.find(from), from.size(), to);
  return text;
}

nlohmann::json read_json(const std::string& path) {
  std::ifstream f(path);
  return nlohmann::json::parse(f);
}

std::vector<float> read_all(const std::string& path) {
  Image img = read_image(path, false);
  return img.data;
}

}  // namespace

TEST_CASE("a tiny optimization cuts the loss at least 10x", "[optimizer]") {
  // No wall-clock assertion: timings belong in bench/, and a busy machine made this one flake.
  const std::string dir = test::temp_dir("tiny-opt");
  // 32×32 views see the 64×64 texture at about 2 texels per pixel over a blurred footprint:
  // compare with the truth at 16×16, the detail the views determine.
  const std::string job = write_tiny_job(dir, 60, R"(, "rmse_resolution": [16, 16])");
  REQUIRE(run_optimize(job, "", 0, true) == 0);
  auto summary = read_json(dir + "/out/summary.json");
  double first = summary["initial_loss"], last = summary["final_loss"];
  INFO("loss " << first << " -> " << last);
  CHECK(first / last >= 10.0);
  CHECK(summary["parameters"]["floor.albedo"]["rmse_final"].get<double>() <
        summary["parameters"]["floor.albedo"]["rmse_initial"].get<double>() / 3);
  CHECK(summary["parameters"]["floor.albedo"]["rmse_resolution"] == nlohmann::json({16, 16}));
  // The validation loss (every 10 iterations by default, fixed seeds) falls cleanly.
  const double v0 = summary["validation_loss_initial"], v1 = summary["validation_loss_final"];
  INFO("validation loss " << v0 << " -> " << v1);
  CHECK(v0 / v1 >= 10.0);
  std::ifstream validation(dir + "/out/validation.csv");
  std::string line;
  int rows = 0;
  while (std::getline(validation, line)) ++rows;
  CHECK(rows == 1 + 7);  // header, iterations 0, 10, …, 60
  // report.html: one page with everything inlined (no other file, no network), finished (no reload).
  std::string report;
  {
    std::ifstream f(dir + "/out/report.html");
    report.assign(std::istreambuf_iterator<char>(f), {});
  }
  CHECK(report.rfind("<!DOCTYPE html>", 0) == 0);
  CHECK(report.find("</html>") != std::string::npos);
  CHECK(report.find("Finished") != std::string::npos);
  CHECK(report.find("http-equiv=\"refresh\"") == std::string::npos);
  CHECK(report.find("validation loss") != std::string::npos);
  size_t images = 0;
  for (size_t at = report.find("src=\""); at != std::string::npos; at = report.find("src=\"", at + 1)) {
    CHECK(report.compare(at, 38, "src=\"data:image/png;base64,iVBORw0KGgo") == 0);  // an inline PNG
    ++images;
  }
  CHECK(images == 4);  // loss, parameter RMSE, comparison, final texture
  // The table's RMSE "start" is the RMSE before the first update: the summary's rmse_initial.
  {
    const std::string row = "against the truth</td><td>";
    const size_t at = report.find(row);
    REQUIRE(at != std::string::npos);
    const double start = std::stod(report.substr(at + row.size(), 20));
    const double initial = summary["parameters"]["floor.albedo"]["rmse_initial"];
    CHECK(start == Approx(initial).epsilon(1e-3));
  }
  for (const char* f : {"loss.csv", "validation.csv", "loss.png", "report.html", "param_rmse.png", "compare.png",
                        "summary.json", "final/floor.albedo.exr", "final/floor.albedo.png",
                        "snapshots/floor.albedo_00050.png", "checkpoint/state.json"})
    CHECK(fs::exists(dir + "/out/" + f));
}

TEST_CASE("the validation loss leaves out the renders' own Monte Carlo noise", "[optimizer]") {
  // Started at the ground truth and barely moved: the loss of each iteration is then mostly the
  // variance of its 8-spp render, while the validation loss, (I_a − T)(I_b − T) over two
  // independent renders, estimates only the expected render's distance to the 64-spp target.
  const std::string dir = test::temp_dir("validation");
  const std::string job = dir + "/job.json";
  const std::string text = tiny_job_at_truth(dir, 4, R"(, "validation": {"every": 2, "spp": 8})");
  std::ofstream(job) << text;
  REQUIRE(run_optimize(job, "", 0, true) == 0);
  auto summary = read_json(dir + "/out/summary.json");
  const double raw = summary["initial_loss"], validation = summary["validation_loss_initial"];
  INFO("loss of the first iteration " << raw << ", validation loss " << validation);
  CHECK(std::abs(validation) < 0.3 * raw);
  CHECK(summary["validation"]["every"] == 2);
  std::ifstream csv(dir + "/out/validation.csv");
  std::string line;
  int rows = 0;
  while (std::getline(csv, line)) ++rows;
  CHECK(rows == 1 + 3);  // iterations 0, 2, 4
}

TEST_CASE("resuming from a checkpoint reaches the same parameters as an uninterrupted run", "[optimizer]") {
  // One worker thread: gradient accumulation order (atomic float adds) is then fixed, so the two
  // runs must agree bit for bit. In log space too: checkpoints keep x and Adam's moments of ln x.
  for (const std::string param_extra : {"", R"(, "parametrization": "log")"}) {
    INFO("parameter keys: " << param_extra);
    const std::string a = test::temp_dir("resume-a"), b = test::temp_dir("resume-b");
    REQUIRE(run_optimize(write_tiny_job(a, 6, "", param_extra), "", 1, true) == 0);
    // Interrupted after 4 iterations (the checkpoint interval is 2), then resumed to 6.
    REQUIRE(run_optimize(write_tiny_job(b, 4, "", param_extra), "", 1, true) == 0);
    const std::string full = write_tiny_job(b, 6, "", param_extra);
    REQUIRE(run_optimize(full, b + "/out", 1, true) == 0);
    CHECK(read_all(a + "/out/final/floor.albedo.exr") == read_all(b + "/out/final/floor.albedo.exr"));
    std::ifstream la(a + "/out/loss.csv"), lb(b + "/out/loss.csv");
    std::string line_a, line_b;
    int rows = 0;
    while (std::getline(la, line_a) && std::getline(lb, line_b)) {
      // Same iteration and loss; the wall-clock column differs.
      CHECK(line_a.substr(0, line_a.find(',', line_a.find(',') + 1)) ==
            line_b.substr(0, line_b.find(',', line_b.find(',') + 1)));
      ++rows;
    }
    CHECK(rows == 7);
  }
}

TEST_CASE("bfloat16 moments: stochastic rounding is unbiased and keeps Adam's second moment moving", "[optimizer]") {
  // A float between two bfloat16 values: over all 2^16 random words the mean is exactly x.
  const float x = 1.f + 1.f / 3.f * 0x1p-7f;
  REQUIRE(bf16_to_float(float_to_bf16(x, 0)) != x);
  double sum = 0;
  for (uint32_t r = 0; r < 65536; ++r) sum += bf16_to_float(float_to_bf16(x, uint16_t(r)));
  CHECK(sum / 65536 == double(x));
  CHECK(bf16_to_float(float_to_bf16(-x, 12345)) == -bf16_to_float(float_to_bf16(x, 12345)));
  // Adam's second moment with beta2 = 0.999 relaxing from 1 to g² = 4: each update is 0.1% of v,
  // below half a bfloat16 step. Stochastic rounding follows the exact EMA; rounding to nearest
  // (the negative control) never leaves 1.
  uint64_t state = 0x9e3779b97f4a7c15ull;
  auto random16 = [&] {
    state = state * 6364136223846793005ull + 1442695040888963407ull;
    return uint16_t(state >> 48);
  };
  uint16_t stochastic = float_to_bf16(1.f, 0), nearest = stochastic;
  double exact = 1;
  for (int t = 0; t < 3000; ++t) {
    exact = 0.999 * exact + 0.001 * 4;
    stochastic = float_to_bf16(float(0.999 * bf16_to_float(stochastic) + 0.001 * 4), random16());
    nearest = float_to_bf16(float(0.999 * bf16_to_float(nearest) + 0.001 * 4), 0x7fff);
  }
  INFO("exact " << exact << ", stochastic " << bf16_to_float(stochastic) << ", nearest " << bf16_to_float(nearest));
  CHECK(std::abs(bf16_to_float(stochastic) - exact) < 0.03 * exact);
  CHECK(bf16_to_float(nearest) == 1.f);
}

TEST_CASE("Adam with bfloat16 moments converges like float32 and halves the moment memory", "[optimizer]") {
  // 4096 values pulled to targets by noisy gradients (noise 10x the signal near the end).
  const size_t n = 4096;
  std::vector<float> target(n);
  for (size_t i = 0; i < n; ++i) target[i] = float(std::sin(0.01 * double(i)));
  auto run = [&](bool half) {
    AdamSettings s;
    s.learning_rate = 0.02;
    s.bf16_moments = half;
    Adam adam(s);
    std::vector<float> x(n, 0.f), g(n);
    uint64_t state = 42;
    for (int t = 0; t < 400; ++t) {
      for (size_t i = 0; i < n; ++i) {
        state = state * 6364136223846793005ull + 1442695040888963407ull;
        const double noise = (double(state >> 11) * 0x1p-53 - 0.5) * 0.2;
        g[i] = float(2 * (x[i] - target[i]) + noise);
      }
      adam.step(x, g);
    }
    CHECK((half ? adam.m16.size() : adam.m.size()) == n);
    CHECK((half ? adam.m.size() : adam.m16.size()) == 0);
    double se = 0;
    for (size_t i = 0; i < n; ++i) se += (double(x[i]) - target[i]) * (double(x[i]) - target[i]);
    return std::sqrt(se / double(n));
  };
  const double rmse32 = run(false), rmse16 = run(true);
  INFO("RMSE float32 " << rmse32 << ", bfloat16 " << rmse16);
  CHECK(rmse32 < 0.02);
  CHECK(rmse16 < 1.1 * rmse32);
}

TEST_CASE("resuming with bfloat16 moments reaches the same parameters as an uninterrupted run", "[optimizer]") {
  const std::string a = test::temp_dir("resume16-a"), b = test::temp_dir("resume16-b");
  auto half = [](const std::string& job) {
    nlohmann::json j = read_json(job);
    j["parameters"]["floor.albedo"]["moments"] = "bfloat16";
    std::ofstream(job) << j.dump();
    return job;
  };
  REQUIRE(run_optimize(half(write_tiny_job(a, 6)), "", 1, true) == 0);
  REQUIRE(run_optimize(half(write_tiny_job(b, 4)), "", 1, true) == 0);
  auto state = read_json(b + "/out/checkpoint/state.json");
  CHECK(state["parameters"]["floor.albedo"]["moments"] == "bfloat16");
  CHECK(fs::file_size(b + "/out/checkpoint/floor.albedo.adam_m") == 64 * 64 * 3 * 2);
  // A float32 config cannot continue from bfloat16 moments.
  try {
    run_optimize(write_tiny_job(b, 6), b + "/out", 1, true);
    FAIL("resumed float32 moments from a bfloat16 checkpoint");
  } catch (const InputError& e) {
    CHECK(std::string(e.what()).find("precision") != std::string::npos);
  }
  REQUIRE(run_optimize(half(write_tiny_job(b, 6)), b + "/out", 1, true) == 0);
  CHECK(read_all(a + "/out/final/floor.albedo.exr") == read_all(b + "/out/final/floor.albedo.exr"));
  // And the bfloat16 run is not the float32 one (the option is in effect).
  const std::string c = test::temp_dir("resume16-c");
  REQUIRE(run_optimize(write_tiny_job(c, 6), "", 1, true) == 0);
  CHECK(read_all(a + "/out/final/floor.albedo.exr") != read_all(c + "/out/final/floor.albedo.exr"));
}

TEST_CASE("Adam's warm-up ramps the learning rate after every reset", "[optimizer]") {
  // A constant gradient makes m̂ / √v̂ = 1 exactly, so each update is the step's learning rate.
  AdamSettings s;
  s.learning_rate = 0.4;
  s.warmup = 4;
  Adam adam(s);
  std::vector<float> x{0.f}, g{1.f};
  auto steps = [&] {
    std::vector<double> d;
    for (int t = 0; t < 6; ++t) {
      const float before = x[0];
      adam.step(x, g);
      d.push_back(double(before) - x[0]);
    }
    return d;
  };
  const std::vector<double> expected{0.1, 0.2, 0.3, 0.4, 0.4, 0.4};
  for (int round = 0; round < 2; ++round) {
    const std::vector<double> d = steps();
    for (size_t k = 0; k < d.size(); ++k) CHECK(d[k] == Approx(expected[k]).epsilon(1e-5));
    adam.reset(1);  // a resolution change: the ramp starts again
  }
  // Without warm-up the first step is the full rate (negative control for the ramp).
  Adam plain(AdamSettings{.learning_rate = 0.4});
  std::vector<float> y{0.f};
  plain.step(y, g);
  CHECK(y[0] == Approx(-0.4f));
}

TEST_CASE("iterate averaging returns the mean of the iterates after average_from", "[optimizer]") {
  // One worker thread: runs of 5 and 6 iterations retrace each other bit for bit, so the run that
  // averages from 4 must return exactly the mean of their results (iterates 5 and 6).
  const std::string a = test::temp_dir("avg-5"), b = test::temp_dir("avg-6"), c = test::temp_dir("avg-mean");
  REQUIRE(run_optimize(write_tiny_job(a, 5), "", 1, true) == 0);
  REQUIRE(run_optimize(write_tiny_job(b, 6), "", 1, true) == 0);
  auto averaging = [](const std::string& job, int from) {
    nlohmann::json j = read_json(job);
    j["parameters"]["floor.albedo"]["average_from"] = from;
    std::ofstream(job) << j.dump();
    return job;
  };
  REQUIRE(run_optimize(averaging(write_tiny_job(c, 6), 4), "", 1, true) == 0);
  const std::vector<float> x5 = read_all(a + "/out/final/floor.albedo.exr"),
                           x6 = read_all(b + "/out/final/floor.albedo.exr"),
                           mean = read_all(c + "/out/final/floor.albedo.exr");
  REQUIRE(x5.size() == mean.size());
  REQUIRE(x5 != x6);
  size_t off = 0;
  for (size_t i = 0; i < mean.size(); ++i) off += mean[i] != x5[i] + (x6[i] - x5[i]) / 2.f;
  CHECK(off == 0);
  auto summary = read_json(c + "/out/summary.json");
  const auto& p = summary["parameters"]["floor.albedo"];
  CHECK(p["averaged_iterates"] == 2);
  CHECK(p["rmse_last_iterate"].get<double>() ==
        Approx(read_json(b + "/out/summary.json")["parameters"]["floor.albedo"]["rmse_final"].get<double>()));
  CHECK(p["rmse_final"].get<double>() != p["rmse_last_iterate"].get<double>());
  // The average survives a resume: 5 iterations (the last checkpoint holds iterate 5 as the
  // average of one), then on to 6.
  const std::string d = test::temp_dir("avg-resume");
  REQUIRE(run_optimize(averaging(write_tiny_job(d, 5), 4), "", 1, true) == 0);
  CHECK(read_json(d + "/out/checkpoint/state.json")["parameters"]["floor.albedo"]["average_count"] == 1);
  REQUIRE(run_optimize(averaging(write_tiny_job(d, 6), 4), d + "/out", 1, true) == 0);
  CHECK(read_all(d + "/out/final/floor.albedo.exr") == mean);
  // average_from at the last iteration averages nothing: the plain result.
  const std::string e = test::temp_dir("avg-none");
  REQUIRE(run_optimize(averaging(write_tiny_job(e, 6), 6), "", 1, true) == 0);
  CHECK(read_all(e + "/out/final/floor.albedo.exr") == x6);
}

TEST_CASE("a stage's own average_from averages within the stage, and the next stage starts from that average",
          "[optimizer]") {
  // One worker thread, so runs of different lengths retrace each other bit for bit. Stage 0 (16²,
  // iterations 0–2) averages its iterates after iteration 1; stage 1 (32²) steps with a learning
  // rate too small to move a value, so its result is the resampled start it was given.
  const std::string stages =
      R"(, "schedule": [{"until": 3, "resolution": [16, 16]AVG}, {"until": 5, "resolution": [32, 32], "lr": 1e-30}])";
  auto job = [&](const std::string& name, int iterations, bool average) {
    std::string sched = stages;
    sched.replace(sched.find("AVG"), 3, average ? R"(, "average_from": 1)" : "");
    const std::string dir = test::temp_dir(name);
    REQUIRE(run_optimize(write_tiny_job(dir, iterations, "", sched), "", 1, true) == 0);
    return read_all(dir + "/out/final/floor.albedo.exr");
  };
  const std::vector<float> x2 = job("stage-avg-2", 2, false), x3 = job("stage-avg-3", 3, false),
                           mean = job("stage-avg-mean", 3, true);
  REQUIRE(x2.size() == 16 * 16 * 3);
  REQUIRE(x2 != x3);
  size_t off = 0;
  for (size_t i = 0; i < mean.size(); ++i) off += mean[i] != x2[i] + (x3[i] - x2[i]) / 2.f;
  CHECK(off == 0);
  // Into stage 1: from the average (resampled as any stage change resamples), not from iterate 3.
  const std::vector<float> from_mean = job("stage-avg-next", 4, true);
  REQUIRE(from_mean.size() == 32 * 32 * 3);
  CHECK(from_mean == resample(mean, 16, 16, 3, 32, 32));
  CHECK(from_mean != resample(x3, 16, 16, 3, 32, 32));  // what the last iterate would have given
}

// The regularizers' gradients against central differences of the values they return, on a grid
// and on an image with values of both signs; a sign-flipped gradient fails the same check.
TEST_CASE("regularizers: total variation and L1 gradients match finite differences", "[optimizer]") {
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(0.05f, 1.f);  // |θ| away from L1's kink at 0
  std::bernoulli_distribution negative(0.5);
  auto make = [&](std::vector<int> shape) {
    Param p;
    p.shape = std::move(shape);
    size_t n = 1;
    for (int d : p.shape) n *= size_t(d);
    p.value.resize(n);
    for (float& v : p.value) v = negative(rng) ? -u(rng) : u(rng);
    p.grad.assign(n, 0.f);
    return p;
  };
  using Reg = double (*)(Param&, double);
  for (const Reg reg : {Reg(add_total_variation), Reg(add_l1)}) {
    for (const std::vector<int>& shape : {std::vector<int>{3, 4, 5, 2}, std::vector<int>{4, 6, 3}}) {
      Param p = make(shape);
      const double w = 0.7;
      const double value = reg(p, w);
      CHECK(value > 0);
      const std::vector<float> grad = p.grad;
      size_t agree = 0, flipped_agree = 0;
      for (size_t i = 0; i < p.value.size(); ++i) {
        const float x = p.value[i], h = 1e-3f;
        p.value[i] = x + h;
        const double up = reg(p, w);
        p.value[i] = x - h;
        const double down = reg(p, w);
        p.value[i] = x;
        const double fd = (up - down) / (2.0 * double(h));
        const double tol = 2e-3 * w / double(p.value.size()) + 1e-3 * std::abs(fd);
        INFO("element " << i << " fd " << fd << " analytic " << grad[i]);
        CHECK(std::abs(grad[i] - fd) < tol);
        agree += std::abs(grad[i] - fd) < tol;
        flipped_agree += std::abs(-grad[i] - fd) < tol;
      }
      CHECK(agree == p.value.size());
      CHECK(flipped_agree < p.value.size() / 10);
    }
  }
  // Total variation leaves scalars and other non-image parameters alone (the job refuses it on
  // them); L1 applies to any parameter (see "the L1 regularizer applies to any parameter").
  Param scalar = make({1});
  CHECK(add_total_variation(scalar, 1.0) == 0.0);
  CHECK(scalar.grad[0] == 0.f);
}

TEST_CASE("config errors are one clear line naming the config", "[optimizer][errors]") {
  const std::string dir = test::temp_dir("opt-errors");
  write_tiny_job(dir, 2);
  auto expect_error = [&](const std::string& json_text, const std::string& fragment) {
    std::ofstream(dir + "/bad.json") << json_text;
    try {
      run_optimize(dir + "/bad.json", "", 0, true);
      FAIL("no error for: " << json_text);
    } catch (const InputError& e) {
      std::string msg = e.what();
      INFO(msg);
      CHECK(msg.find("\n") == std::string::npos);
      CHECK(msg.find(fragment) != std::string::npos);
    }
  };
  const std::string head = R"({"scene": "scene.json", "output": "o", )";
  expect_error(head + R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": ["top"]}})",
               "bad.json: /views: give \"targets\"");
  expect_error(
      head +
          R"("parameters": {"floor.nope": {"lr": 0.1}}, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "unknown parameter");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1, "bounds": [1, 0]}}, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "/parameters/floor.albedo/bounds");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1, "moments": "fp8"}}, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "/parameters/floor.albedo/moments: expected \"float32\" or \"bfloat16\"");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1, "warmup": -3}}, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "/parameters/floor.albedo/warmup");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1, "average_from": 2.5}}, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "/parameters/floor.albedo/average_from");
  Image small(5, 5, 3);
  write_image(dir + "/small.exr", small);
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": ["top"], "targets": {"top": "small.exr"}}})",
      "small.exr: target is 5x5");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": ["top"], "targets": {"top": "small.exr"}}, "typo": 1})",
      "unknown key 'typo'");
  expect_error(R"({"scene": "scene.json", )", "bad.json: 1:");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": [{"name": "top", "origin": [0, 1, 1], "target": [0, 0, 0], "fov": 40}], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "camera name 'top' already exists");
  expect_error(
      head +
          R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": [{"origin": [0, 1, 0], "fov": 40}], "reference": {"set": {"floor.albedo": "truth.exr"}}}})",
      "/views/cameras/0: missing required key 'target'");
  // Large steps: only for a mesh's positions, not with bounds, λ > 0.
  auto with_parameters = [&](const std::string& parameters) {
    return head + R"("parameters": )" + parameters +
           R"(, "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}}}})";
  };
  // Regularizers: one {type, weight} or a list, each type once.
  expect_error(
      with_parameters(R"({"floor.albedo": {"lr": 0.1, "regularizer": {"type": "l2", "weight": 1}}})"),
      "bad.json: /parameters/floor.albedo/regularizer/type: unknown regularizer 'l2' (expected \"tv\" or \"l1\")");
  expect_error(
      with_parameters(
          R"({"floor.albedo": {"lr": 0.1, "regularizer": [{"type": "l1", "weight": 1}, {"type": "l1", "weight": 2}]}})"),
      "bad.json: /parameters/floor.albedo/regularizer/1/type: regularizer 'l1' given twice");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "regularizer": [{"type": "tv", "weight": -1}]}})"),
               "bad.json: /parameters/floor.albedo/regularizer/0/weight");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "regularizer": [3]}})"),
               "bad.json: /parameters/floor.albedo/regularizer/0: expected an object");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "large_steps": {"lambda": 10}}})"),
               "/parameters/floor.albedo/large_steps: only for a mesh's positions");
  expect_error(with_parameters(R"({"floor.positions": {"lr": 0.1, "bounds": [0, 1], "large_steps": {"lambda": 10}}})"),
               "/parameters/floor.positions/bounds: bounds cannot be combined with large_steps");
  expect_error(with_parameters(R"({"floor.positions": {"lr": 0.1, "large_steps": {"lambda": 0}}})"),
               "/parameters/floor.positions/large_steps/lambda");
  expect_error(with_parameters(R"({"floor.positions": {"lr": 0.1, "large_steps": {"lambda": 5, "lamda": 1}}})"),
               "unknown key 'lamda'");
  // A schedule stage's large_steps_lambda: ≥ 0, and only for grids.
  expect_error(
      with_parameters(
          R"({"floor.albedo": {"lr": 0.1, "schedule": [{"until": 2, "resolution": [8, 8], "large_steps_lambda": -1}]}})"),
      "/parameters/floor.albedo/schedule/0/large_steps_lambda");
  expect_error(
      with_parameters(
          R"({"floor.albedo": {"lr": 0.1, "schedule": [{"until": 2, "resolution": [8, 8], "large_steps_lambda": 2}]}})"),
      "/parameters/floor.albedo/large_steps: only for a mesh's positions (<shape>.positions) or a grid");
  // A log parametrization: "linear" or "log", an upper bound > 0, not for a mesh's positions.
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "parametrization": "exp"}})"),
               "/parameters/floor.albedo/parametrization: expected \"linear\" or \"log\"");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "bounds": [-2, -1], "parametrization": "log"}})"),
               "/parameters/floor.albedo/bounds: a log parametrization needs an upper bound > 0");
  expect_error(with_parameters(R"({"floor.positions": {"lr": 0.1, "parametrization": "log"}})"),
               "/parameters/floor.positions/parametrization: \"log\" is for positive values");
  // Adam's betas: two numbers in [0, 1).
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "betas": [0.9, 1.0]}})"),
               "/parameters/floor.albedo/betas: expected [beta1, beta2], each in [0, 1)");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "betas": 0.9}})"), "/parameters/floor.albedo/betas");
  // A schedule stage's own iterate averaging: a non-negative iteration.
  expect_error(
      with_parameters(
          R"({"floor.albedo": {"lr": 0.1, "schedule": [{"until": 2, "resolution": [8, 8], "average_from": -1}]}})"),
      "/parameters/floor.albedo/schedule/0/average_from");
  // An image schedule: a factor that divides every view's resolution, stages in order.
  const std::string tail = R"("parameters": {"floor.albedo": {"lr": 0.1}}, "views": {"cameras": ["top"],
      "reference": {"set": {"floor.albedo": "truth.exr"}}}, )";
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "downsample": 3}]})",
               "bad.json: /image_schedule/0/downsample: 3 does not divide the 32x32 of view 'top'");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "downsample": 2}, {"until": 2, "downsample": 4}]})",
               "bad.json: /image_schedule/1/until: stages must be increasing");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "downsample": 0}]})", "/image_schedule/0/downsample");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "factor": 2}]})", "unknown key 'factor'");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "views_per_iteration": -1}]})",
               "/image_schedule/0/views_per_iteration");
  // A block-mean loss: blocks that divide every render, at every image-schedule factor.
  expect_error(head + tail + R"("loss_downsample": 3})",
               "bad.json: /loss_downsample: 3 does not divide the 32x32 of view 'top'");
  expect_error(head + tail + R"("loss_downsample": 32, "image_schedule": [{"until": 2, "downsample": 2}]})",
               "bad.json: /loss_downsample: 32 does not divide the 16x16 of view 'top' at image-schedule downsample 2");
  expect_error(head + tail + R"("loss_downsample": 0})", "/loss_downsample");
  // A stage's own block loss: checked against that stage's renders.
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "loss_downsample": 3}]})",
               "bad.json: /image_schedule/0/loss_downsample: 3 does not divide the 32x32 of view 'top'");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "downsample": 2, "loss_downsample": 32}]})",
               "bad.json: /image_schedule/0/loss_downsample: 32 does not divide the 16x16 of view 'top' at "
               "image-schedule downsample 2");
  expect_error(head + tail + R"("image_schedule": [{"until": 2, "loss_downsample": 0}]})",
               "/image_schedule/0/loss_downsample");
  // Whole numbers were read as numbers and truncated (2.5 iterations ran 2); a stage ending at
  // iteration 0 was accepted and never used.
  expect_error(head + tail + R"("iterations": 2.5})", "bad.json: /iterations: expected a whole number");
  expect_error(head + tail + R"("checkpoint_every": 2.7})", "bad.json: /checkpoint_every: expected a whole number");
  expect_error(head + tail + R"("image_schedule": [{"until": 2.5}]})", "/image_schedule/0/until: expected a whole");
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "schedule": [{"until": 0, "resolution": [8, 8]}]}})"),
               "/parameters/floor.albedo/schedule/0/until: value 0 outside the valid range");
  // A bad loss named neither the config nor the key.
  expect_error(head + tail + R"("loss": "l3"})", "bad.json: /loss: unknown loss 'l3'");
  // An init of the wrong type pointed at /parameters/floor.albedo/floor.albedo.
  expect_error(with_parameters(R"({"floor.albedo": {"lr": 0.1, "init": {"a": 1}}})"),
               "bad.json: /parameters/floor.albedo/init: expected a file name, a number or a list of numbers");
  // Exponential decay ignored "every".
  expect_error(
      with_parameters(R"({"floor.albedo": {"lr": 0.1, "decay": {"type": "exponential", "rate": 0.5, "every": 10}}})"),
      "/parameters/floor.albedo/decay/every: only for \"step\" decay");
  // Total variation of a parameter that is no image or grid did nothing, silently.
  expect_error(with_parameters(R"({"environment.radiance": {"lr": 0.1, "regularizer": {"type": "tv", "weight": 1}}})"),
               "bad.json: /parameters/environment.radiance/regularizer: \"tv\" is for image and grid parameters "
               "(this one has shape [3])");
  // The scene's own value outside the bounds was rendered and differentiated once, then clamped.
  expect_error(with_parameters(R"({"environment.radiance": {"lr": 0.1, "bounds": [0.2, 0.8]}})"),
               "bad.json: /parameters/environment.radiance/bounds: the scene's value, element 0 = 1, is outside [0.2, "
               "0.8] (give an \"init\" inside them)");
}

TEST_CASE("a grid stage without large steps is plain Adam, uniform Adam only where large steps run", "[optimizer]") {
  // A parameter's large_steps sets uniform Adam; a schedule stage with large_steps_lambda 0 is
  // documented as plain Adam, but stepped with the uniform second moment (the largest element's),
  // so only the largest-gradient element moved by lr.
  AdamSettings uniform;
  uniform.learning_rate = 0.1;
  uniform.uniform = true;
  AdamSettings plain = uniform;
  plain.uniform = false;
  const std::vector<float> gradient = {1.f, -0.01f, 0.2f, 0.f};
  std::vector<float> a(4, 0.5f), b(4, 0.5f), c(4, 0.5f);
  Adam ua(uniform), pa(plain), ub(uniform);
  ua.step(a, gradient, false);
  pa.step(b, gradient);
  ub.step(c, gradient);
  CHECK(a == b);
  CHECK(a[1] == Approx(0.6f));                 // plain Adam's first step: ±lr for every element with a gradient
  CHECK(c[1] == Approx(0.5f + 0.1f * 0.01f));  // uniform: scaled by the largest gradient
}

TEST_CASE("a checkpoint whose parameter shape does not fit the parameter is refused", "[optimizer][errors]") {
  // A negative dimension wrapped the size ("internal error: cannot create std::vector larger than
  // max_size()"); a reshaped texture of the same value count resumed on scrambled texels.
  const std::string dir = test::temp_dir("opt-shape");
  REQUIRE(run_optimize(write_tiny_job(dir, 2), "", 1, true) == 0);
  const std::string state_path = dir + "/out/checkpoint/state.json";
  const nlohmann::json state = read_json(state_path);
  REQUIRE(state["parameters"]["floor.albedo"]["shape"] == nlohmann::json::array({64, 64, 3}));
  for (const char* shape : {"[-64, -64, 3]", "[64, 64, 3, 1]", "[64, 64, 1]", "[12288]", "[0, 64, 3]"}) {
    INFO(shape);
    nlohmann::json bad = state;
    bad["parameters"]["floor.albedo"]["shape"] = nlohmann::json::parse(shape);
    std::ofstream(state_path) << bad.dump();
    try {
      run_optimize(write_tiny_job(dir, 4), dir + "/out", 1, true);
      FAIL("resumed with shape " << shape);
    } catch (const InputError& e) {
      const std::string msg = e.what();
      INFO(msg);
      CHECK(msg.find("state.json") != std::string::npos);
      CHECK(msg.find("does not fit the parameter ([64, 64, 3])") != std::string::npos);
    }
  }
  std::ofstream(state_path) << state.dump();
  CHECK(run_optimize(write_tiny_job(dir, 4), dir + "/out", 1, true) == 0);
}

TEST_CASE("the L1 regularizer applies to any parameter", "[optimizer]") {
  // It returned 0 for anything but images and grids: an L1 prior on an RGB value did nothing.
  Param p;
  p.shape = {3};
  p.value = {0.5f, -0.25f, 0.f};
  p.grad.assign(3, 0.f);
  CHECK(add_l1(p, 3.0) == Approx(0.75));
  CHECK(p.grad == std::vector<float>{1.f, -1.f, 0.f});
}

TEST_CASE("an image schedule renders early iterations smaller, against block means of the targets", "[optimizer]") {
  const std::string dir = test::temp_dir("opt-image-schedule");
  const std::string job = write_tiny_job(dir, 4);
  // A half-resolution film records the 2×2 block means of the full one (pixels are box-filtered):
  // the downsampled targets are exactly what the smaller renders estimate. 16² at 1024 spp
  // against 32² at 256 spp (the same samples per area), per pixel and channel.
  auto scene = load_scene(dir + "/scene.json");
  scene->cameras[1].width = scene->cameras[1].height = 16;
  scene->cameras[1].update();
  const Image small = render(*scene, {1, 1024, 3, false});
  scene->cameras[1].width = scene->cameras[1].height = 32;
  scene->cameras[1].update();
  const Image full = render(*scene, {1, 256, 4, false});
  const Image blocks = box_downsample(full, 2);
  REQUIRE(blocks.width == 16);
  double mean_difference = 0, mean_value = 0, worst = 0;
  for (size_t i = 0; i < small.data.size(); ++i) {
    mean_difference += double(small.data[i]) - blocks.data[i];
    mean_value += small.data[i];
    worst = std::max(worst, std::abs(double(small.data[i]) - blocks.data[i]));
  }
  mean_difference /= double(small.data.size());
  mean_value /= double(small.data.size());
  INFO("mean 16² value " << mean_value << ", mean difference " << mean_difference << ", largest pixel difference "
                         << worst);
  CHECK(std::abs(mean_difference) < 2e-3 * mean_value);
  // Pixel by pixel within the noise of 1024 samples of this direct-lit floor; a film shifted by
  // half a small pixel would move the checker's edges (albedo 0.08 against 0.85) by far more.
  CHECK(worst < 0.05 * mean_value);

  // The job: iterations 0–2 at 16², then 32². The loss of a small render is taken against the
  // block means (lower noise: four times the samples per pixel area).
  std::string text;
  {
    std::ifstream f(job);
    text.assign(std::istreambuf_iterator<char>(f), {});
  }
  auto with_schedule = [&](const std::string& out, const std::string& schedule) {
    std::string t = text;
    t.replace(t.find("\"output\": \"out\""), 15, "\"output\": \"" + out + "\"");
    t.insert(t.rfind('}'), ", \"image_schedule\": " + schedule);
    std::ofstream(dir + "/" + out + ".json") << t;
    return dir + "/" + out + ".json";
  };
  REQUIRE(run_optimize(with_schedule("scheduled", R"([{"until": 3, "downsample": 2}])"), "", 1, true) == 0);
  REQUIRE(run_optimize(with_schedule("plain", "[]"), "", 1, true) == 0);
  auto losses = [&](const std::string& out) {
    std::ifstream f(dir + "/" + out + "/loss.csv");
    std::string line;
    std::vector<double> l;
    std::getline(f, line);
    while (std::getline(f, line)) l.push_back(std::stod(line.substr(line.find(',') + 1)));
    return l;
  };
  const std::vector<double> scheduled = losses("scheduled"), plain = losses("plain");
  REQUIRE(scheduled.size() == 4);
  REQUIRE(plain.size() == 4);
  // Iteration 0 starts from the same texture: the 16² loss is the 32² loss without most of its
  // per-pixel noise and without the detail a 16² film averages away, so it is smaller.
  INFO("iteration 0: 16² loss " << scheduled[0] << ", 32² loss " << plain[0]);
  CHECK(scheduled[0] < plain[0]);
  CHECK(scheduled[0] > 0.5 * plain[0]);  // the same images, not another problem

  // A stage's views_per_iteration: iterations 0–1 render one view, as a job of one view per
  // iteration does (the same views and seeds: the same losses, bit for bit on one thread); from
  // iteration 2 all three views, as the plain job does at its start.
  auto with_views = [&](const std::string& out, const std::string& extra) {
    std::string t = text;
    t.replace(t.find("\"output\": \"out\""), 15, "\"output\": \"" + out + "\"");
    t.insert(t.rfind('}'), extra);
    std::ofstream(dir + "/" + out + ".json") << t;
    return dir + "/" + out + ".json";
  };
  REQUIRE(run_optimize(with_views("staged", R"(, "image_schedule": [{"until": 2, "views_per_iteration": 1}])"), "", 1,
                       true) == 0);
  REQUIRE(run_optimize(with_views("one", R"(, "views_per_iteration": 1)"), "", 1, true) == 0);
  const std::vector<double> staged = losses("staged"), one = losses("one");
  REQUIRE(staged.size() == 4);
  REQUIRE(one.size() == 4);
  CHECK(staged[0] == one[0]);
  CHECK(staged[1] == one[1]);
  CHECK(staged[0] != plain[0]);  // one view's loss, not the mean over three
  CHECK(staged[2] != one[2]);
}

TEST_CASE("a block-mean loss: its adjoint is its derivative, per pixel and through a render", "[optimizer]") {
  // Per pixel: the value is the loss of the block means, and the adjoint its central differences.
  Image image(6, 4, 3), target(6, 4, 3);
  uint64_t state = 12345;
  auto uniform = [&] { return float((state = mix64(state)) >> 40) / float(1 << 24); };
  for (auto& v : image.data) v = 0.2f + uniform();
  for (auto& v : target.data) v = 0.2f + uniform();
  for (LossType type : {LossType::L2, LossType::L1, LossType::RelativeL2}) {
    const LossResult r = compute_block_loss(type, image, target, 2);
    CHECK(r.value ==
          Approx(compute_loss(type, box_downsample(image, 2), box_downsample(target, 2)).value).epsilon(1e-12));
    REQUIRE(r.adjoint.width == 6);
    REQUIRE(r.adjoint.height == 4);
    for (size_t i = 0; i < image.data.size(); ++i) {
      const float h = 1e-3f;
      Image plus = image, minus = image;
      plus.data[i] += h, minus.data[i] -= h;
      const double fd =
          (compute_block_loss(type, plus, target, 2).value - compute_block_loss(type, minus, target, 2).value) /
          (double(plus.data[i]) - double(minus.data[i]));
      INFO(loss_name(type) << " value " << i);
      CHECK(r.adjoint.data[i] == Approx(fd).epsilon(2e-3).margin(1e-7));
    }
  }
  CHECK_THROWS_AS(compute_block_loss(LossType::L2, image, target, 4), InputError);  // 4 does not divide 6x4
  CHECK_THROWS_AS(compute_block_loss(LossType::L2, image, box_downsample(target, 2), 2), InputError);  // 3x2 target

  // Through a render: with equal seeds the adjoint pass differentiates the very render it replays,
  // so δI of the block loss gives its directional derivative along a texture perturbation (the
  // albedo does not move sampling) — a δI sent to the wrong pixels would not.
  const std::string dir = test::temp_dir("opt-block-loss");
  write_tiny_job(dir, 1);
  auto scene = load_scene(dir + "/scene.json");
  const Image reference = render(*scene, {1, 64, 5, false});
  const int albedo = scene->params.find("floor.albedo");
  REQUIRE(albedo >= 0);
  scene->params.require_grad({"floor.albedo"});
  std::vector<float> direction(scene->params[albedo].size());
  for (auto& d : direction) d = uniform() - 0.5f;
  for (auto& v : scene->params[albedo].value) v = 0.3f + 0.4f * uniform();
  const std::vector<float> start = scene->params[albedo].value;
  const PassOptions pass{1, 4, 9, false};
  const LossResult r = compute_block_loss(LossType::L2, render(*scene, pass), reference, 4);
  scene->params.zero_grad();
  backward(*scene, pass, AdjointMethod::Prb, [&](size_t p, const Vec3f&) {
    return Vec3f{r.adjoint.data[p * 3], r.adjoint.data[p * 3 + 1], r.adjoint.data[p * 3 + 2]};
  });
  double analytic = 0;
  for (size_t i = 0; i < direction.size(); ++i) analytic += double(scene->params[albedo].grad[i]) * direction[i];
  auto loss_at = [&](float t) {
    for (size_t i = 0; i < direction.size(); ++i) scene->params[albedo].value[i] = start[i] + t * direction[i];
    return compute_block_loss(LossType::L2, render(*scene, pass), reference, 4).value;
  };
  const double fd = (loss_at(1e-2f) - loss_at(-1e-2f)) / 2e-2;
  INFO("directional derivative: adjoint " << analytic << ", same-seed central difference " << fd);
  CHECK(std::abs(fd) > 1e-6);
  CHECK(analytic == Approx(fd).epsilon(2e-3));

  // In the job: started at the truth and barely moved, each iteration's loss is the renders' own
  // noise, independent from pixel to pixel; 2×2 block means carry a quarter of its variance.
  const std::string job_dir = test::temp_dir("opt-block-loss-job");
  const std::string text = tiny_job_at_truth(job_dir, 6);
  auto with_blocks = [&](const std::string& out, int k, const std::string& extra = "") {
    std::string t = text;
    t.replace(t.find("\"output\": \"out\""), 15, "\"output\": \"" + out + "\"");
    t.insert(t.rfind('}'), ", \"loss_downsample\": " + std::to_string(k) + extra);
    std::ofstream(job_dir + "/" + out + ".json") << t;
    return job_dir + "/" + out + ".json";
  };
  REQUIRE(run_optimize(with_blocks("blocks", 2), "", 0, true) == 0);
  REQUIRE(run_optimize(with_blocks("pixels", 1), "", 0, true) == 0);
  // Blocks for the first three iterations only (an image-schedule stage's own loss_downsample).
  REQUIRE(run_optimize(with_blocks("staged", 1, R"(, "image_schedule": [{"until": 3, "loss_downsample": 2}])"), "", 0,
                       true) == 0);
  auto losses = [&](const std::string& out) {
    std::ifstream f(job_dir + "/" + out + "/loss.csv");
    std::string line;
    std::getline(f, line);
    std::vector<std::string> rows;
    while (std::getline(f, line)) {
      const size_t a = line.find(',') + 1, b = line.find(',', a);
      rows.push_back(line.substr(a, b - a));  // the loss column, as printed
    }
    REQUIRE(rows.size() == 6);  // one row per iteration
    return rows;
  };
  auto mean_loss = [&](const std::vector<std::string>& rows, size_t from, size_t to) {
    double sum = 0;
    for (size_t i = from; i < to; ++i) sum += std::stod(rows[i]);
    return sum / double(to - from);
  };
  const auto blocks = losses("blocks"), pixels = losses("pixels"), staged = losses("staged");
  const double blocks_loss = mean_loss(blocks, 0, 6), pixels_loss = mean_loss(pixels, 0, 6);
  INFO("mean loss at the truth: 2x2 blocks " << blocks_loss << ", pixels " << pixels_loss);
  CHECK(blocks_loss > 0.15 * pixels_loss);
  CHECK(blocks_loss < 0.4 * pixels_loss);
  // The staged run is the block run until its stage ends (the same renders, the same steps), then
  // a loss of pixels again.
  for (size_t i = 0; i < 3; ++i) CHECK(staged[i] == blocks[i]);
  const double staged_after = mean_loss(staged, 3, 6), pixels_after = mean_loss(pixels, 3, 6);
  INFO("iterations 3-5: staged " << staged_after << ", pixels " << pixels_after);
  CHECK(staged_after > 0.8 * pixels_after);
  CHECK(staged_after < 1.25 * pixels_after);
}

TEST_CASE("cached reference targets are re-rendered when the scene or the reference changes", "[optimizer]") {
  const std::string dir = test::temp_dir("optimizer-target-cache");
  const std::string job = write_tiny_job(dir, 1);
  REQUIRE(run_optimize(job, "", 1, true) == 0);
  const std::string target = dir + "/out/targets/top.exr";
  const std::vector<float> first = read_all(target);
  const auto written = std::filesystem::last_write_time(target);
  // The same job: the cache is used (not rewritten).
  REQUIRE(run_optimize(job, "", 1, true) == 0);
  CHECK(std::filesystem::last_write_time(target) == written);
  // A brighter sky in the scene file: the target follows (it was once reused from the old scene).
  std::string scene;
  {
    std::ifstream in(dir + "/scene.json");
    scene.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  const std::string old_sky = R"("radiance": [1, 1, 1])";
  REQUIRE(scene.find(old_sky) != std::string::npos);
  scene.replace(scene.find(old_sky), old_sky.size(), R"("radiance": [2, 2, 2])");
  std::ofstream(dir + "/scene.json") << scene;
  REQUIRE(run_optimize(job, "", 1, true) == 0);
  const std::vector<float> second = read_all(target);
  REQUIRE(second.size() == first.size());
  double ratio = 0;
  for (size_t i = 0; i < first.size(); ++i) ratio += double(second[i]) / std::max(double(first[i]), 1e-6);
  CHECK(ratio / double(first.size()) == Approx(2.0).epsilon(0.05));
}

namespace {

// A closed triangulated octahedron with vertex 0 duplicated as vertex 6 (a seam: triangles 4..7 use
// the copy), positions [N, 3] row-major.
struct SeamMesh {
  std::vector<float> x{0, 1, 0, 1, 0, 0, 0, 0, 1, -1, 0, 0, 0, 0, -1, 0, -1, 0, 0, 1, 0};
  std::vector<uint32_t> indices{0, 2, 1, 0, 3, 2, 0, 4, 3, 0, 1, 4, 5, 1, 2, 5, 2, 3, 5, 3, 4, 5, 4, 1};
  SeamMesh() {  // the lower half's triangles use the top copy through a seam vertex
    indices = {0, 2, 1, 6, 3, 2, 0, 4, 3, 6, 1, 4, 5, 1, 2, 5, 2, 3, 5, 3, 4, 5, 4, 1};
  }
};

}  // namespace

TEST_CASE("large steps: u = (I + lambda L) x round-trips and the u-gradient is the chain rule",
          "[optimizer][large_steps]") {
  SeamMesh mesh;
  const double lambda = 3.0;
  LargeSteps ls(mesh.x, mesh.indices, lambda, "test");
  CHECK(ls.vertex_count() == 7);
  CHECK(ls.node_count() == 6);  // the seam copy is welded to vertex 0
  // A copy whose zero coordinates are −0 (a mirrored or negated mesh) is at the same position, as
  // for the edges of the boundary terms (engine/core/weld.h); it was a separate node.
  SeamMesh negated;
  negated.x[18] = -0.f, negated.x[20] = -0.f;
  CHECK(LargeSteps(negated.x, negated.indices, lambda, "test").node_count() == 6);
  // u = M x by hand for the apex (vertex 0, neighbours 1..4 through either copy): degree 4.
  const std::vector<float> u = ls.to_u(mesh.x);
  const double apex_y = (1 + 4 * lambda) * 1.0 - lambda * (0 + 0 + 0 + 0);
  CHECK(u[1] == Approx(apex_y));
  CHECK(u[3 * 6 + 1] == Approx(apex_y));  // the copy carries the same u
  // Vertex 1 = (1,0,0): neighbours 0, 2, 4, 5 → u_x = (1 + 4λ)·1 − λ·(0 + 0 + 0 + 0).
  CHECK(u[3] == Approx(1 + 4 * lambda));
  const std::vector<float> back = ls.to_x(u);
  for (size_t i = 0; i < back.size(); ++i) CHECK(back[i] == Approx(mesh.x[i]).margin(1e-6));
  // Chain rule: f(x) = Σ w·x. Central differences of f(to_x(u)) in u vs gradient_u(w); a
  // perturbation of one copy of the seam vertex moves the node by half (to_x averages copies), so
  // the derivative per copy is half the node's: compare the sum over the two copies.
  std::vector<float> w(mesh.x.size());
  for (size_t i = 0; i < w.size(); ++i) w[i] = float(std::sin(1.7 * double(i) + 0.3));
  const std::vector<float> gu = ls.gradient_u(w);
  auto f = [&](const std::vector<float>& uu) {
    const std::vector<float> xx = ls.to_x(uu);
    double s = 0;
    for (size_t i = 0; i < xx.size(); ++i) s += double(w[i]) * double(xx[i]);
    return s;
  };
  const float h = 1e-2f;
  for (size_t i = 3; i < 18; ++i) {  // vertices 1..5 (no seam)
    std::vector<float> up = u, dn = u;
    up[i] += h, dn[i] -= h;
    CHECK(gu[i] == Approx((f(up) - f(dn)) / (2 * h)).epsilon(1e-3).margin(1e-4));
  }
  for (size_t k = 0; k < 3; ++k) {  // the seam node: perturb both copies together
    std::vector<float> up = u, dn = u;
    up[k] += h, up[18 + k] += h, dn[k] -= h, dn[18 + k] -= h;
    CHECK(gu[k] == Approx((f(up) - f(dn)) / (2 * h)).epsilon(1e-3).margin(1e-4));
    CHECK(gu[18 + k] == gu[k]);
  }
}

TEST_CASE("grid large steps: (I + lambda L) by hand, its inverse by conjugate gradients, the chain rule",
          "[optimizer][large_steps]") {
  const GridDims d{5, 4, 3, 2};  // x, y, z, channels: corners, edges, faces and interior voxels
  const double lambda = 2.5;
  std::vector<float> x(d.size());
  for (size_t i = 0; i < x.size(); ++i) x[i] = float(std::sin(0.9 * double(i) + 0.2));
  auto at = [&](const std::vector<float>& v, int ix, int iy, int iz, int c) {
    return v[((size_t(iz) * size_t(d.y) + size_t(iy)) * size_t(d.x) + size_t(ix)) * size_t(d.c) + size_t(c)];
  };
  const std::vector<float> u = grid_apply_m(d, lambda, x);
  // By hand: every voxel, each channel on its own, neighbours inside the grid only.
  for (int iz = 0; iz < d.z; ++iz)
    for (int iy = 0; iy < d.y; ++iy)
      for (int ix = 0; ix < d.x; ++ix)
        for (int c = 0; c < d.c; ++c) {
          double lap = 0;
          const double v = at(x, ix, iy, iz, c);
          if (ix > 0) lap += v - at(x, ix - 1, iy, iz, c);
          if (ix + 1 < d.x) lap += v - at(x, ix + 1, iy, iz, c);
          if (iy > 0) lap += v - at(x, ix, iy - 1, iz, c);
          if (iy + 1 < d.y) lap += v - at(x, ix, iy + 1, iz, c);
          if (iz > 0) lap += v - at(x, ix, iy, iz - 1, c);
          if (iz + 1 < d.z) lap += v - at(x, ix, iy, iz + 1, c);
          CHECK(at(u, ix, iy, iz, c) == Approx(v + lambda * lap).margin(1e-5));
        }
  // A constant grid is a fixed point (no flux through the faces); the solve inverts the apply.
  const std::vector<float> ones(d.size(), 0.7f);
  for (float v : grid_apply_m(d, lambda, ones)) CHECK(v == Approx(0.7f));
  const std::vector<float> back = grid_solve_m(d, lambda, u);
  for (size_t i = 0; i < x.size(); ++i) CHECK(back[i] == Approx(x[i]).margin(2e-5));
  // Chain rule: with x = M⁻¹u and f = Σ w·x, df/du = M⁻¹ w (M is symmetric): central differences.
  std::vector<float> w(x.size());
  for (size_t i = 0; i < w.size(); ++i) w[i] = float(std::cos(1.3 * double(i)));
  const std::vector<float> gu = grid_solve_m(d, lambda, w);
  auto f = [&](const std::vector<float>& uu) {
    const std::vector<float> xx = grid_solve_m(d, lambda, uu);
    double s = 0;
    for (size_t i = 0; i < xx.size(); ++i) s += double(w[i]) * double(xx[i]);
    return s;
  };
  for (size_t i = 0; i < u.size(); i += 7) {
    std::vector<float> up = u, dn = u;
    up[i] += 0.05f, dn[i] -= 0.05f;
    CHECK(gu[i] == Approx((f(up) - f(dn)) / 0.1).epsilon(1e-3).margin(1e-4));
  }
  // A one-voxel spike in the gradient spreads into a bump that sums to the spike (M⁻¹ keeps the
  // mean: 1ᵀM = 1ᵀ) and peaks at the spike.
  std::vector<float> spike(d.size(), 0.f);
  const size_t centre = ((size_t(1) * size_t(d.y) + 2) * size_t(d.x) + 2) * size_t(d.c);  // (2, 2, 1), channel 0
  spike[centre] = 1.f;
  const std::vector<float> bump = grid_solve_m(d, lambda, spike);
  double total = 0, other_channel = 0;
  for (size_t i = 0; i < bump.size(); ++i) (i % 2 == 0 ? total : other_channel) += bump[i];
  CHECK(total == Approx(1.0).margin(1e-4));
  CHECK(other_channel == Approx(0.0).margin(1e-6));
  CHECK(*std::max_element(bump.begin(), bump.end()) == bump[centre]);
  CHECK(bump[centre] < 0.5f);
  // Values that do not match the dimensions are refused.
  CHECK_THROWS(grid_apply_m(d, lambda, std::vector<float>(7)));
}

TEST_CASE("large steps damp a one-vertex spike into a smooth bump and keep seams closed", "[optimizer][large_steps]") {
  SeamMesh mesh;
  LargeSteps ls(mesh.x, mesh.indices, 10.0, "test");
  std::vector<float> g(mesh.x.size(), 0.f);
  g[3 * 2 + 2] = 1.f;  // a gradient on vertex 2's z only
  const std::vector<float> gu = ls.gradient_u(g);
  // M⁻¹ is a positive smoothing kernel: the vertex keeps the largest share, its neighbours (0, 1,
  // 3, 5) less, the opposite vertex 4 least, all positive.
  const float self = gu[8], neighbour = gu[3 * 1 + 2], opposite = gu[3 * 4 + 2];
  CHECK(self > neighbour);
  CHECK(neighbour > opposite);
  CHECK(opposite > 0.f);
  CHECK(self < 1.f);
  // Rows of M sum to 1 (L annihilates constants), so M⁻¹ preserves the total: Σ M⁻¹g = Σ g over
  // nodes (the welded node counts once).
  double total = 0;
  for (size_t v = 0; v < 6; ++v) total += gu[3 * v + 2];
  CHECK(total == Approx(1.0).epsilon(1e-5));
  // A step through u leaves the seam's copies at one position.
  std::vector<float> u = ls.to_u(mesh.x);
  for (size_t i = 0; i < u.size(); ++i) u[i] -= 0.3f * ls.gradient_u(g)[i];
  const std::vector<float> x = ls.to_x(u);
  for (size_t k = 0; k < 3; ++k) CHECK(x[k] == x[18 + k]);
  CHECK_THROWS_AS(LargeSteps(mesh.x, {0, 1, 9}, 1.0, "test"), InputError);
  CHECK_THROWS_AS(LargeSteps(mesh.x, mesh.indices, 0.0, "test"), InputError);
}

TEST_CASE("uniform Adam divides every element by the largest second moment", "[optimizer][large_steps]") {
  AdamSettings s;
  s.learning_rate = 0.1;
  s.uniform = true;
  Adam adam(s);
  std::vector<float> x{0.f, 0.f, 0.f}, g{4.f, -1.f, 0.5f};
  adam.step(x, g);
  // Step 1: m̂ = g, v̂ = g², max √v̂ = 4: every element moves lr·g/4, keeping the gradient's shape.
  CHECK(x[0] == Approx(-0.1).margin(1e-6));
  CHECK(x[1] == Approx(0.025).margin(1e-6));
  CHECK(x[2] == Approx(-0.0125).margin(1e-6));
  // Plain Adam would have moved each by ±lr.
  AdamSettings p = s;
  p.uniform = false;
  Adam plain(p);
  std::vector<float> y{0.f, 0.f, 0.f};
  plain.step(y, g);
  CHECK(y[2] == Approx(-0.1).margin(1e-6));
}

TEST_CASE("surface distance: zero for sliding vertices, the offset for a moved surface", "[optimizer][large_steps]") {
  // A 3×3-vertex grid of the unit square (8 triangles) in z = 0.
  std::vector<float> a;
  for (int y = 0; y < 3; ++y)
    for (int x = 0; x < 3; ++x) a.insert(a.end(), {0.5f * float(x), 0.5f * float(y), 0.f});
  std::vector<uint32_t> idx;
  for (uint32_t y = 0; y < 2; ++y)
    for (uint32_t x = 0; x < 2; ++x) {
      const uint32_t v = 3 * y + x;
      idx.insert(idx.end(), {v, v + 1, v + 4, v, v + 4, v + 3});
    }
  CHECK(surface_distance(a, a, idx) == 0.0);
  // The centre vertex slides within the plane: the vertex error is 0.2/3 per coordinate, the
  // surface does not move.
  std::vector<float> slid = a;
  slid[3 * 4] += 0.2f;
  CHECK(surface_distance(a, slid, idx) == Approx(0.0).margin(1e-12));
  // The whole surface lifted by 0.25: every vertex is 0.25 from the other surface.
  std::vector<float> lifted = a;
  for (size_t v = 0; v < 9; ++v) lifted[3 * v + 2] += 0.25f;
  CHECK(surface_distance(a, lifted, idx) == Approx(0.25));
  // Only the centre vertex lifted by h: a's centre is within h of b's tent, b's apex exactly h
  // from a's plane, the other vertices lie on both surfaces: (h·c + h)/(2·9) with c ∈ (0, 1].
  std::vector<float> tent = a;
  tent[3 * 4 + 2] += 0.3f;
  const double d = surface_distance(a, tent, idx);
  CHECK(d > 0.3 / 18.0);
  CHECK(d <= 0.6 / 18.0 + 1e-9);
  // Mismatched inputs.
  CHECK(surface_distance(a, std::vector<float>(a.begin(), a.end() - 3), idx) == -1.0);
}

TEST_CASE("the bundled optimize configs are valid, and the deformation job runs with large steps",
          "[optimizer][large_steps]") {
  const std::string root = BL_SOURCE_DIR;
  for (const auto& entry : fs::directory_iterator(root + "/scenes")) {
    const fs::path config = entry.path() / "optimize.json";
    if (!fs::exists(config)) continue;
    INFO(config.string());
    CHECK_NOTHROW(check_optimize_config(config.string()));
  }
  // scenes/deform/optimize.json, 4 iterations into a temporary folder.
  const std::string dir = test::temp_dir("deform-job");
  nlohmann::json job = read_json(root + "/scenes/deform/optimize.json");
  job["scene"] = root + "/scenes/deform/scene.json";
  job["views"]["reference"]["set"]["blob.positions"] = root + "/scenes/deform/target.ply";
  job["views"]["reference"]["spp"] = 4;
  job["output"] = dir + "/out";
  job["iterations"] = 4;
  job["resolution"] = {24, 24};
  std::ofstream(dir + "/job.json") << job.dump();
  REQUIRE(run_optimize(dir + "/job.json", "", 0, true) == 0);
  const auto summary = read_json(dir + "/out/summary.json");
  const auto& d = summary["parameters"]["blob.positions"]["surface_distance"];
  CHECK(d["initial"].get<double>() == Approx(0.0829).epsilon(0.01));  // sphere vs blob, measured in python too
  // Positions are compared vertex by vertex, at no resolution (the summary said [1, 1]).
  CHECK_FALSE(summary["parameters"]["blob.positions"].contains("rmse_resolution"));
  CHECK(d["final"].get<double>() < d["initial"].get<double>());
  // final/blob.ply: the optimized vertices, readable as the positions of the same mesh.
  auto scene = load_scene(root + "/scenes/deform/scene.json");
  apply_override(*scene, "blob.positions=" + dir + "/out/final/blob.ply");
  const auto final_params = read_json(dir + "/out/final/params.json");
  const std::vector<float> expect = final_params["blob.positions"].get<std::vector<float>>();
  CHECK(scene->params[scene->params.find("blob.positions")].value == expect);
}
