// Optimizer tests: Adam against hand-computed steps, a tiny end-to-end texture recovery, resume
// equivalence, and config errors.
#include <catch2/catch.hpp>

#include <cmath>
#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/io/image_io.h"
#include "engine/optimize/optimizer.h"
#include "test_scenes.h"

using namespace bl;
namespace fs = std::filesystem;

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
std::string write_tiny_job(const std::string& dir, int iterations, const std::string& extra = "") {
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
  "parameters": {"floor.albedo": {"lr": 0.05, "bounds": [0, 1]}},
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
  for (const char* f :
       {"loss.csv", "loss.png", "param_rmse.png", "compare.png", "summary.json", "final/floor.albedo.exr",
        "final/floor.albedo.png", "snapshots/floor.albedo_00050.png", "checkpoint/state.json"})
    CHECK(fs::exists(dir + "/out/" + f));
}

TEST_CASE("resuming from a checkpoint reaches the same parameters as an uninterrupted run", "[optimizer]") {
  // One worker thread: gradient accumulation order (atomic float adds) is then fixed, so the two
  // runs must agree bit for bit.
  const std::string a = test::temp_dir("resume-a"), b = test::temp_dir("resume-b");
  REQUIRE(run_optimize(write_tiny_job(a, 6), "", 1, true) == 0);
  // Interrupted after 4 iterations (the checkpoint interval is 2), then resumed to 6.
  REQUIRE(run_optimize(write_tiny_job(b, 4), "", 1, true) == 0);
  const std::string full = write_tiny_job(b, 6);
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
}
