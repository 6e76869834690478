// `backlight optimize CONFIG`: multi-view gradient descent on scene parameters. The config format
// is documented in the README ("Optimization config"); errors name the config file and the JSON
// pointer. Every output is written atomically; checkpoints are whole directories swapped in by
// rename, so a killed run resumes from the last complete one and reaches the same parameters.
#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <tbb/global_control.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <string_view>
#include <type_traits>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/core/sampler.h"
#include "engine/dist/dist.h"
#include "engine/integrators/gradient.h"
#include "engine/io/grid_view.h"
#include "engine/io/json_node.h"
#include "engine/io/plot.h"
#include "engine/io/progress.h"
#include "engine/optimize/large_steps.h"
#include "engine/optimize/mesh_distance.h"
#include "engine/optimize/optimizer.h"
#include "engine/optimize/regularizers.h"
#include "engine/optimize/resample.h"
#include "engine/scene/scene_load.h"
#include "engine/scene/volume_io.h"

namespace bl {

namespace fs = std::filesystem;

namespace {

// Atomic, not volatile sig_atomic_t: the handler may run on any thread (a TBB worker) while the
// main thread reads the flag, which sig_atomic_t does not make a race-free exchange (helper-37's
// TSan audit); a lock-free atomic is as safe inside the handler.
std::atomic<int> interrupted{0};
static_assert(std::atomic<int>::is_always_lock_free);
// The first Ctrl-C asks for a checkpoint after the current view; a second one ends the process
// at once (outputs are written atomically, so nothing is left truncated: the last checkpoint
// stays usable).
void on_sigint(int) {
  interrupted.store(1, std::memory_order_relaxed);
  std::signal(SIGINT, SIG_DFL);
  static const char note[] = "\noptimize: stopping after the current view (Ctrl-C again to quit at once)\n";
  [[maybe_unused]] const auto written = write(STDERR_FILENO, note, sizeof note - 1);
}

struct Stage {
  int until = 0;  // iterations [previous until, until) run at this resolution
  int width = 0, height = 0;
  int depth = 0;                   // > 0: a volume grid stage [X, Y, Z] = [width, height, depth]
  double lr = 0;                   // > 0: the learning rate during this stage (decay still applies); 0: the parameter's
  double large_steps_lambda = -1;  // ≥ 0: a grid's large-steps λ during this stage (0: off); < 0: the parameter's
  int average_from = -1;           // ≥ 0: iterate averaging within this stage from here (replaces the parameter's)
};

struct OptimizedParam {
  std::string name;
  int handle = -1;
  Adam adam;
  double lr = 0;  // the configured learning rate (stages may override it)
  std::vector<Stage> stages;
  json init;  // null: keep the scene's value
  std::optional<Param> ground_truth;
  double tv_weight = 0;  // total-variation regularizer (grids and images)
  double l1_weight = 0;  // sparsity: weight × mean |θ| (any parameter)
  // Iterate averaging (Polyak–Ruppert): with average_from = N ≥ 0 the result is the mean of the
  // values after iterations N+1, …, the last (restarted by a resolution change after N: the next
  // stage starts from the finished stage's average, resampled). It removes the jitter Monte Carlo
  // gradients leave in the last iterates; the renders of the iterations themselves use the current
  // iterate. A stage's own average_from replaces N during that stage.
  int average_from = -1;
  std::vector<float> average;
  int average_count = 0;
  // Large steps (large_steps.h) for a mesh's `positions` or a grid: λ > 0 turns it on; Adam then
  // steps on u = (I + λL) x with a uniform second moment unless the config says otherwise. Bounds
  // (grids only) then hold for x: Adam's own are off and x is clamped after each step.
  double large_steps_lambda = 0;
  std::shared_ptr<LargeSteps> large_steps;  // a mesh's
  bool grid_large_steps = false;
  bool has_bounds = false, has_schedule = false;
  float bounds[2] = {-1e30f, 1e30f};  // "bounds" as given (where they apply: see bounds_outside_adam)
  bool bounds_outside_adam = false;
  // λ > 0 for the parameter or one of its stages.
  bool wants_large_steps() const {
    return large_steps_lambda > 0 ||
           std::any_of(stages.begin(), stages.end(), [](const Stage& s) { return s.large_steps_lambda > 0; });
  }
  // "parametrization": "log": Adam (and large steps) work on u = ln max(x, kLogFloor) and the
  // parameter takes x = e^u after each step, so a step changes x by a factor, not an amount: small
  // values (empty space of a density) move little, large ones fast. Bounds then hold for x.
  bool log_space = false;
  float lower = -1e30f, upper = 1e30f;
  // A mesh's `positions`: its triangles (for the surface distance and final/<shape>.ply).
  std::vector<uint32_t> mesh_indices;
  const std::vector<float>& result(const Param& p) const { return average_count > 0 ? average : p.value; }
};

struct Config {
  std::string file;
  json source;  // the config as parsed: what a checkpoint records it was made from
  std::string scene;
  std::vector<std::string> scene_overrides;
  std::vector<OptimizedParam> params;
  std::vector<std::string> views;                   // camera names or indices
  std::vector<Camera> extra_cameras;                // camera poses given in the config
  std::map<std::string, std::string> target_files;  // camera name → image
  std::vector<std::string> reference_overrides;     // "NAME=VALUE" for rendering targets
  int reference_spp = 64;
  int views_per_iteration = 0;  // 0 = all
  LossType loss = LossType::L2;
  int spp = 4, adjoint_spp = 4;
  bool decorrelate = true;
  int iterations = 100;
  uint64_t seed = 0;
  std::string output;
  int checkpoint_every = 10, snapshot_every = 25;
  int width = 0, height = 0;  // render resolution override (0 = the cameras')
  int rmse_width = 0, rmse_height = 0;
  int validation_every = 10;  // completed iterations between validation losses; 0 = none
  int validation_spp = 0;     // samples per pixel of each of its two renders (0 = spp)
  // Coarse-to-fine in image space: iterations before `until` render every view at 1/`downsample`
  // of its resolution against the k×k box average of its target.
  struct ImageStage {
    int until = 0;
    int downsample = 1;
    int views_per_iteration = -1;  // -1: the top-level setting
    int loss_downsample = -1;      // -1: the top-level setting
  };
  std::vector<ImageStage> image_schedule;
  // A low-pass loss: the loss compares k×k block means of the render and the target, so a
  // render's Monte Carlo noise is averaged over k² pixels before it enters δI.
  int loss_downsample = 1;
};

// `key`: where in `n` errors point (the assignment's name, or e.g. "init").
std::string override_string(const std::string& name, const json& v, const Node& n, const fs::path& dir,
                            const std::string& key = "") {
  const std::string& at = key.empty() ? name : key;
  // Numbers as written (std::to_string kept 6 decimals: an init of 1.5e-7 became 0).
  auto number = [](double x) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.17g", x);
    return std::string(buf);
  };
  if (v.is_string()) return name + "=" + (dir / v.get<std::string>()).lexically_normal().string();
  if (v.is_number()) return name + "=" + number(v.get<double>());
  if (v.is_array()) {
    std::string s = name + "=";
    for (size_t i = 0; i < v.size(); ++i) {
      if (!v[i].is_number()) n.fail_at(at, "expected numbers");
      s += (i ? "," : "") + number(v[i].get<double>());
    }
    return s;
  }
  n.fail_at(at, "expected a file name, a number or a list of numbers");
}

// apply_override for an assignment the config at JSON pointer `pointer` makes: its errors name
// the config and the pointer, not a --set nobody gave.
void apply_config_override(Scene& scene, const std::string& assignment, const std::string& file,
                           const std::string& pointer) {
  try {
    apply_override(scene, assignment);
  } catch (const InputError& e) {
    std::string m = e.what();
    for (const char* prefix : {"--set: ", "--set "})
      if (m.rfind(prefix, 0) == 0) m = m.substr(std::strlen(prefix));
    throw file_error(file, pointer + ": " + m);
  }
}

Config parse_config(const std::string& path) {
  const std::string text = read_json_file(path);
  json root = parse_json_text(text, path);
  Config c;
  c.file = path;
  c.source = root;
  const fs::path dir = fs::path(path).parent_path();
  Node n(root, "", c.file);
  c.scene = (dir / n.string("scene")).lexically_normal().string();
  if (n.has("set")) {
    Node s = n.child("set");
    for (auto it = s.at_all().begin(); it != s.at_all().end(); ++it)
      c.scene_overrides.push_back(override_string(it.key(), it.value(), s, dir));
  }
  if (n.string("output").empty()) n.fail_at("output", "an empty folder name");
  // The operating system would make the folder named by the part before a NUL byte.
  if (n.string("output").find('\0') != std::string::npos) n.fail_at("output", "the folder name contains a NUL byte");
  c.output = (dir / n.string("output")).lexically_normal().string();
  c.iterations = int(n.integer("iterations", 100, 1, 10000000));
  c.seed = uint64_t(n.integer("seed", 0, 0, 4294967295));
  c.spp = int(n.integer("spp", 4, 1, long(limits::kSpp)));
  c.adjoint_spp = int(n.integer("adjoint_spp", c.spp, 1, long(limits::kSpp)));
  c.decorrelate = n.boolean("decorrelate", true);
  c.loss_downsample = int(n.integer("loss_downsample", 1, 1, 64));
  c.loss = LossType::L2;
  if (n.has("loss")) {
    try {
      c.loss = parse_loss(n.string("loss"));
    } catch (const InputError& e) {
      n.fail_at("loss", e.what());
    }
  }
  c.checkpoint_every = int(n.integer("checkpoint_every", 10, 1, 10000000));
  c.snapshot_every = int(n.integer("snapshot_every", 25, 1, 10000000));
  c.views_per_iteration = int(n.integer("views_per_iteration", 0, 0, 10000));
  auto read_size = [&](const char* key, int& w, int& h) {
    if (const json* r = n.find(key)) {
      if (!r->is_array() || r->size() != 2 || !(*r)[0].is_number_integer() || !(*r)[1].is_number_integer() ||
          (*r)[0].get<int64_t>() < 1 || (*r)[1].get<int64_t>() < 1)
        n.fail_at(key, "expected [width, height]");
      limits::check_image_size(c.file + ": /" + key, (*r)[0].get<uint64_t>(), (*r)[1].get<uint64_t>());
      w = (*r)[0].get<int>(), h = (*r)[1].get<int>();
    }
  };
  read_size("resolution", c.width, c.height);
  read_size("rmse_resolution", c.rmse_width, c.rmse_height);
  c.validation_spp = c.spp;
  if (n.has("validation")) {
    Node v = n.child("validation");
    c.validation_every = int(v.integer("every", 10, 0, 10000000));
    c.validation_spp = int(v.integer("spp", c.spp, 1, long(limits::kSpp)));
    v.finish();
  }

  if (const json* st = n.find("image_schedule")) {
    if (!st->is_array())
      n.fail_at("image_schedule",
                "expected a list of {\"until\", \"downsample\", \"views_per_iteration\", \"loss_downsample\"}");
    for (size_t i = 0; i < st->size(); ++i) {
      Node s((*st)[i], "/image_schedule/" + std::to_string(i), c.file);
      Config::ImageStage stage;
      stage.until = int(s.integer_required("until", 1, 10000000));
      stage.downsample = int(s.integer("downsample", 1, 1, 64));
      stage.views_per_iteration = int(s.integer("views_per_iteration", -1, 0, 10000));
      stage.loss_downsample = int(s.integer("loss_downsample", -1, 1, 64));
      if (!c.image_schedule.empty() && stage.until <= c.image_schedule.back().until)
        s.fail_at("until", "stages must be increasing");
      s.finish();
      c.image_schedule.push_back(stage);
    }
  }

  Node views = n.child("views");
  if (views.has("ring")) {
    // A ring of cameras around a target (multi-view volume setups): `count` poses at equal angles,
    // `radius` from the target's vertical axis, at `height` above it, all looking at it.
    Node r = views.child("ring");
    const int count = int(r.integer("count", 8, 1, 1024));
    const double radius = r.number_required("radius", 1e-6, 1e9), height = r.number("height", 0.0, -1e9, 1e9);
    const Vec3f target = r.vec3("target", {0, 0, 0});
    const double fov = r.number("fov", 40.0, 1e-3, 179.9), phase = r.number("angle_offset", 0.0, -360.0, 360.0);
    r.finish();
    for (int k = 0; k < count; ++k) {
      const double a = (phase + 360.0 * k / count) * kPi / 180.0;
      Camera cam;
      cam.name = "ring" + std::to_string(k);
      cam.target = target;
      cam.origin = target + Vec3f{float(radius * std::sin(a)), float(height), float(radius * std::cos(a))};
      cam.fov_degrees = float(fov);
      cam.update();
      c.extra_cameras.push_back(cam);
      c.views.push_back(cam.name);
    }
  }
  const json* cams_ptr = views.find("cameras");
  static const json no_cameras = json::array();
  const json& cams = cams_ptr ? *cams_ptr : no_cameras;
  if (!cams.is_array() || (cams.empty() && c.views.empty()))
    views.fail_at("cameras", "expected a non-empty list of camera names or indices (or a \"ring\")");
  for (size_t i = 0; i < cams.size(); ++i) {
    if (cams[i].is_object()) {
      // An extra pose, in the scene format's camera syntax.
      Node cn(cams[i], views.pointer("cameras") + "/" + std::to_string(i), c.file);
      c.extra_cameras.push_back(parse_camera(cn, "view" + std::to_string(i)));
      c.views.push_back(c.extra_cameras.back().name);
    } else if (cams[i].is_string() || cams[i].is_number_integer()) {
      c.views.push_back(cams[i].is_string() ? cams[i].get<std::string>() : cams[i].dump());
    } else {
      views.fail_at("cameras/" + std::to_string(i), "expected a camera name, an index or a camera object");
    }
  }
  if (views.has("targets")) {
    Node t = views.child("targets");
    for (auto it = t.at_all().begin(); it != t.at_all().end(); ++it) {
      if (!it.value().is_string()) t.fail_at(it.key(), "expected an image file name");
      c.target_files[it.key()] = (dir / it.value().get<std::string>()).lexically_normal().string();
    }
  }
  if (views.has("reference")) {
    Node r = views.child("reference");
    if (r.has("set")) {
      Node s = r.child("set");
      for (auto it = s.at_all().begin(); it != s.at_all().end(); ++it)
        c.reference_overrides.push_back(override_string(it.key(), it.value(), s, dir));
    }
    c.reference_spp = int(r.integer("spp", 64, 1, long(limits::kSpp)));
    r.finish();
  }
  if (c.target_files.empty() && c.reference_overrides.empty())
    views.fail("give \"targets\" (camera → image) or a \"reference\" scene variant to render them from");
  views.finish();

  Node params = n.child("parameters");
  if (params.at_all().empty()) params.fail("no parameters to optimize");
  for (auto it = params.at_all().begin(); it != params.at_all().end(); ++it) {
    Node p(it.value(), params.pointer(it.key()), c.file);
    params.mark_used(it.key());
    OptimizedParam op;
    op.name = it.key();
    AdamSettings a;
    a.learning_rate = op.lr = p.number_required("lr", 0, 1e6);
    if (const json* b = p.find("bounds")) {
      if (!b->is_array() || b->size() != 2 || !(*b)[0].is_number() || !(*b)[1].is_number() ||
          (*b)[0].get<double>() > (*b)[1].get<double>())
        p.fail_at("bounds", "expected [lower, upper] with lower ≤ upper");
      a.lower = (*b)[0].get<float>(), a.upper = (*b)[1].get<float>();
      op.bounds[0] = a.lower, op.bounds[1] = a.upper;
    }
    if (p.has("decay")) {
      Node d = p.child("decay");
      a.decay = d.string("type");
      if (a.decay != "exponential" && a.decay != "step") d.fail_at("type", "expected \"exponential\" or \"step\"");
      a.decay_rate = d.number_required("rate", 0, 1);
      if (a.decay == "exponential" && d.has("every"))
        d.fail_at("every", "only for \"step\" decay (exponential decay multiplies the rate in every iteration)");
      a.decay_every = a.decay == "step" ? int(d.integer("every", 50, 1, 10000000)) : 0;
      d.finish();
    }
    if (p.has("moments")) {
      const std::string m = p.string("moments");
      if (m != "float32" && m != "bfloat16") p.fail_at("moments", "expected \"float32\" or \"bfloat16\"");
      a.bf16_moments = m == "bfloat16";
    }
    if (const json* init = p.find("init")) op.init = *init;
    if (const json* st = p.find("schedule")) {
      if (!st->is_array()) p.fail_at("schedule", "expected a list of {\"until\", \"resolution\"}");
      for (size_t i = 0; i < st->size(); ++i) {
        Node s((*st)[i], p.pointer("schedule") + "/" + std::to_string(i), c.file);
        Stage stage;
        stage.until = int(s.integer_required("until", 1, 10000000));
        const json& r = s.at("resolution");
        bool ok = r.is_array() && (r.size() == 2 || r.size() == 3);
        for (size_t k = 0; ok && k < r.size(); ++k)
          ok = r[k].is_number_integer() && r[k].get<int64_t>() >= 1 && r[k].get<uint64_t>() <= limits::kImageSide;
        if (!ok) s.fail_at("resolution", "expected [width, height] (images) or [x, y, z] (grids) of positive integers");
        const std::string where = c.file + ": " + p.pointer("schedule") + "/" + std::to_string(i) + "/resolution";
        if (r.size() == 2) {
          limits::check_image_size(where, r[0].get<uint64_t>(), r[1].get<uint64_t>());
        } else {
          limits::checked_product(where, "voxel count",
                                  {r[0].get<uint64_t>(), r[1].get<uint64_t>(), r[2].get<uint64_t>()},
                                  limits::kGridVoxels);
          stage.depth = r[2].get<int>();
        }
        stage.width = r[0].get<int>(), stage.height = r[1].get<int>();
        if (s.has("lr")) stage.lr = s.number_required("lr", 1e-30, 1e6);
        if (s.has("large_steps_lambda")) stage.large_steps_lambda = s.number_required("large_steps_lambda", 0, 1e9);
        if (s.has("average_from")) stage.average_from = int(s.integer("average_from", 0, 0, 10000000));
        if (!op.stages.empty() && stage.until <= op.stages.back().until)
          s.fail_at("until", "stages must be increasing");
        s.finish();
        op.stages.push_back(stage);
      }
    }
    if (const json* b = p.find("betas")) {
      // Adam's moment decay rates (PyTorch's `betas`): [β1, β2], each in [0, 1).
      if (!b->is_array() || b->size() != 2 || !(*b)[0].is_number() || !(*b)[1].is_number() ||
          !((*b)[0].get<double>() >= 0 && (*b)[0].get<double>() < 1) ||
          !((*b)[1].get<double>() >= 0 && (*b)[1].get<double>() < 1))
        p.fail_at("betas", "expected [beta1, beta2], each in [0, 1)");
      a.beta1 = (*b)[0].get<double>(), a.beta2 = (*b)[1].get<double>();
    }
    if (p.has("warmup")) a.warmup = int(p.integer("warmup", 0, 0, 10000000));
    if (p.has("average_from")) op.average_from = int(p.integer("average_from", 0, 0, 10000000));
    if (p.has("large_steps")) {
      Node l = p.child("large_steps");
      op.large_steps_lambda = l.number_required("lambda", 1e-6, 1e9);
      a.uniform = l.boolean("uniform_adam", true);
      l.finish();
    }
    if (p.has("parametrization")) {
      const std::string t = p.string("parametrization");
      if (t != "linear" && t != "log") p.fail_at("parametrization", "expected \"linear\" or \"log\"");
      op.log_space = t == "log";
      if (op.log_space && a.upper <= 0) p.fail_at("bounds", "a log parametrization needs an upper bound > 0");
    }
    // Meshes refuse bounds and schedules once the parameter is known to be a mesh's (resolve).
    op.has_bounds = p.has("bounds"), op.has_schedule = p.has("schedule");
    if (op.wants_large_steps() || op.log_space) {
      // Bounds hold for x, clamped after each step (Adam's own would clamp u = (I + λL)x or ln x).
      op.lower = a.lower, op.upper = a.upper;
      a.lower = -1e30f, a.upper = 1e30f;
      op.bounds_outside_adam = true;
    }
    if (const json* reg = p.find("regularizer")) {
      // One {type, weight} or a list of them, each type at most once.
      const bool list = reg->is_array();
      const size_t count = list ? reg->size() : 1;
      std::set<std::string> seen;
      for (size_t i = 0; i < count; ++i) {
        const std::string where = p.pointer("regularizer") + (list ? "/" + std::to_string(i) : "");
        Node r(list ? (*reg)[i] : *reg, where, c.file);
        const std::string type = r.string("type");
        double* weight = type == "tv" ? &op.tv_weight : type == "l1" ? &op.l1_weight : nullptr;
        if (!weight) r.fail_at("type", "unknown regularizer '" + type + "' (expected \"tv\" or \"l1\")");
        if (!seen.insert(type).second) r.fail_at("type", "regularizer '" + type + "' given twice");
        *weight = r.number_required("weight", 0, 1e12);
        r.finish();
      }
    }
    op.adam = Adam(a);
    p.finish();
    c.params.push_back(std::move(op));
  }
  n.finish();
  return c;
}

uint64_t iteration_seed(uint64_t seed, int iteration, int view, int pass) {
  return mix64(mix64(seed ^ 0x6f7074696d697a65ull) + uint64_t(iteration) * 0x9e3779b97f4a7c15ull +
               uint64_t(view) * 0xd1b54a32d192ed03ull + uint64_t(pass)) &
         0xffffffffull;
}

bool is_grid(const Param& p) { return p.shape.size() == 4; }

// 64-bit FNV-1a, as 16 hex digits: a checkpoint's record of a file or an image (std::hash, which
// the target cache's key uses, may change with the standard library; a record outlives builds).
uint64_t fnv1a(const void* data, size_t bytes, uint64_t h = 0xcbf29ce484222325ull) {
  const auto* b = static_cast<const unsigned char*>(data);
  for (size_t i = 0; i < bytes; ++i) h = (h ^ b[i]) * 0x100000001b3ull;
  return h;
}
std::string hex64(uint64_t h) {
  char text[17];
  std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(h));
  return text;
}
bool is_hex64(const json& j) {
  return j.is_string() && j.get<std::string>().size() == 16 &&
         j.get<std::string>().find_first_not_of("0123456789abcdef") == std::string::npos;
}

// A path in a one-line message, not shortened (printable_name).
std::string whole_name(const std::string& path) { return printable_name(path, std::string::npos); }

// The paths of the keys where two configs differ ("parameters.wall.albedo.lr"; a list is one
// value: "schedule", not each stage), in key order, a key of only one of them included.
void config_differences(const json& a, const json& b, const std::string& path, std::vector<std::string>& out) {
  if (!a.is_object() || !b.is_object()) {
    if (a != b) out.push_back(path);
    return;
  }
  std::set<std::string> keys;
  for (auto it = a.begin(); it != a.end(); ++it) keys.insert(it.key());
  for (auto it = b.begin(); it != b.end(); ++it) keys.insert(it.key());
  for (const auto& k : keys) {
    const std::string at = path.empty() ? printable_name(k) : path + "." + printable_name(k);
    if (!a.contains(k) || !b.contains(k))
      out.push_back(at);
    else
      config_differences(a[k], b[k], at, out);
  }
}

// "a, b, c and 4 more": at most `cap` names (the one-line note stays readable).
std::string name_list(const std::vector<std::string>& names, size_t cap) {
  std::string text;
  for (size_t i = 0; i < names.size() && i < cap; ++i) text += (i ? ", " : "") + names[i];
  if (names.size() > cap) text += " and " + std::to_string(names.size() - cap) + " more";
  return text;
}

// Whether a parameter already has a stage's resolution.
bool has_resolution(const Param& p, const Stage& s) {
  if (is_grid(p)) return s.depth == 0 || (p.shape[2] == s.width && p.shape[1] == s.height && p.shape[0] == s.depth);
  return !p.is_image() || s.depth > 0 || (p.width() == s.width && p.height() == s.height);
}

// Sets an image or grid parameter to a stage's resolution, resampling its values (images take
// [w, h] stages, grids [x, y, z]; other combinations leave the parameter alone).
void resize_param(Param& p, const Stage& s) {
  if (has_resolution(p, s)) return;
  if (is_grid(p)) {
    const int c = p.shape[3];
    p.value = resample_grid(p.value, p.shape[2], p.shape[1], p.shape[0], c, s.width, s.height, s.depth);
    p.shape = {s.depth, s.height, s.width, c};
  } else {
    p.value = resample(p.value, p.width(), p.height(), p.channels(), s.width, s.height);
    p.shape = {s.height, s.width, p.channels()};
  }
  p.grad.assign(p.value.size(), 0.f);
}

// Root-mean-square difference of `values` (laid out as parameter a) and parameter b after
// resampling both to (w, h) (images) or to b's size (grids).
double rmse(const Param& a, const std::vector<float>& values, const Param& b, int w, int h) {
  std::vector<float> x = values, y = b.value;
  if (is_grid(a) && is_grid(b)) {
    x = resample_grid(values, a.shape[2], a.shape[1], a.shape[0], a.shape[3], b.shape[2], b.shape[1], b.shape[0]);
  } else if (a.is_image()) {
    x = resample(values, a.width(), a.height(), a.channels(), w ? w : b.width(), h ? h : b.height());
    y = resample(b.value, b.width(), b.height(), b.channels(), w ? w : b.width(), h ? h : b.height());
  }
  double s = 0;
  for (size_t i = 0; i < x.size(); ++i) s += (double(x[i]) - y[i]) * (double(x[i]) - y[i]);
  return std::sqrt(s / double(std::max<size_t>(1, x.size())));
}

// A grid parameter as a .vol grid in the unit box (the medium's box is the scene's business).
// A grid parameter's dimensions in the unit box (values stay in the parameter: grids are large).
VolumeGrid grid_of(const Param& p) {
  VolumeGrid g;
  g.z = p.shape[0], g.y = p.shape[1], g.x = p.shape[2], g.channels = p.shape[3];
  return g;
}
GridView view_of(const Param& p) { return {&p.value, p.shape[2], p.shape[1], p.shape[0], p.shape[3]}; }

Image param_image(const Param& p) {
  Image img(p.width(), p.height(), p.channels() == 1 ? 1 : 3);
  img.data = p.value;
  return img;
}

template <class T>
void write_floats(const std::string& path, const std::vector<T>& v) {
  write_bytes_atomic(path, v.data(), v.size() * sizeof(T));
}

// Floats (or bfloat16 bit patterns, T = uint16_t) of a checkpoint file.
template <class T = float>
std::vector<T> read_floats(const std::string& path, size_t count) {
  // The size is checked against the file before allocating: a checkpoint's recorded shape is input.
  std::error_code ec;
  const auto bytes = fs::file_size(path, ec);
  if (ec || count > bytes / sizeof(T) || bytes != count * sizeof(T))
    throw file_error(path, "checkpoint file is truncated or has the wrong size");
  std::ifstream f(path, std::ios::binary);
  std::vector<T> v(count);
  if (!f.read(reinterpret_cast<char*>(v.data()), std::streamsize(count * sizeof(T))) || f.peek() != EOF)
    throw file_error(path, "checkpoint file is truncated or has the wrong size");
  return v;
}

// Runs `python3 SCRIPT args...` (Debian's /usr/bin/python3 when present) with its output
// discarded; returns its exit status, or -1 when it could not be started or was killed.
int run_python(const std::vector<std::string>& args) {
  const std::string python = fs::exists("/usr/bin/python3") ? "/usr/bin/python3" : "python3";
  std::vector<std::string> all{python};
  all.insert(all.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& a : all) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
  pid_t pid = 0;
  const int spawned = ::posix_spawnp(&pid, python.c_str(), &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (spawned != 0) return -1;
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0)
    if (errno != EINTR) return -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

std::string base64(const std::string& bytes) {
  static const char* const table = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 2 < bytes.size(); i += 3) {
    const uint32_t v = uint32_t(uint8_t(bytes[i])) << 16 | uint32_t(uint8_t(bytes[i + 1])) << 8 | uint8_t(bytes[i + 2]);
    out += {table[v >> 18], table[v >> 12 & 63], table[v >> 6 & 63], table[v & 63]};
  }
  if (i + 1 == bytes.size()) {
    const uint32_t v = uint32_t(uint8_t(bytes[i])) << 16;
    out += {table[v >> 18], table[v >> 12 & 63], '=', '='};
  } else if (i + 2 == bytes.size()) {
    const uint32_t v = uint32_t(uint8_t(bytes[i])) << 16 | uint32_t(uint8_t(bytes[i + 1])) << 8;
    out += {table[v >> 18], table[v >> 12 & 63], table[v >> 6 & 63], '='};
  }
  return out;
}

std::string html_escape(const std::string& text) {
  std::string out;
  for (char ch : text) {
    switch (ch) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out += ch;
    }
  }
  return out;
}

// A PNG file as an inline <img> (the page needs no other file), or nothing when it is absent.
std::string inline_png(const std::string& path, const std::string& caption) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return "";
  const std::string bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  if (bytes.size() < 8 || bytes.compare(0, 8, "\x89PNG\r\n\x1a\n") != 0) return "";
  return "<figure><img alt=\"" + html_escape(caption) + "\" src=\"data:image/png;base64," + base64(bytes) +
         "\"><figcaption>" + html_escape(caption) + "</figcaption></figure>\n";
}

// tools/plot_optimize of this source tree (the plots of an optimize run, drawn with matplotlib).
std::string plot_script() { return std::string(BL_SOURCE_DIR) + "/tools/plot_optimize"; }

struct LogRow {
  int iteration;
  double loss, seconds;
  double rmse = -1;  // first optimized parameter vs ground truth, when known
};

// A validation loss after `iteration` completed iterations.
struct ValidationRow {
  int iteration;
  double loss, seconds;
};

class Job {
 public:
  Job(Config c, bool quiet, bool resume_any_scene)
      : c_(std::move(c)), quiet_(quiet), resume_any_scene_(resume_any_scene) {}

  int run(bool resume) {
    scene_ = load_scene(c_.scene);
    // What a checkpoint records of the scene: everything loaded from its file (the textures,
    // meshes and grids it refers to too), before the config's "set" (that is the config's part).
    scene_content_ = scene_->content_hash();
    scene_bytes_ = read_input_file(c_.scene);  // once: the target keys and the checkpoint's record hash it
    apply_scene_overrides(*scene_);
    require_same_scene(*scene_);
    resolve_views();
    for (auto& p : c_.params) {
      p.handle = scene_->params.find(p.name);
      if (p.handle < 0)
        throw file_error(c_.file, "/parameters/" + p.name + ": unknown parameter (see `backlight params`)");
      p.adam.reset(scene_->params[p.handle].size());
      const Mesh* mesh = nullptr;
      for (size_t k = 0; k < scene_->meshes.size() && k < scene_->mesh_poses.size(); ++k)
        if (scene_->mesh_poses[k].positions == p.handle) mesh = &scene_->meshes[k];
      if (mesh) p.mesh_indices = mesh->indices;
      const std::string where = c_.file + ": /parameters/" + p.name;
      // A stage's resolution must fit the parameter: [w, h] for an image, [x, y, z] for a grid
      // (anything else was ignored without a word).
      const Param& param = scene_->params[p.handle];
      for (size_t k = 0; k < p.stages.size(); ++k) {
        const Stage& st = p.stages[k];
        if (st.width == 0) continue;
        const std::string at = where + "/schedule/" + std::to_string(k) + "/resolution: ";
        if (is_grid(param) && st.depth == 0) throw InputError(at + "a grid parameter takes [x, y, z], got [w, h]");
        if (param.is_image() && st.depth > 0) throw InputError(at + "an image parameter takes [w, h], got [x, y, z]");
        if (!is_grid(param) && !param.is_image())
          throw InputError(at + "only image and grid parameters can change resolution (this one has shape " +
                           scene_->params.shape_string(p.handle) + ")");
      }
      if (p.tv_weight > 0 && !is_grid(param) && !param.is_image())  // it did nothing, silently
        throw InputError(where + "/regularizer: \"tv\" is for image and grid parameters (this one has shape " +
                         scene_->params.shape_string(p.handle) + ")");
      if (p.has_bounds) {  // they must meet the parameter's valid range (steps are clamped into both)
        const float lo = p.bounds[0], hi = p.bounds[1];
        if (hi < param.lower || lo > param.upper) {
          std::ostringstream m;
          m << where << "/bounds: [" << lo << ", " << hi << "] lies outside the valid range [" << param.lower << ", "
            << param.upper << "] of '" << p.name << "'";
          throw InputError(m.str());
        }
      }
      if (p.log_space && mesh)
        throw InputError(where + "/parametrization: \"log\" is for positive values, not a mesh's positions");
      if (p.wants_large_steps() && !mesh && is_grid(scene_->params[p.handle])) {
        p.grid_large_steps = true;
      } else if (p.wants_large_steps()) {
        if (!mesh)
          throw InputError(where +
                           "/large_steps: only for a mesh's positions (<shape>.positions) or a grid "
                           "(e.g. <medium>.density)");
        if (p.has_bounds) throw InputError(where + "/bounds: bounds cannot be combined with large_steps on a mesh");
        if (p.has_schedule)
          throw InputError(where + "/schedule: a schedule cannot be combined with large_steps on a mesh");
        p.large_steps = std::make_shared<LargeSteps>(scene_->params[p.handle].value, mesh->indices,
                                                     p.large_steps_lambda, c_.file + ": /parameters/" + p.name);
      }
    }
    std::vector<std::string> names;
    for (const auto& p : c_.params) names.push_back(p.name);
    scene_->params.require_grad(names);
    // Under MPI (engine/dist/dist.h) every rank runs this job on its share of each pass's
    // pixels; only rank 0 writes and prints. All ranks read the scene, the targets and, on
    // --resume, the checkpoint: the output folder must be on a filesystem every rank sees.
    // What the config can get wrong is found before the output folder is made: a start that
    // fails leaves no folder (and no rendered targets) behind.
    check_downsampling();
    if (!resume) dist::agreed_step([&] { apply_initial_values(); });  // a bad "init" fails alike on every rank
    read_target_inputs();
    made_from_ = made_from();
    // The checkpoint's record is read before anything is written into the folder: a checkpoint of
    // another scene is refused before that scene's targets replace the cached ones.
    if (resume) dist::agreed_step([&] { check_made_from(); });
    if (root_) {
      ensure_output_folder(c_.output);
      // A run killed while writing leaves its temporaries; this run owns the folder, so clear them,
      // and the checkpoint a killed run was writing (it stayed until the next checkpoint).
      remove_stale_temporaries(c_.output);
      remove_checkpoint_dir(out("checkpoint.tmp"));
      if (!resume) remove_previous_outputs();
    }
    prepare_targets();
    prepare_image_stages();
    matplotlib_ = root_ && probe_matplotlib();
    if (!matplotlib_ && !quiet_ && !builtin_plots_chosen())
      std::fprintf(stderr, "optimize: python3-matplotlib not found: simple plots; with it, run %s %s\n",
                   plot_script().c_str(), c_.output.c_str());
    int start = 0;
    if (resume) {
      // Every rank reads it; a bad checkpoint is reported once, not by each rank.
      dist::agreed_step([&] { start = load_checkpoint(); });
      // The logs as the checkpoint has them: a killed run left rows after it, and a fresh start
      // killed in its clean-up none (a finished run's checkpoint then runs no iteration to write them).
      write_log();
      if (!validation_.empty()) write_validation();
      // After the checkpoint was read: a bad one is one line, the error, not a note and an error.
      if (root_ && !resume_note_.empty()) std::fprintf(stderr, "%s\n", resume_note_.c_str());
    }
    snapshot_initial();
    return optimize(start);
  }

 private:
  Config c_;
  bool quiet_;
  bool resume_any_scene_;
  uint64_t scene_content_ = 0;  // scene_'s content_hash() as loaded from its file
  std::string scene_bytes_;     // the scene file, read once (target_key, made_from)
  json made_from_;              // what this run's checkpoints record they were made from (made_from())
  // --resume: the checkpoint folder, its state.json as read by check_made_from (load_checkpoint
  // reads the rest), and the note on what it was made from (empty when nothing differs).
  std::string resume_dir_;
  json resume_state_;
  std::string resume_note_;
  const bool root_ = dist::is_root();
  std::unique_ptr<Scene> scene_;
  std::vector<int> cameras_;
  std::vector<Image> targets_;
  // Downsampled views of the image schedule, by factor: a camera index and a target per view.
  struct ScaledViews {
    std::vector<int> cameras;
    std::vector<Image> targets;
  };
  std::map<int, ScaledViews> scaled_views_;
  std::vector<LogRow> log_;
  std::vector<ValidationRow> validation_;
  bool matplotlib_ = false;
  double elapsed_before_ = 0;  // seconds spent before a resume
  double initial_loss_ = -1;
  double initial_rmse_ = -1;  // before the first update (log_ rows hold the RMSE after their update)
  double step_seconds_ = 0;   // regularizers, optimizer steps and sampling tables, since this start

  std::string out(const std::string& name) const { return (fs::path(c_.output) / name).string(); }

  // FNV-1a over the bits of the optimized parameters: every MPI rank must end with the same.
  uint64_t parameter_hash() const {
    uint64_t h = 0xcbf29ce484222325ull;
    for (const auto& p : c_.params)
      for (float v : scene_->params[p.handle].value) {
        uint32_t bits;
        std::memcpy(&bits, &v, sizeof bits);
        h = (h ^ bits) * 0x100000001b3ull;
      }
    return h;
  }

  // Grids are written in their medium's box; pictures share one scale, the ground truth's maximum.
  VolumeGrid grid_of(const Param& p) const {
    VolumeGrid g = bl::grid_of(p);
    for (const auto& m : scene_->media)
      if (m.grid && (scene_->params[m.density].name == p.name || scene_->params[m.albedo].name == p.name))
        g.bbox_min = m.bbox_min, g.bbox_max = m.bbox_max;
    return g;
  }
  static float grid_vmax(const OptimizedParam& op, const Param& p) {
    const std::vector<float>& v = op.ground_truth ? op.ground_truth->value : p.value;
    return v.empty() ? 1.f : *std::max_element(v.begin(), v.end());
  }

  // Extra poses from the config join the scene's cameras (and the reference scene's, for targets).
  void add_extra_cameras(Scene& scene) const {
    for (const auto& cam : c_.extra_cameras) {
      for (const auto& existing : scene.cameras)
        if (existing.name == cam.name)
          throw file_error(c_.file, "/views/cameras: camera name '" + cam.name + "' already exists in the scene");
      scene.cameras.push_back(cam);
    }
  }

  void resolve_views() {
    add_extra_cameras(*scene_);
    for (const auto& v : c_.views) {
      int index = -1;
      for (size_t i = 0; i < scene_->cameras.size(); ++i)
        if (scene_->cameras[i].name == v) index = int(i);
      if (index < 0 && !v.empty() && v.size() <= 9 && v.find_first_not_of("0123456789") == std::string::npos)
        index = std::stoi(v);  // at most 9 digits: fits an int
      if (index < 0 || size_t(index) >= scene_->cameras.size())
        throw file_error(c_.file, "/views/cameras: unknown camera '" + printable_name(v) + "'");
      // A view's target is a file named after its camera (targets/NAME.exr): "../x" would be
      // written outside the output folder. Refused before the folder is made.
      const std::string& name = scene_->cameras[size_t(index)].name;
      if (const std::string problem = object_name_problem(name); !problem.empty())
        throw file_error(c_.file, "/views/cameras: camera name '" + printable_name(name) + "' " + problem);
      cameras_.push_back(index);
    }
    if (c_.width)
      for (auto& cam : scene_->cameras) cam.width = c_.width, cam.height = c_.height, cam.update();
    for (auto& cam : scene_->cameras) validate_camera(cam, c_.file);
  }

  // What a reference target of view v is rendered from, as text (hashed: the scene file's bytes).
  std::string target_key(size_t v, const Camera& cam) const {
    std::string key = "scene " + std::to_string(std::hash<std::string>{}(scene_bytes_)) + "\n";
    for (const auto& o : c_.scene_overrides) key += "set " + o + "\n";
    for (const auto& o : c_.reference_overrides) key += "reference " + o + "\n";
    // What the files behind those names hold (a texture or grid file rewritten in place kept its
    // name: the cache was reused): every parameter value and mesh of the reference variant.
    key += "content " + std::to_string(reference_content_) + "\n";
    key += "spp " + std::to_string(c_.reference_spp) + " seed " + std::to_string(0xabcdefull + v) + " camera " +
           cam.name + " " + std::to_string(cam.width) + "x" + std::to_string(cam.height) + "\n";
    return key;
  }

  // The targets' inputs, read before anything is written: the target files (size-checked) and
  // the reference variant (its "set" files applied), which renders the other targets and holds
  // the ground truth of the parameter RMSE.
  std::map<std::string, Image> target_images_;  // by camera name
  std::unique_ptr<Scene> reference_;
  uint64_t reference_content_ = 0;  // reference_->content_hash()
  void read_target_inputs() {
    for (const auto& [name, file] : c_.target_files) {  // (a target of no view was ignored)
      bool viewed = false;
      for (int c : cameras_) viewed = viewed || scene_->cameras[size_t(c)].name == name;
      if (!viewed) throw file_error(c_.file, "/views/targets/" + name + ": camera '" + name + "' is not a view");
    }
    for (size_t v = 0; v < cameras_.size(); ++v) {
      const Camera& cam = scene_->cameras[size_t(cameras_[v])];
      if (auto it = c_.target_files.find(cam.name); it != c_.target_files.end()) {
        Image t = read_image(it->second, true);
        if (t.width != cam.width || t.height != cam.height)
          throw file_error(it->second, "target is " + std::to_string(t.width) + "x" + std::to_string(t.height) +
                                           " but view '" + cam.name + "' renders " + std::to_string(cam.width) + "x" +
                                           std::to_string(cam.height));
        target_images_[cam.name] = std::move(t);
      } else if (c_.reference_overrides.empty()) {
        throw file_error(c_.file, "/views/targets: no target for camera '" + cam.name + "'");
      }
    }
    if (!c_.reference_overrides.empty()) {
      reference_ = load_reference();
      add_extra_cameras(*reference_);
      if (c_.width)
        for (auto& rc : reference_->cameras) rc.width = c_.width, rc.height = c_.height, rc.update();
      reference_content_ = reference_->content_hash();
    }
    // What a checkpoint records of each view's target: a target file's pixels, or what a reference
    // target is rendered from (the target cache's key).
    for (size_t v = 0; v < cameras_.size(); ++v) {
      const Camera& cam = scene_->cameras[size_t(cameras_[v])];
      uint64_t h;
      if (auto it = target_images_.find(cam.name); it != target_images_.end()) {
        const Image& t = it->second;
        const int size[3] = {t.width, t.height, t.channels};
        h = fnv1a(t.data.data(), t.data.size() * sizeof(float), fnv1a(size, sizeof size));
      } else {
        const std::string key = target_key(v, cam);
        h = fnv1a(key.data(), key.size());
      }
      target_prints_[cam.name] = hex64(h);
    }
  }
  std::map<std::string, std::string> target_prints_;  // by camera name

  // What this run's checkpoints were made from: the config as parsed (without "output": where the
  // run writes, which --resume names anyway), the scene file (its absolute name, its bytes and the
  // content loaded from it) and every view's target. check_made_from compares a checkpoint's with it.
  json made_from() const {
    json config = c_.source;
    if (config.is_object()) config.erase("output");
    std::error_code ec;
    fs::path file = fs::weakly_canonical(fs::absolute(c_.scene), ec);
    if (ec) file = fs::absolute(c_.scene).lexically_normal();
    return {{"config", config},
            {"scene",
             {{"file", file.string()},
              {"bytes", hex64(fnv1a(scene_bytes_.data(), scene_bytes_.size()))},
              {"content", hex64(scene_content_)}}},
            {"targets", target_prints_}};
  }

  // The checkpoint --resume continues from: checkpoint/, or checkpoint.old/ when a swap was cut short.
  std::string checkpoint_to_resume() const {
    std::string dir = out("checkpoint");
    if (!fs::exists(dir + "/state.json") && fs::exists(out("checkpoint.old") + "/state.json"))
      dir = out("checkpoint.old");
    if (fs::exists(dir + "/state.json")) return dir;
    // targets/ is made by every run before its first checkpoint, and a start without --resume
    // removes the previous run's checkpoint with its other outputs: a run started here and was
    // stopped before it wrote one.
    if (fs::is_directory(out("targets")))
      throw file_error(c_.output,
                       "--resume: no checkpoint in this directory (the last run started in it stopped before its "
                       "first checkpoint, and a start without --resume removes the previous run's): start it again "
                       "without --resume");
    throw file_error(c_.output, "--resume: no checkpoint in this directory");
  }

  // Reads the checkpoint's state.json and compares its record of what it was made from with this
  // run's: a changed config or scene file is resumed (resuming with other settings is how a run
  // is continued on purpose) after one note naming what differs; a checkpoint of another scene,
  // another file with other content, is refused without --resume-any-scene: its parameters of the
  // same names and shapes are that scene's values. A checkpoint without the record (written
  // before checkpoints had one) resumes with a note.
  void check_made_from() {
    resume_dir_ = checkpoint_to_resume();
    const std::string state_path = resume_dir_ + "/state.json";
    resume_state_ = parse_json_text(read_input_file(state_path), state_path);
    const json& state = resume_state_;
    if (!state.is_object()) return;  // load_checkpoint says what is wrong with it
    const std::string resuming = "optimize: resuming " + whole_name(resume_dir_);
    if (!state.contains("made_from")) {
      resume_note_ = resuming +
                     ", which records nothing of what it was made from (an older backlight's checkpoint): its "
                     "config, scene and targets are unknown";
      return;
    }
    auto bad = [&](const std::string& at, const std::string& what) { throw file_error(state_path, at + ": " + what); };
    const json& m = state["made_from"];
    if (!m.is_object())
      bad("/made_from", "expected an object {config, scene, targets} (what the checkpoint was made from)");
    if (!m.contains("config") || !m["config"].is_object()) bad("/made_from/config", "expected the config's object");
    if (!m.contains("scene") || !m["scene"].is_object())
      bad("/made_from/scene", "expected an object {file, bytes, content}");
    const json& scene = m["scene"];
    if (!scene.contains("file") || !scene["file"].is_string() || scene["file"].get<std::string>().empty())
      bad("/made_from/scene/file", "expected the scene file's name");
    for (const char* key : {"bytes", "content"})
      if (!scene.contains(key) || !is_hex64(scene[key]))
        bad(std::string("/made_from/scene/") + key, "expected 16 hexadecimal digits");
    if (!m.contains("targets") || !m["targets"].is_object())
      bad("/made_from/targets", "expected an object {view: 16 hexadecimal digits}");
    for (auto it = m["targets"].begin(); it != m["targets"].end(); ++it)
      if (!is_hex64(it.value()))
        bad("/made_from/targets/" + printable_name(it.key()), "expected 16 hexadecimal digits");

    std::vector<std::string> changes, keys, targets;
    config_differences(m["config"], made_from_["config"], "", keys);
    if (!keys.empty()) changes.push_back("the config differs in " + name_list(keys, 6));
    const json& now = made_from_["scene"];
    const std::string was_file = scene["file"].get<std::string>(), now_file = now["file"].get<std::string>();
    const bool same_bytes = scene["bytes"] == now["bytes"], same_content = scene["content"] == now["content"];
    if (!same_bytes || !same_content) {
      if (was_file != now_file) {
        if (!resume_any_scene_)
          throw file_error(state_path, "the checkpoint was made from the scene " + whole_name(was_file) +
                                           ", this config's is " + whole_name(now_file) +
                                           ", another file with other content: parameters of the same names and "
                                           "shapes hold that scene's values (--resume-any-scene resumes it anyway)");
        changes.push_back("another scene (was " + whole_name(was_file) + ")");
      } else {
        changes.push_back(same_bytes ? "files the scene refers to changed" : "scene file changed");
      }
    }
    for (auto it = made_from_["targets"].begin(); it != made_from_["targets"].end(); ++it)
      if (m["targets"].contains(it.key()) && m["targets"][it.key()] != it.value())
        targets.push_back(printable_name(it.key()));
    if (!targets.empty()) changes.push_back("targets of " + name_list(targets, 4) + " changed");
    if (changes.empty()) return;
    resume_note_ = resuming + " made from other inputs: ";
    for (size_t i = 0; i < changes.size(); ++i) resume_note_ += (i ? "; " : "") + changes[i];
  }

  // A start without --resume removes what an earlier run wrote into the folder, before its own first
  // write: that run's final/ stayed while the new one went on, snapshots of iterations the new run
  // never reached stayed for ever, and its initial.exr (another config's start) went into the new
  // compare.png. Only names this job writes go (a user's other files in the folder, final/ or
  // snapshots/ stay), and not the cached targets, which have their own key. summary.json goes first
  // (it says the folder's run finished: killed early, a fresh run left a summary of 40 iterations
  // beside its own checkpoint of 5, helper-45) and the checkpoint last: a run killed in between
  // leaves the previous run's checkpoint for --resume, whose outputs are written again as it goes.
  void remove_previous_outputs() {
    auto remove = [](const fs::path& path) {
      std::error_code ec;
      fs::remove(path, ec);
      if (ec) throw file_error(path.string(), "cannot remove the previous run's output (" + ec.message() + ")");
    };
    remove(out("summary.json"));
    for (const char* name : {"loss.csv", "validation.csv", "loss.png", "param_rmse.png", "report.html", "compare.png",
                             "slices.png", "initial.exr"})
      remove(out(name));
    // Parameter names are <object>.<property>: final/NAME.ext, snapshots/NAME_00025.ext.
    const std::regex final_names(R"((view\.exr|params\.json|.+\.[^.]+\.(vol|png|exr)|.+\.ply))"),
        snapshot_names(R"((view_[0-9]{5,}\.png|.+\.[^.]+_[0-9]{5,}\.(vol|png|exr)))");
    for (const auto& [folder, names] : {std::pair{"final", &final_names}, std::pair{"snapshots", &snapshot_names}}) {
      std::error_code ec;
      if (!fs::is_directory(fs::symlink_status(out(folder), ec))) continue;
      std::vector<fs::path> doomed;
      for (fs::directory_iterator it(out(folder), ec), end; !ec && it != end; it.increment(ec))
        if (it->is_regular_file(ec) && std::regex_match(it->path().filename().string(), *names))
          doomed.push_back(it->path());
      if (ec) throw file_error(out(folder), "cannot list the previous run's outputs (" + ec.message() + ")");
      for (const auto& path : doomed) remove(path);
      fs::remove(out(folder), ec);  // when nothing else is left in it
    }
    crash_point("outputs-removed");
    remove_checkpoint_dir(out("checkpoint.old"));
    remove_checkpoint_dir(out("checkpoint"));
    crash_point("outputs-cleared");
  }

  void prepare_targets() {
    if (root_) fs::create_directories(out("targets"));
    for (size_t v = 0; v < cameras_.size(); ++v) {
      const Camera& cam = scene_->cameras[size_t(cameras_[v])];
      if (auto it = target_images_.find(cam.name); it != target_images_.end()) {
        targets_.push_back(std::move(it->second));
        continue;
      }
      // Rendered from the reference variant and cached with a key of what it was rendered from
      // (the scene file's bytes, the overrides, spp, camera and film): a cache from another scene
      // or reference, or of the wrong size, is re-rendered. Rank 0 decides (all ranks must take
      // the same branch: the render is collective).
      const std::string cached = out("targets/" + cam.name + ".exr"), key_file = cached + ".key";
      const std::string key = target_key(v, cam);
      bool use_cache = false;
      if (root_ && fs::exists(cached) && fs::exists(key_file)) {
        std::ifstream in(key_file, std::ios::binary);
        const std::string stored((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
        if (stored == key) {
          Image t = read_image(cached, false);
          use_cache = t.width == cam.width && t.height == cam.height;
        }
      }
      if (dist::root_value(use_cache)) {
        targets_.push_back(read_image(cached, false));
        continue;
      }
      Image t = render(*reference_, {cameras_[v], c_.reference_spp, 0xabcdefull + v, !quiet_});
      if (root_) {
        // The old key goes first: a run killed between the two renames left a new image beside
        // the old key, and the next run of the old config took it as its target (helper-45).
        std::error_code ec;
        fs::remove(key_file, ec);
        if (ec) throw file_error(key_file, "cannot remove the stale cache key (" + ec.message() + ")");
        write_image(cached, t);
        crash_point("target-written");
        write_text_atomic(key_file, key);
      }
      targets_.push_back(std::move(t));
    }
    target_images_.clear();
    // Ground truth for the parameter RMSE: the reference variant's values.
    if (reference_)
      for (auto& p : c_.params) p.ground_truth = reference_->params[reference_->params.find(p.name)];
    reference_.reset();
  }

  // The image schedule's views: for each factor k, a copy of every view's camera at 1/k of its
  // resolution and its target averaged over k×k blocks. A pixel is the box-filtered mean of the
  // radiance over its area, so the averaged target is exactly what the smaller render estimates.
  void prepare_image_stages() {
    for (size_t i = 0; i < c_.image_schedule.size(); ++i) {
      const int k = c_.image_schedule[i].downsample;
      if (k == 1 || scaled_views_.count(k)) continue;
      ScaledViews& views = scaled_views_[k];
      for (size_t v = 0; v < cameras_.size(); ++v) {
        Camera cam = scene_->cameras[size_t(cameras_[v])];
        cam.name += "/" + std::to_string(k);
        cam.width /= k, cam.height /= k;  // k divides them (check_downsampling)
        cam.update();
        views.cameras.push_back(int(scene_->cameras.size()));
        scene_->cameras.push_back(cam);
        views.targets.push_back(box_downsample(targets_[v], k));
      }
    }
  }

  // Every image-schedule factor divides every view's film, and each block loss's k the renders it
  // applies to: the top-level k those after the last stage (and of stages without their own), a
  // stage's own k that stage's.
  void check_downsampling() const {
    auto check = [&](int k, int f, const std::string& where) {
      for (int c : cameras_) {
        const Camera& cam = scene_->cameras[size_t(c)];
        const bool film = cam.width % f == 0 && cam.height % f == 0;
        if (!film || (cam.width / f) % k != 0 || (cam.height / f) % k != 0)
          throw file_error(c_.file, where + ": " + std::to_string(film ? k : f) + " does not divide the " +
                                        std::to_string(film ? cam.width / f : cam.width) + "x" +
                                        std::to_string(film ? cam.height / f : cam.height) + " of view '" + cam.name +
                                        "'" +
                                        (f == 1 || !film ? "" : " at image-schedule downsample " + std::to_string(f)));
      }
    };
    for (size_t i = 0; i < c_.image_schedule.size(); ++i)
      check(1, c_.image_schedule[i].downsample, "/image_schedule/" + std::to_string(i) + "/downsample");
    check(c_.loss_downsample, 1, "/loss_downsample");
    for (size_t i = 0; i < c_.image_schedule.size(); ++i) {
      const auto& s = c_.image_schedule[i];
      if (s.loss_downsample > 0)
        check(s.loss_downsample, s.downsample, "/image_schedule/" + std::to_string(i) + "/loss_downsample");
      else
        check(c_.loss_downsample, s.downsample, "/loss_downsample");
    }
  }

  // The image-schedule stage of iteration `it` (null after the last).
  const Config::ImageStage* image_stage_at(int it) const {
    for (const auto& s : c_.image_schedule)
      if (it < s.until) return &s;
    return nullptr;
  }

  // The downsampling factor of iteration `it` (1: full resolution).
  int downsample_at(int it) const {
    const Config::ImageStage* s = image_stage_at(it);
    return s ? s->downsample : 1;
  }

  // The block loss's k at iteration `it` (1: the loss of pixels).
  int loss_downsample_at(int it) const {
    const Config::ImageStage* s = image_stage_at(it);
    return s && s->loss_downsample > 0 ? s->loss_downsample : c_.loss_downsample;
  }

  // The views rendered by iteration `it` (0: all).
  int views_at(int it) const {
    const Config::ImageStage* s = image_stage_at(it);
    return s && s->views_per_iteration >= 0 ? s->views_per_iteration : c_.views_per_iteration;
  }

  // The config's "set", "views/reference/set" and a parameter's "init" applied to a scene.
  void apply_scene_overrides(Scene& scene) const {
    for (const auto& o : c_.scene_overrides)
      apply_config_override(scene, o, c_.file, "/set/" + o.substr(0, o.find('=')));
  }
  std::unique_ptr<Scene> load_reference() const {
    auto reference = load_scene(c_.scene);
    apply_scene_overrides(*reference);
    for (const auto& o : c_.reference_overrides)
      apply_config_override(*reference, o, c_.file, "/views/reference/set/" + o.substr(0, o.find('=')));
    return reference;
  }
  void apply_init(Scene& scene, const OptimizedParam& p) const {
    Node holder = Node::at_pointer("/parameters/" + p.name, c_.file);
    apply_config_override(scene, override_string(p.name, p.init, holder, fs::path(c_.file).parent_path(), "init"),
                          c_.file, "/parameters/" + p.name + "/init");
  }

  void apply_initial_values() {
    for (auto& p : c_.params) {
      Param& param = scene_->params[p.handle];
      if (!p.init.is_null()) apply_init(*scene_, p);
      // A start outside the bounds (an init's, or the scene's own value) would be rendered and
      // differentiated once, then clamped.
      const float lo = p.bounds[0], hi = p.bounds[1];
      for (size_t i = 0; p.has_bounds && i < param.value.size(); ++i)
        if (param.value[i] < lo || param.value[i] > hi) {
          std::ostringstream m;
          m << c_.file << ": /parameters/" << p.name;
          if (!p.init.is_null())
            m << "/init: element " << i << " = " << param.value[i] << " is outside the bounds [" << lo << ", " << hi
              << "]";
          else
            m << "/bounds: the scene's value, element " << i << " = " << param.value[i] << ", is outside [" << lo
              << ", " << hi << "] (give an \"init\" inside them)";
          throw InputError(m.str());
        }
      if (!p.stages.empty()) resize_param(param, p.stages[0]);
      p.adam.reset(param.size());
    }
    scene_->prepare_sampling();
  }

  void snapshot_initial() {
    if (dist::root_value(fs::exists(out("initial.exr")))) return;
    const Image initial = render(*scene_, {cameras_[0], c_.reference_spp, 0xabcdefull, false});
    if (root_) write_image(out("initial.exr"), initial);
  }

  // Stage of a parameter at an iteration (the last stage extends to the end).
  static const Stage* stage_at(const OptimizedParam& p, int iteration) {
    for (const auto& s : p.stages)
      if (iteration < s.until) return &s;
    return p.stages.empty() ? nullptr : &p.stages.back();
  }

  // A grid's large-steps λ at an iteration: its stage's, else the parameter's.
  static double grid_lambda(const OptimizedParam& p, int iteration) {
    const Stage* s = stage_at(p, iteration);
    return s && s->large_steps_lambda >= 0 ? s->large_steps_lambda : p.large_steps_lambda;
  }

  int optimize(int start) {
    std::signal(SIGINT, on_sigint);
    Progress progress("optimize", uint64_t(c_.iterations), "it", !quiet_);
    progress.set_done_before(uint64_t(start));
    auto t0 = std::chrono::steady_clock::now();
    auto seconds = [&] {
      return elapsed_before_ + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    };
    const int view_count = int(cameras_.size());
    validate(start, seconds);  // the starting point (already recorded when resuming)
    for (int it = start; it < c_.iterations; ++it) {
      for (auto& p : c_.params) {
        const Stage* s = stage_at(p, it);
        Param& param = scene_->params[p.handle];
        if (s && !has_resolution(param, *s)) {
          // The finished stage's result is its iterate average, when it kept one.
          if (p.average_count > 0) param.value = p.average;
          resize_param(param, *s);
          p.adam.reset(param.size());
          p.average.clear(), p.average_count = 0;
          scene_->prepare_sampling();  // majorants of the new grid
        }
        p.adam.set_learning_rate(s && s->lr > 0 ? s->lr : p.lr);
      }
      scene_->params.zero_grad();
      // A subset of views per iteration: a rotation through a seeded permutation.
      std::vector<int> order(static_cast<size_t>(view_count));
      for (int v = 0; v < view_count; ++v) order[size_t(v)] = v;
      for (int v = view_count - 1; v > 0; --v)
        std::swap(order[size_t(v)], order[mix64(c_.seed + uint64_t(it) * 131 + uint64_t(v)) % uint64_t(v + 1)]);
      const int views = views_at(it);
      const int per_iteration = views > 0 ? std::min(views, view_count) : view_count;
      double loss = 0;
      Image first_view;
      bool stop = false;
      for (int k = 0; k < per_iteration; ++k) {
        // Ctrl-C: all ranks stop at the same view when each gets SIGINT. (Under mpirun a Ctrl-C
        // becomes SIGTERM then SIGKILL for the ranks: they end without this checkpoint, and
        // --resume starts from the last periodic one.)
        if ((stop = dist::any(interrupted.load(std::memory_order_relaxed) != 0))) break;
        const int v = order[size_t(k)];
        const int factor = downsample_at(it);
        const int camera = factor == 1 ? cameras_[size_t(v)] : scaled_views_.at(factor).cameras[size_t(v)];
        const Image& target = factor == 1 ? targets_[size_t(v)] : scaled_views_.at(factor).targets[size_t(v)];
        GradientRequest rq;
        rq.loss = c_.loss;
        rq.target = &target;
        rq.pass = {camera, c_.spp, iteration_seed(c_.seed, it, v, 0), false};
        rq.adjoint_seed = c_.decorrelate ? iteration_seed(c_.seed, it, v, 1) : rq.pass.seed;
        rq.accumulate = true;
        const int loss_k = loss_downsample_at(it);
        if (loss_k > 1 || c_.adjoint_spp != c_.spp) {
          // The loss render and the adjoint pass are separate passes: different sample counts, or
          // the loss of block means, which needs every pixel of a block before any δ is known.
          Image img = render(*scene_, rq.pass);
          LossResult lr =
              loss_k > 1 ? compute_block_loss(c_.loss, img, target, loss_k) : compute_loss(c_.loss, img, target);
          PassOptions adj{camera, c_.adjoint_spp, rq.adjoint_seed, false};
          backward(*scene_, adj, AdjointMethod::Prb, [&](size_t p, const Vec3f&) {
            return Vec3f{lr.adjoint.data[p * 3], lr.adjoint.data[p * 3 + 1], lr.adjoint.data[p * 3 + 2]};
          });
          loss += lr.value;
          if (k == 0) first_view = std::move(img);
        } else {
          GradientResult r = compute_gradient(*scene_, rq);
          loss += r.loss;
          if (k == 0) first_view = std::move(r.image);
        }
      }
      if (stop) {
        progress.finish();
        write_checkpoint(it, seconds());
        write_report(it, seconds(), false, true);
        std::fprintf(stderr, "optimize: interrupted; checkpoint of %d completed iteration(s) in %s\n", it,
                     c_.output.c_str());
        return 0;
      }
      if (initial_rmse_ < 0 && log_.empty()) initial_rmse_ = current_rmse();
      dist::reduce_gradients(scene_->params);  // the ranks' shares of every view, summed once
      // The sum can overflow where every rank's share did not (and the separate loss and adjoint
      // passes are checked nowhere else): Adam would turn inf into NaN parameters and checkpoint them.
      check_gradients_finite(scene_->params);
      if (!std::isfinite(loss))
        throw InputError("the loss of iteration " + std::to_string(it) +
                         " is not finite: float overflow (a radiance too large)");
      const auto step_start = std::chrono::steady_clock::now();
      loss /= per_iteration;
      for (auto& p : c_.params) {
        Param& param = scene_->params[p.handle];
        for (auto& g : param.grad) g /= float(per_iteration);
        loss += add_total_variation(param, p.tv_weight);
        loss += add_l1(param, p.l1_weight);
        if (p.log_space) to_log_space(param.value, param.grad);
        if (p.large_steps) {
          std::vector<float> u = p.large_steps->to_u(param.value);
          p.adam.step(u, p.large_steps->gradient_u(param.grad));
          param.value = p.large_steps->to_x(u);
        } else if (const double lambda = grid_lambda(p, it); p.grid_large_steps && lambda > 0) {
          const GridDims d{param.shape[2], param.shape[1], param.shape[0], param.shape[3]};
          std::vector<float> u = grid_apply_m(d, lambda, param.value);
          p.adam.step(u, grid_solve_m(d, lambda, param.grad));
          param.value = grid_solve_m(d, lambda, u, param.value);
        } else {  // plain Adam, also in a grid's stages without large steps (λ = 0)
          p.adam.step(param.value, param.grad, false);
        }
        if (p.log_space)
          for (float& x : param.value) x = std::exp(x);
        if (p.bounds_outside_adam)
          for (float& x : param.value) x = std::clamp(x, p.lower, p.upper);
        // And always into the parameter's valid range (an albedo in [0, 1], a roughness in its
        // own): a step must not produce values the scene loader would refuse. Bounds inside it
        // make this a no-op.
        for (float& x : param.value) x = std::clamp(x, param.lower, param.upper);
        const Stage* stage = stage_at(p, it);
        const int average_from = stage && stage->average_from >= 0 ? stage->average_from : p.average_from;
        if (average_from >= 0 && it + 1 > average_from) {
          if (p.average_count == 0) {
            p.average = param.value;
          } else {
            for (size_t i = 0; i < param.value.size(); ++i)
              p.average[i] += (param.value[i] - p.average[i]) / float(p.average_count + 1);
          }
          ++p.average_count;
        }
      }
      scene_->prepare_sampling();
      // Work every rank repeats in full (not divided among MPI ranks): bench/mpi's cost model.
      step_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - step_start).count();
      if (initial_loss_ < 0 && log_.empty()) initial_loss_ = loss;
      log_.push_back({it, loss, seconds(), current_rmse()});
      write_log();
      validate(it + 1, seconds);
      char note[96];
      const std::string val =
          validation_.empty() ? "" : " validation " + std::to_string(validation_.back().loss).substr(0, 10);
      if (log_.back().rmse >= 0)
        std::snprintf(note, sizeof note, "loss %.4g rmse %.4f%s", loss, log_.back().rmse, val.c_str());
      else
        std::snprintf(note, sizeof note, "loss %.4g%s", loss, val.c_str());
      progress.set_note(note);
      progress.advance(1);
      if ((it + 1) % c_.snapshot_every == 0 || it + 1 == c_.iterations) {
        snapshot(it + 1, first_view);
        plot();
        write_report(it + 1, seconds(), false);
      }
      if ((it + 1) % c_.checkpoint_every == 0 || it + 1 == c_.iterations) write_checkpoint(it + 1, seconds());
    }
    progress.finish();
    finish(seconds());
    return 0;
  }

  // The validation loss: every view rendered twice with fixed seeds of its own (the same at every
  // validation) and compared with its target. For l2 and rel_l2 it is the mean of
  // (I_a − T)(I_b − T) [/ (T² + 0.01)]: the two renders are independent, so this estimates the loss
  // of the *expected* render against the target without the renders' own Monte Carlo variance,
  // which dominates a few-spp loss (it may come out slightly negative when the loss is near zero).
  // l1 has no such form: the mean of both renders' losses.
  double validation_loss() const {
    double total = 0;
    for (size_t v = 0; v < cameras_.size(); ++v) {
      auto seed = [&](uint64_t k) { return mix64(mix64(c_.seed ^ 0x76616c6964617465ull) + uint64_t(v) * 2 + k); };
      const Image a = render(*scene_, {cameras_[v], c_.validation_spp, seed(0), false});
      const Image b = render(*scene_, {cameras_[v], c_.validation_spp, seed(1), false});
      const Image& t = targets_[v];
      double sum = 0;
      for (size_t i = 0; i < t.data.size(); ++i) {
        const double da = double(a.data[i]) - t.data[i], db = double(b.data[i]) - t.data[i];
        switch (c_.loss) {
          case LossType::L2:
            sum += da * db;
            break;
          case LossType::RelativeL2:
            sum += da * db / (double(t.data[i]) * t.data[i] + 0.01);
            break;
          case LossType::L1:
            sum += 0.5 * (std::abs(da) + std::abs(db));
            break;
        }
      }
      total += sum / double(t.data.size());
    }
    return total / double(cameras_.size());
  }

  // Records the validation loss after `done` completed iterations when it is due.
  template <class Seconds>
  void validate(int done, const Seconds& seconds) {
    if (c_.validation_every <= 0) return;
    if (done % c_.validation_every != 0 && done != c_.iterations) return;
    if (!validation_.empty() && validation_.back().iteration >= done) return;
    validation_.push_back({done, validation_loss(), seconds()});
    write_validation();
  }

  void write_validation() const {
    if (!root_) return;
    std::string csv = "iteration,validation_loss,time_s\n";
    char line[96];
    for (const auto& r : validation_) {
      std::snprintf(line, sizeof line, "%d,%.9g,%.3f\n", r.iteration, r.loss, r.seconds);
      csv += line;
    }
    write_text_atomic(out("validation.csv"), csv);
  }

  // report.html: one self-contained page (images inlined) with the run's state, its curves, the
  // comparison of target, start and result, and the latest parameter snapshots. While the run
  // goes on it reloads itself every 15 s; it is rewritten at every snapshot and at the end.
  // A run stopped by a signal (`interrupted`) gets a page that no longer reloads and shows the
  // last snapshot's images.
  void write_report(int done, double seconds, bool finished, bool interrupted = false) const {
    if (!root_) return;
    auto fmt = [](double v) {
      char b[32];
      std::snprintf(b, sizeof b, "%.4g", v);
      return std::string(b);
    };
    std::string h = "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n";
    if (!finished && !interrupted) h += "<meta http-equiv=\"refresh\" content=\"15\">\n";
    h += "<title>backlight optimize: " + html_escape(fs::path(c_.file).filename().string()) + "</title>\n";
    h += "<style>body{font-family:sans-serif;margin:2em;max-width:1100px}table{border-collapse:collapse}"
         "td,th{border:1px solid #bbb;padding:4px 10px;text-align:left}figure{display:inline-block;margin:8px;"
         "vertical-align:top}img{max-width:520px;image-rendering:pixelated;border:1px solid #ddd}"
         "figcaption{font-size:90%;color:#444}.curves img{image-rendering:auto}</style></head><body>\n";
    h += "<h1>backlight optimize</h1>\n<p>" + html_escape(c_.file) + " &rarr; " + html_escape(c_.output) + "</p>\n";
    h += "<p><b>" +
         std::string(finished      ? "Finished"
                     : interrupted ? "Interrupted"
                                   : "Running") +
         "</b>: " + std::to_string(done) + " of " + std::to_string(c_.iterations) + " iterations, " + fmt(seconds) +
         " s" +
         (finished      ? ""
          : interrupted ? " (checkpoint saved: continue with <code>optimize --resume</code>)"
                        : " (this page reloads every 15 s)") +
         ".</p>\n";
    h += "<table>\n<tr><th>quantity</th><th>start</th><th>now</th></tr>\n";
    if (!log_.empty())
      h += "<tr><td>loss (" + std::string(loss_name(c_.loss)) + ", " + std::to_string(c_.spp) +
           " spp, each iteration)</td><td>" + fmt(log_.front().loss) + "</td><td>" + fmt(log_.back().loss) +
           "</td></tr>\n";
    if (!validation_.empty())
      h += "<tr><td>validation loss (" + std::to_string(c_.validation_spp) + " spp, fixed seeds)</td><td>" +
           fmt(validation_.front().loss) + "</td><td>" + fmt(validation_.back().loss) + "</td></tr>\n";
    if (!log_.empty() && log_.front().rmse >= 0)
      h += "<tr><td>RMSE of " + html_escape(c_.params.front().name) + " against the truth</td><td>" +
           fmt(initial_rmse_ >= 0 ? initial_rmse_ : log_.front().rmse) + "</td><td>" + fmt(log_.back().rmse) +
           "</td></tr>\n";
    h += "<tr><td>views</td><td colspan=\"2\">" + std::to_string(cameras_.size()) + " (" +
         std::to_string(c_.views_per_iteration > 0 ? c_.views_per_iteration : int(cameras_.size())) + " per iteration" +
         (std::any_of(c_.image_schedule.begin(), c_.image_schedule.end(),
                      [](const Config::ImageStage& s) { return s.views_per_iteration >= 0; })
              ? " after the image schedule"
              : "") +
         "), " + std::to_string(c_.spp) + " + " + std::to_string(c_.adjoint_spp) + " spp</td></tr>\n";
    // The plots are shown smaller than drawn: pixelated (nearest-neighbour) scaling would drop
    // their one-pixel strokes (minus signs, grid lines), so only the renders keep it.
    h += "</table>\n<h2>Curves</h2>\n<div class=\"curves\">\n";
    h += inline_png(out("loss.png"), "loss of each iteration and validation loss");
    h += inline_png(out("param_rmse.png"), "parameter RMSE against the ground truth");
    h += "</div>\n<h2>Images</h2>\n";
    h += inline_png(out("compare.png"), "target | initial | final (first view)");
    const int shown = interrupted ? done - done % c_.snapshot_every : done;  // the last snapshot's
    char tag[32];
    std::snprintf(tag, sizeof tag, "%05d", shown);
    if (!finished)
      h += inline_png(out("snapshots/view_" + std::string(tag) + ".png"),
                      "first view after iteration " + std::to_string(shown));
    h += "<h2>Parameters</h2>\n";
    for (const auto& p : c_.params) {
      const std::string file =
          finished ? out("final/" + p.name + ".png") : out("snapshots/" + p.name + "_" + tag + ".png");
      h += inline_png(file, p.name + (finished ? " (final)" : " (iteration " + std::to_string(shown) + ")"));
    }
    h += "</body></html>\n";
    write_text_atomic(out("report.html"), h);
  }

  // RMSE of the first optimized parameter against its ground truth (at rmse_resolution), or −1.
  // RMSE of `values` (laid out as `param`) against p's ground truth, at the config's RMSE size.
  double truth_rmse(const OptimizedParam& p, const Param& param, const std::vector<float>& values) const {
    const Param& gt = *p.ground_truth;
    return rmse(param, values, gt, c_.rmse_width ? c_.rmse_width : gt.width(),
                c_.rmse_height ? c_.rmse_height : gt.height());
  }

  // The RMSE of the run's result so far (the iterate average when averaging).
  double current_rmse() const {
    const OptimizedParam& p = c_.params.front();
    if (!p.ground_truth) return -1;
    const Param& param = scene_->params[p.handle];
    return truth_rmse(p, param, p.result(param));
  }

  void write_log() {
    if (!root_) return;
    const bool has_rmse = !log_.empty() && log_.front().rmse >= 0;
    std::string csv = has_rmse ? "iteration,loss,time_s,param_rmse\n" : "iteration,loss,time_s\n";
    PlotSeries loss, error;
    char line[160];
    for (const auto& r : log_) {
      if (has_rmse)
        std::snprintf(line, sizeof line, "%d,%.9g,%.3f,%.6g\n", r.iteration, r.loss, r.seconds, r.rmse);
      else
        std::snprintf(line, sizeof line, "%d,%.9g,%.3f\n", r.iteration, r.loss, r.seconds);
      csv += line;
      loss.x.push_back(r.iteration);
      loss.y.push_back(r.loss);
      error.x.push_back(r.iteration);
      error.y.push_back(r.rmse);
    }
    write_text_atomic(out("loss.csv"), csv);
    if (matplotlib_) return;  // plot() draws them at snapshots and at the end
    write_line_plot(out("loss.png"), loss, true, "loss");
    if (has_rmse) write_line_plot(out("param_rmse.png"), error, true, "parameter RMSE");
  }

  // Whether tools/plot_optimize can run here (python3 with matplotlib); decided once per run.
  // BACKLIGHT_PLOTS=builtin skips it (the built-in plotter; the test suite's optimizer runs use it:
  // python's start-up and matplotlib cost more than a tiny job's iterations).
  static bool builtin_plots_chosen() {
    const char* choice = std::getenv("BACKLIGHT_PLOTS");
    return choice && std::string(choice) == "builtin";
  }
  bool probe_matplotlib() const {
    return !builtin_plots_chosen() && fs::exists(plot_script()) && run_python({"-c", "import matplotlib"}) == 0;
  }

  // loss.png and param_rmse.png drawn by matplotlib from the CSV files. Without it the built-in
  // plotter draws them at every iteration, and the command is printed once.
  void plot() {
    if (!root_) return;
    if (!matplotlib_) return;
    // --parent: the plot dies with this process (a killed run leaves no plot writing on).
    if (run_python({plot_script(), "--parent", std::to_string(getpid()), c_.output}) == 0) return;
    matplotlib_ = false;
    std::fprintf(stderr, "optimize: plotting with matplotlib failed; drawing simple plots instead (run %s %s)\n",
                 plot_script().c_str(), c_.output.c_str());
    write_log();
  }

  void snapshot(int iteration, const Image& view) {
    if (!root_) return;
    const std::string dir = out("snapshots");
    fs::create_directories(dir);
    char tag[32];
    std::snprintf(tag, sizeof tag, "%05d", iteration);
    for (const auto& p : c_.params) {
      const Param& param = scene_->params[p.handle];
      if (is_grid(param)) {
        write_vol(dir + "/" + p.name + "_" + tag + ".vol", grid_of(param), param.value);
        write_grid_picture(dir + "/" + p.name + "_" + tag + ".png", grid_sheet(view_of(param), grid_vmax(p, param)));
      }
      if (!param.is_image()) continue;
      write_image(dir + "/" + p.name + "_" + tag + ".exr", param_image(param));
      write_image(dir + "/" + p.name + "_" + tag + ".png", param_image(param), param.srgb);
    }
    if (view.width) write_image(dir + "/view_" + std::string(tag) + ".png", view);
  }

  void write_checkpoint(int next_iteration, double seconds) {
    if (!root_) return;
    const std::string tmp = out("checkpoint.tmp"), final_dir = out("checkpoint"), old = out("checkpoint.old");
    remove_checkpoint_dir(tmp);
    fs::create_directories(tmp);
    json state;
    state["next_iteration"] = next_iteration;
    state["seconds"] = seconds;
    state["initial_loss"] = initial_loss_;
    state["initial_rmse"] = initial_rmse_;
    json log = json::array();
    for (const auto& r : log_) log.push_back({r.iteration, r.loss, r.seconds, r.rmse});
    state["log"] = log;
    json validation = json::array();
    for (const auto& r : validation_) validation.push_back({r.iteration, r.loss, r.seconds});
    state["validation"] = validation;
    state["made_from"] = made_from_;
    for (const auto& p : c_.params) {
      const Param& param = scene_->params[p.handle];
      const bool half = p.adam.settings().bf16_moments;
      state["parameters"][p.name] = {{"shape", param.shape},
                                     {"adam_t", p.adam.steps()},
                                     {"adam_decay_t", p.adam.decay_steps()},
                                     {"moments", half ? "bfloat16" : "float32"},
                                     {"average_count", p.average_count}};
      write_floats(tmp + "/" + p.name + ".value", param.value);
      if (p.average_count > 0) write_floats(tmp + "/" + p.name + ".average", p.average);
      if (half) {
        write_floats(tmp + "/" + p.name + ".adam_m", p.adam.m16);
        write_floats(tmp + "/" + p.name + ".adam_v", p.adam.v16);
      } else {
        write_floats(tmp + "/" + p.name + ".adam_m", p.adam.m);
        write_floats(tmp + "/" + p.name + ".adam_v", p.adam.v);
      }
    }
    // state.json is written last: a checkpoint directory is complete exactly when it has one.
    write_text_atomic(tmp + "/state.json", state.dump(1));
    // On the disk before the swap: after a power cut the renames below may have happened while
    // the files' data had not, leaving an empty state.json in checkpoint/ and no checkpoint.old/.
    sync_folder(tmp);
    crash_point("checkpoint-written");
    // Swap directories without a gap: at every moment checkpoint/ or checkpoint.old/ is complete.
    // checkpoint.old/ is deleted only while checkpoint/ is complete (after a resume from
    // checkpoint.old/, checkpoint/ may be missing, and then checkpoint.old/ must survive until
    // the new checkpoint/ is in place).
    if (fs::exists(final_dir + "/state.json")) {
      remove_checkpoint_dir(old);
      crash_point("old-removed");
      fs::rename(final_dir, old);
      crash_point("final-moved");
    } else {
      remove_checkpoint_dir(final_dir);  // an incomplete leftover, if any
    }
    fs::rename(tmp, final_dir);
    sync_path(c_.output);  // the renames themselves
    crash_point("tmp-renamed");
    remove_checkpoint_dir(old);
  }

  // Removes a checkpoint directory, state.json first, so a half-removed one is never taken for a
  // complete one.
  static void remove_checkpoint_dir(const std::string& dir) {
    std::error_code ec;
    fs::remove(dir + "/state.json", ec);
    fs::remove_all(dir);
  }

  // Fault injection for the crash-safety test: BACKLIGHT_CRASH_AT=<name> kills the process (as
  // kill -9 would, with no cleanup) when it reaches the named point of the checkpoint swap (or,
  // "target-written", between a cached target and its key).
  static void crash_point(const char* name) {
    static const char* at = std::getenv("BACKLIGHT_CRASH_AT");
    if (at && std::strcmp(at, name) == 0) std::_Exit(137);
  }

  // The checkpoint check_made_from found and read.
  int load_checkpoint() {
    const std::string dir = resume_dir_;
    const std::string state_path = dir + "/state.json";
    const json state = std::move(resume_state_);
    // A checkpoint is input like any other: every number is checked before the run continues
    // from it (a huge next_iteration ran for ever, a NaN moment made every later value NaN).
    auto bad = [&](const std::string& what) { throw file_error(state_path, what); };
    auto integer = [&](const json& j, const std::string& name, int64_t lo, int64_t hi) {
      const bool in_range = j.is_number_unsigned()  ? j.get<uint64_t>() <= uint64_t(hi) && lo <= 0
                            : j.is_number_integer() ? j.get<int64_t>() >= lo && j.get<int64_t>() <= hi
                                                    : false;
      if (!j.is_number_integer()) bad(name + " is not an integer");
      if (!in_range) bad(name + " is outside " + std::to_string(lo) + ".." + std::to_string(hi));
      return int(j.get<int64_t>());
    };
    auto number = [&](const json& j, const std::string& name, double lo) {
      if (!j.is_number()) bad(name + " is not a number");
      const double v = j.get<double>();
      if (!std::isfinite(v)) bad(name + " is not a finite number");
      if (v < lo) bad(name + " is below " + std::to_string(lo));
      return v;
    };
    // Adam's moments: finite, the second one not negative (bfloat16 patterns are a float's high bits).
    auto check_moments = [&](const std::string& name, const auto& m, const auto& v) {
      auto as_float = [](auto x) {
        if constexpr (std::is_same_v<std::decay_t<decltype(x)>, uint16_t>)
          return std::bit_cast<float>(uint32_t(x) << 16);
        else
          return float(x);
      };
      for (size_t i = 0; i < m.size(); ++i)
        if (!std::isfinite(as_float(m[i])))
          throw file_error(dir + "/" + name + ".adam_m", "element " + std::to_string(i) + " is NaN or infinite");
      for (size_t i = 0; i < v.size(); ++i)
        if (!(as_float(v[i]) >= 0.f) || !std::isfinite(as_float(v[i])))
          throw file_error(dir + "/" + name + ".adam_v",
                           "element " + std::to_string(i) + " is not a finite number >= 0");
    };
    try {
      const int next_iteration = integer(state.at("next_iteration"), "next_iteration", 0, c_.iterations);
      for (auto& p : c_.params) {
        const json& s = state.at("parameters").at(p.name);
        Param& param = scene_->params[p.handle];
        // The checkpoint's shape: the parameter's own, except the resolution of an image or a
        // grid (a schedule resamples them). A negative dimension wrapped the size (an internal
        // error), and a reshaped one (same count, other layout) resumed on scrambled values.
        const std::vector<int64_t> shape = s.at("shape").get<std::vector<int64_t>>();
        const bool resampled = param.is_image() || is_grid(param);
        bool fits = shape.size() == param.shape.size() && !shape.empty();
        for (size_t k = 0; fits && k < shape.size(); ++k)
          fits = shape[k] >= 1 && uint64_t(shape[k]) <= limits::kImageSide &&
                 (resampled ? k + 1 < shape.size() || shape[k] == param.shape[k] : shape[k] == param.shape[k]);
        auto shape_text = [](const auto& v) {
          std::string t = "[";
          for (size_t k = 0; k < v.size(); ++k) t += (k ? ", " : "") + std::to_string(v[k]);
          return t + "]";
        };
        if (!fits)
          throw file_error(dir + "/state.json", "the checkpoint's shape " + shape_text(shape) + " of '" + p.name +
                                                    "' does not fit the parameter (" + shape_text(param.shape) + ")");
        uint64_t count = 1;
        for (int64_t d : shape)
          if (!limits::checked_mul(count, uint64_t(d), count)) count = UINT64_MAX;
        limits::require_at_most(dir + "/state.json: " + p.name, "value count", count, limits::kParamValues);
        const size_t size = size_t(count);
        param.shape.assign(shape.begin(), shape.end());
        param.value = read_floats(dir + "/" + p.name + ".value", size);
        validate_param(param, dir + "/" + p.name + ".value");
        param.grad.assign(size, 0.f);
        const bool half = p.adam.settings().bf16_moments;
        if (s.value("moments", std::string("float32")) != (half ? "bfloat16" : "float32"))
          throw file_error(dir + "/state.json",
                           "checkpoint moments of '" + p.name + "' are not in this config's precision (\"moments\")");
        if (half) {
          p.adam.m16 = read_floats<uint16_t>(dir + "/" + p.name + ".adam_m", size);
          p.adam.v16 = read_floats<uint16_t>(dir + "/" + p.name + ".adam_v", size);
          check_moments(p.name, p.adam.m16, p.adam.v16);
        } else {
          p.adam.m = read_floats(dir + "/" + p.name + ".adam_m", size);
          p.adam.v = read_floats(dir + "/" + p.name + ".adam_v", size);
          check_moments(p.name, p.adam.m, p.adam.v);
        }
        // Steps since the last moment reset ≤ steps overall ≤ iterations done.
        const int decay_t = integer(s.at("adam_decay_t"), p.name + " adam_decay_t", 0, next_iteration);
        p.adam.set_state(integer(s.at("adam_t"), p.name + " adam_t", 0, decay_t), decay_t);
        p.average_count = s.contains("average_count")
                              ? integer(s.at("average_count"), p.name + " average_count", 0, next_iteration)
                              : 0;
        p.average.clear();
        if (p.average_count > 0) {
          p.average = read_floats(dir + "/" + p.name + ".average", size);
          Param average;  // the range to check against, without copying the value or gradient
          average.name = param.name, average.lower = param.lower, average.upper = param.upper;
          average.value = p.average;
          validate_param(average, dir + "/" + p.name + ".average");
        }
      }
      const auto row = [&](const json& r, size_t n, const std::string& name) -> const json& {
        if (!r.is_array() || r.size() != n) bad(name + " rows must be arrays of " + std::to_string(n) + " numbers");
        return r;
      };
      for (const auto& r : state.at("log")) {
        row(r, 4, "log");
        // (rmse is −1 without a ground truth)
        log_.push_back({integer(r[0], "log iteration", 0, next_iteration), number(r[1], "log loss", -HUGE_VAL),
                        number(r[2], "log seconds", 0.0), number(r[3], "log rmse", -1.0)});
      }
      if (state.contains("validation"))  // checkpoints from before validation losses have none
        for (const auto& r : state.at("validation")) {
          row(r, 3, "validation");
          validation_.push_back({integer(r[0], "validation iteration", 0, next_iteration),
                                 // (unbiased: slightly negative near zero)
                                 number(r[1], "validation loss", -HUGE_VAL), number(r[2], "validation seconds", 0.0)});
        }
      elapsed_before_ = number(state.at("seconds"), "seconds", 0.0);
      initial_loss_ = number(state.at("initial_loss"), "initial_loss", -1.0);  // −1: not measured yet
      if (state.contains("initial_rmse") && !state.at("initial_rmse").is_null())
        initial_rmse_ = number(state.at("initial_rmse"), "initial_rmse", -1.0);
      scene_->prepare_sampling();
      return next_iteration;
    } catch (const json::exception& e) {
      // Without nlohmann's "[json.exception.out_of_range.403] " prefix: "key 'adam_m' not found".
      std::string what = e.what();
      if (const size_t id = what.find("] "); what.rfind("[json.exception.", 0) == 0 && id != std::string::npos)
        what.erase(0, id + 2);
      throw file_error(dir + "/state.json", "checkpoint does not match this config (" + what + ")");
    }
  }

  void finish(double seconds) {
    // The result of an averaging parameter is its iterate average (the last iterate's RMSE is
    // kept for the summary).
    std::map<std::string, double> last_iterate_rmse;
    for (auto& p : c_.params) {
      if (p.average_count == 0) continue;
      Param& param = scene_->params[p.handle];
      if (p.ground_truth) last_iterate_rmse[p.name] = truth_rmse(p, param, param.value);
      param.value = p.average;
    }
    scene_->prepare_sampling();
    // compare.png: target | initial | final, for the first view (rendered by all ranks).
    const Image final_view = render(*scene_, {cameras_[0], c_.reference_spp, 0xabcdefull, false});
    const double mpi_seconds = dist::mpi_seconds(), reduced = dist::reduced_bytes();
    const std::vector<double> rss = dist::gather(dist::peak_rss_bytes()), in_mpi = dist::gather(mpi_seconds),
                              bytes = dist::gather(reduced), steps = dist::gather(step_seconds_),
                              hashes = dist::gather(double(parameter_hash() >> 12));  // 52 bits: exact
    if (!root_) return;
    fs::create_directories(out("final"));
    json summary;
    summary["iterations"] = c_.iterations;
    summary["wall_time_seconds"] = seconds;
    summary["initial_loss"] = log_.empty() ? 0.0 : log_.front().loss;
    summary["final_loss"] = log_.empty() ? 0.0 : log_.back().loss;
    summary["views"] = cameras_.size();
    summary["views_per_iteration"] = c_.views_per_iteration;
    summary["spp"] = c_.spp;
    summary["adjoint_spp"] = c_.adjoint_spp;
    // Each process of the run (MPI ranks; one on a single process), since this start or resume.
    summary["ranks"] = json::array();
    for (size_t r = 0; r < rss.size(); ++r)
      summary["ranks"].push_back({{"rank", r},
                                  {"peak_rss_mb", rss[r] / 1048576.0},
                                  {"mpi_seconds", in_mpi[r]},
                                  {"reduced_mb", bytes[r] / 1048576.0},
                                  {"step_seconds", steps[r]},
                                  {"parameter_hash", uint64_t(hashes[r])}});
    if (!validation_.empty()) {
      summary["validation_loss_initial"] = validation_.front().loss;
      summary["validation_loss_final"] = validation_.back().loss;
      summary["validation"] = {{"every", c_.validation_every}, {"spp", c_.validation_spp}};
    }
    json final_params = json::object();
    for (const auto& p : c_.params) {
      const Param& param = scene_->params[p.handle];
      if (is_grid(param)) {
        write_vol(out("final/" + p.name + ".vol"), grid_of(param), param.value);
        write_grid_picture(out("final/" + p.name + ".png"), grid_sheet(view_of(param), grid_vmax(p, param)));
      } else if (param.is_image()) {
        write_image(out("final/" + p.name + ".exr"), param_image(param));
        write_image(out("final/" + p.name + ".png"), param_image(param), param.srgb);
      } else {
        final_params[p.name] = param.value;
      }
      if (!p.mesh_indices.empty()) {
        // The optimized mesh, for a mesh viewer: world positions, the scene's triangles.
        std::string ply = "ply\nformat ascii 1.0\ncomment backlight optimize: " + p.name + "\nelement vertex " +
                          std::to_string(param.value.size() / 3) +
                          "\nproperty float x\nproperty float y\nproperty float z\nelement face " +
                          std::to_string(p.mesh_indices.size() / 3) +
                          "\nproperty list uchar int vertex_indices\nend_header\n";
        char line[96];
        for (size_t v = 0; v + 2 < param.value.size(); v += 3) {
          std::snprintf(line, sizeof line, "%.9g %.9g %.9g\n", param.value[v], param.value[v + 1], param.value[v + 2]);
          ply += line;
        }
        for (size_t t = 0; t + 2 < p.mesh_indices.size(); t += 3) {
          std::snprintf(line, sizeof line, "3 %u %u %u\n", p.mesh_indices[t], p.mesh_indices[t + 1],
                        p.mesh_indices[t + 2]);
          ply += line;
        }
        write_text_atomic(out("final/" + p.name.substr(0, p.name.rfind('.')) + ".ply"), ply);
      }
      if (p.ground_truth) {
        const Param& gt = *p.ground_truth;
        int w = c_.rmse_width ? c_.rmse_width : gt.width(), h = c_.rmse_height ? c_.rmse_height : gt.height();
        // The initial value, rebuilt the same way the run started.
        auto initial_scene = load_scene(c_.scene);
        apply_scene_overrides(*initial_scene);
        Param initial = initial_scene->params[initial_scene->params.find(p.name)];
        if (!p.init.is_null()) {
          apply_init(*initial_scene, p);
          initial = initial_scene->params[initial_scene->params.find(p.name)];
        }
        double before = truth_rmse(p, initial, initial.value), after = truth_rmse(p, param, param.value);
        if (is_grid(param) && is_grid(gt) && is_grid(initial)) {
          // slices.png: ground truth / initial / final, rows of the same four panels.
          const float vmax = grid_vmax(p, param);
          write_grid_picture(out("slices.png"),
                             stack_rows({grid_sheet(view_of(gt), vmax), grid_sheet(view_of(initial), vmax),
                                         grid_sheet(view_of(param), vmax)}));
        }
        summary["parameters"][p.name] = {
            {"rmse_initial", before}, {"rmse_final", after}, {"rmse_reduction", after > 0 ? before / after : 0.0}};
        // Images are compared resampled to a resolution, grids at the truth's; other parameters
        // (vectors, a mesh's positions) value by value, at no resolution (a mesh said "at 1x1").
        if (is_grid(gt))
          summary["parameters"][p.name]["rmse_resolution"] = {gt.shape[2], gt.shape[1], gt.shape[0]};
        else if (param.is_image())
          summary["parameters"][p.name]["rmse_resolution"] = {w, h};
        if (!p.mesh_indices.empty()) {
          const double d0 = surface_distance(initial.value, gt.value, p.mesh_indices),
                       d1 = surface_distance(param.value, gt.value, p.mesh_indices);
          if (d0 >= 0 && d1 >= 0)
            summary["parameters"][p.name]["surface_distance"] = {
                {"initial", d0}, {"final", d1}, {"reduction", d1 > 0 ? d0 / d1 : 0.0}};
        }
        if (p.average_count > 0) {
          summary["parameters"][p.name]["averaged_iterates"] = p.average_count;
          summary["parameters"][p.name]["rmse_last_iterate"] = last_iterate_rmse[p.name];
        }
      }
    }
    write_text_atomic(out("final/params.json"), final_params.dump(1) + "\n");
    write_image(out("final/view.exr"), final_view);
    Image initial = read_image(out("initial.exr"), false);
    const Image& target = targets_[0];
    Image compare(target.width * 3, target.height, 3);
    const Image* panels[3] = {&target, &initial, &final_view};
    for (int k = 0; k < 3; ++k)
      for (int y = 0; y < target.height; ++y)
        for (int x = 0; x < target.width; ++x)
          for (int ch = 0; ch < 3; ++ch) compare.at(k * target.width + x, y, ch) = panels[k]->at(x, y, ch);
    write_image(out("compare.png"), compare);
    write_text_atomic(out("summary.json"), summary.dump(1) + "\n");
    write_report(c_.iterations, seconds, true);
    // Again at the end: a process killed just before this run started (a plot child dying with
    // its parent) may still have been alive when the start cleared the folder.
    remove_stale_temporaries(c_.output);
    std::fprintf(stderr, "optimize: %d iterations in %.1f s, loss %.4g -> %.4g; results in %s\n", c_.iterations,
                 seconds, summary["initial_loss"].get<double>(), summary["final_loss"].get<double>(),
                 c_.output.c_str());
    if (!validation_.empty())
      std::fprintf(stderr, "optimize: validation loss (%d spp, fixed seeds) %.4g -> %.4g\n", c_.validation_spp,
                   validation_.front().loss, validation_.back().loss);
    for (auto it = summary["parameters"].begin(); summary.contains("parameters") && it != summary["parameters"].end();
         ++it) {
      std::string at;
      if (it.value().contains("rmse_resolution"))
        for (const auto& d : it.value()["rmse_resolution"])
          at += (at.empty() ? " at " : "x") + std::to_string(d.get<int>());
      std::fprintf(stderr, "optimize: %s RMSE vs ground truth %.4f -> %.4f (%.1fx)%s\n", it.key().c_str(),
                   it.value()["rmse_initial"].get<double>(), it.value()["rmse_final"].get<double>(),
                   it.value()["rmse_reduction"].get<double>(), at.c_str());
      if (it.value().contains("surface_distance")) {
        const json& d = it.value()["surface_distance"];
        std::fprintf(stderr, "optimize: %s surface distance to the truth %.5f -> %.5f (%.1fx)\n", it.key().c_str(),
                     d["initial"].get<double>(), d["final"].get<double>(), d["reduction"].get<double>());
      }
    }
  }
};

}  // namespace

int run_optimize(const std::string& config_path, const std::string& resume_dir, int threads, bool quiet,
                 bool resume_any_scene) {
  if (threads < 0) throw InputError("--threads must be ≥ 1");
  limits::require_at_most("--threads", "thread count", uint64_t(threads), limits::kThreads);
  std::unique_ptr<tbb::global_control> limit;
  if (threads > 0)
    limit = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, size_t(threads));
  return with_path_errors([&] {
    Config config = parse_config(config_path);
    if (!resume_dir.empty()) {
      if (!fs::is_directory(resume_dir)) throw file_error(resume_dir, "--resume: not a directory");
      config.output = resume_dir;
    }
    Job job(std::move(config), quiet, resume_any_scene);
    return job.run(!resume_dir.empty());
  });
}

void check_optimize_config(const std::string& config_path) {
  with_path_errors([&] { (void)parse_config(config_path); });
}

}  // namespace bl
