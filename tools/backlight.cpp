// backlight — command-line front end: render, params, grad, check, optimize.
// Every user error (bad file, bad flag, bad value) prints one line "backlight: <problem>" and
// exits with code 2; internal failures exit with 1.
#include <tbb/global_control.h>
#include <CLI/CLI.hpp>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <memory>
#include <new>
#include <optional>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/dist/dist.h"
#include "engine/integrators/gradient.h"
#include "engine/integrators/loss.h"
#include "engine/integrators/render.h"
#include "engine/integrators/taped.h"
#include "engine/io/image_io.h"
#include "engine/io/progress.h"
#include "engine/optimize/optimizer.h"
#include "engine/scene/scene_load.h"

using namespace bl;
namespace fs = std::filesystem;

namespace {

// Integer flags take decimal digits, with a '-' only where negatives mean something (--max-depth
// -1). CLI11 converts with strtoll(.., 0), which read "0x10" as 16 and "010" as 8 (octal) and
// skipped leading spaces, while --seed refused "0x1F" and "1e1" was CLI11's "Could not convert".
// This transform checks the text and the range of the flag's type, and drops leading zeros, so
// that CLI11's conversion reads the decimal number that was written.
// max_text is max written out for the message; negative values are taken by int flags only, down
// to -2^31.
CLI::Validator decimal(bool negative, uint64_t max, const char* max_text, const char* description = "") {
  return CLI::Validator(
      [=](std::string& text) -> std::string {
        const bool minus = negative && !text.empty() && text[0] == '-';
        const std::string digits = text.substr(minus ? 1 : 0);
        if (digits.empty() || digits.find_first_not_of("0123456789") != std::string::npos)
          return "'" + text +
                 (negative ? "' is not an integer (decimal digits, after an optional '-')"
                           : "' is not a non-negative integer (decimal digits only)");
        errno = 0;
        const uint64_t magnitude = std::strtoull(digits.c_str(), nullptr, 10);
        if (errno == ERANGE || magnitude > max + (minus ? 1 : 0))
          return "'" + text + (minus ? std::string("' is below -2^31") : "' exceeds " + std::string(max_text));
        text = (minus && magnitude > 0 ? "-" : "") + std::to_string(magnitude);
        return {};
      },
      description);
}
const CLI::Validator kCount = decimal(false, INT32_MAX, "2^31 - 1");          // int flags ≥ 0
const CLI::Validator kInteger = decimal(true, INT32_MAX, "2^31 - 1");         // int flags that take -1
const CLI::Validator kSeed = decimal(false, UINT64_MAX, "2^64 - 1", "SEED");  // CLI11 took "-1" and 10^23 as 2^64 - 1

const std::string kThreadsHelp =
    "Worker threads (default, or 0: all cores; at most " + std::to_string(limits::kThreads) + ")";

// Flags every scene-consuming command shares.
struct SceneFlags {
  std::string scene;
  std::vector<std::string> sets;
  std::string resolution;
  int camera = 0;
  std::optional<int> spp, max_depth, rr_depth;
  std::optional<uint64_t> seed;
  int threads = 0;
  bool quiet = false;

  void add_to(CLI::App* app) {
    app->add_option("scene", scene, "Scene file (.json, a .gltf/.glb or a Mitsuba 3 .xml, rendered directly)")
        ->required();
    app->add_option("--set", sets, "Override a parameter: NAME=path/to/image.exr or NAME=v1,v2,v3 (repeatable)");
    app->add_option("--resolution", resolution, "Film size WxH (overrides the camera's)");
    app->add_option("--camera", camera, "Camera index (default 0)")->transform(kCount);
    app->add_option("--spp", spp, "Samples per pixel (default: the scene's)")->transform(kCount);
    app->add_option("--seed", seed, "Sampler seed (default: the scene's)")->transform(kSeed);
    app->add_option("--max-depth", max_depth,
                    "Maximum path segments incl. the camera ray (Mitsuba 3's max_depth; -1 = unlimited)")
        ->transform(kInteger);
    app->add_option("--rr-depth", rr_depth,
                    "Russian roulette from this surface vertex on; 0 = off (default: the scene's)")
        ->transform(kCount);
    app->add_option("--threads", threads, kThreadsHelp)->transform(kCount);
    app->add_flag("--quiet,-q", quiet, "No progress bar");
  }

  std::unique_ptr<Scene> load() const {
    auto s = load_scene(scene);
    for (const auto& a : sets) apply_override(*s, a);
    if (camera < 0 || size_t(camera) >= s->cameras.size())
      throw InputError("--camera " + std::to_string(camera) + ": the scene has " + std::to_string(s->cameras.size()) +
                       " camera(s)");
    if (!resolution.empty()) {
      // Digits only, at most 5 per side: sscanf's %d wrapped 4294967304 around to 8.
      const auto side = [&](const std::string& digits) {
        if (digits.empty() || digits.size() > 5 ||
            !std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; }))
          return 0;
        return std::stoi(digits);
      };
      const size_t x = resolution.find_first_of("xX");
      const int w = x == std::string::npos ? 0 : side(resolution.substr(0, x));
      const int h = x == std::string::npos ? 0 : side(resolution.substr(x + 1));
      if (w < 1 || h < 1 || w > 16384 || h > 16384)
        throw InputError("--resolution '" + resolution + "': expected WxH, each side in 1..16384, e.g. 256x256");
      for (auto& c : s->cameras) c.width = w, c.height = h;
      for (auto& c : s->cameras) c.update();
    }
    if (spp) {
      if (*spp < 1) throw InputError("--spp must be ≥ 1");
      limits::require_at_most("--spp", "sample count", uint64_t(*spp), limits::kSpp);
      s->settings.spp = *spp;
    }
    if (max_depth) {
      if (*max_depth == 0 || *max_depth < -1) throw InputError("--max-depth must be ≥ 1, or -1 for unlimited");
      s->settings.max_depth = *max_depth;
    }
    if (rr_depth) {
      if (*rr_depth < 0) throw InputError("--rr-depth must be ≥ 0");
      s->settings.rr_depth = *rr_depth;
    }
    if (seed) s->settings.seed = *seed;
    require_same_scene(*s);
    return s;
  }
  PassOptions pass(const Scene& s) const {
    PassOptions o;
    o.camera = camera;
    o.spp = s.settings.spp;
    o.seed = s.settings.seed;
    o.progress = !quiet;
    return o;
  }
};

std::unique_ptr<tbb::global_control> thread_limit(int threads) {
  if (threads < 0) throw InputError("--threads must be ≥ 1 (or 0: all cores)");
  limits::require_at_most("--threads", "thread count", uint64_t(threads), limits::kThreads);
  if (threads == 0) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, size_t(threads));
}

Image read_target(const std::string& path, const Camera& cam, const char* what) {
  Image t = read_image(path, true);
  if (t.width != cam.width || t.height != cam.height)
    throw file_error(path, std::string(what) + " is " + std::to_string(t.width) + "x" + std::to_string(t.height) +
                               " but the camera renders " + std::to_string(cam.width) + "x" +
                               std::to_string(cam.height));
  if (t.channels < 3) {
    Image rgb(t.width, t.height, 3);
    for (size_t i = 0; i < t.pixel_count(); ++i)
      for (int c = 0; c < 3; ++c) rgb.data[i * 3 + size_t(c)] = t.data[i * size_t(t.channels)];
    return rgb;
  }
  return t;
}

int cmd_render(SceneFlags& f, const std::string& output) {
  auto limit = thread_limit(f.threads);
  if (dist::is_root()) {  // only rank 0 writes
    // The folder must exist (a mistyped one is an error, not a new folder); temporaries of this
    // output name that a killed render left there (of a process that no longer runs) are removed.
    const std::filesystem::path folder = std::filesystem::path(output).parent_path();
    check_output_creatable(output);
    remove_stale_temporaries(folder.empty() ? "." : folder.string(), false,
                             regex_escaped(std::filesystem::path(output).stem().string()));
  }
  auto scene = f.load();
  PassStats stats;
  Image img = render(*scene, f.pass(*scene), &stats);
  if (dist::is_root()) write_image(output, img);
  // The ray mix (shadow rays, camera rays traced in packets) is what bench/primal's bare Embree
  // loop casts to put the render's throughput in proportion.
  const double rays = double(std::max<uint64_t>(stats.rays, 1));
  std::fprintf(stderr, "render: %dx%d, %d spp, %.2f s, %ssamples/s, %srays/s (%.1f%% shadow, %.1f%% camera) -> %s\n",
               img.width, img.height, scene->settings.spp, stats.seconds,
               human_count(double(stats.samples) / stats.seconds).c_str(),
               human_count(double(stats.rays) / stats.seconds).c_str(), 100.0 * double(stats.shadow_rays) / rays,
               100.0 * double(stats.packet_rays) / rays, output.c_str());
  return 0;
}

int cmd_params(SceneFlags& f, bool as_json, const std::string& dump) {
  auto limit = thread_limit(f.threads);                             // --threads is checked here too (-5 was accepted)
  if (!dump.empty() && dist::is_root()) check_output_folder(dump);  // before printing anything
  auto scene = f.load();
  const auto& params = scene->params;
  if (as_json) {
    nlohmann::json arr = nlohmann::json::array();
    for (size_t i = 0; i < params.count(); ++i) {
      const Param& p = params[int(i)];
      arr.push_back({{"name", p.name}, {"shape", p.shape}, {"size", p.size()}, {"lower", p.lower}, {"upper", p.upper}});
    }
    std::cout << arr.dump(1) << "\n";
  } else {
    // The valid range too: what a --set, an init or the optimizer's projection must keep to.
    for (size_t i = 0; i < params.count(); ++i) {
      const Param& p = params[int(i)];
      std::printf("%-32s %-16s %-10zu [%g, %g]\n", p.name.c_str(), params.shape_string(int(i)).c_str(), p.size(),
                  double(p.lower), double(p.upper));
    }
  }
  if (!dump.empty() && dist::is_root()) {
    ensure_output_folder(dump);
    dump_parameter_values(*scene, dump);
  }
  return 0;
}

struct GradFlags {
  std::string target, adjoint_image, out, method = "prb", loss = "l2", memory_budget;
  std::optional<uint64_t> adjoint_seed;
  std::vector<std::string> params;
  bool replay_whole_paths = false;
  void add_to(CLI::App* app) {
    app->add_option("--target", target, "Target image the loss compares the render with");
    auto* adjoint =
        app->add_option("--adjoint-image", adjoint_image,
                        "Back-propagate this image-space gradient dI instead of a loss (gradient of sum(dI * I))");
    app->add_option("--out", out, "Output directory")->required();
    app->add_option("--method", method, "prb (path replay, default), rb (radiative backpropagation) or taped");
    // An adjoint image is its own functional: a --loss with it was ignored without a word.
    app->add_option("--loss", loss, "l2 (default), l1 or rel_l2 (with --target)")->excludes(adjoint);
    app->add_option("--adjoint-seed", adjoint_seed, "Seed of the adjoint pass (default: --seed, the exact derivative)")
        ->transform(kSeed);
    app->add_option("--param", params,
                    "Parameter to differentiate (repeatable; default: every appearance parameter, not the geometry's "
                    "translate/rotate/scale/positions or cameras, which are differentiated when named)");
    app->add_option("--memory-budget", memory_budget,
                    "Taped mode: limit on the tape and its sweep's adjoints (20 bytes per recorded operation, "
                    "checked every 8 samples), e.g. 512MB or 4GB (default 80% of RAM or of a lower cgroup limit)");
    app->add_flag("--replay-whole-paths", replay_whole_paths,
                  "prb/rb: replay each path to its end, not only to its last vertex that can produce a derivative "
                  "(same gradient, slower; for benchmarks)");
  }
};

struct CheckFlags {
  std::string target, adjoint_image, param, method = "prb", loss = "l2";
  int directions = 4, seeds = 1;
  double eps = 1e-2, tolerance = 1e-2;
  uint64_t direction_seed = 1;
  std::optional<uint64_t> adjoint_seed;
  void add_to(CLI::App* app) {
    app->add_option("--target", target, "Target image of the loss");
    auto* adjoint =
        app->add_option("--adjoint-image", adjoint_image, "Check the linear functional sum(dI * I) instead of a loss");
    app->add_option("--param", param, "Parameter to check")->required();
    app->add_option("--directions", directions, "Number of random directions (default 4)")->transform(kCount);
    app->add_option(
        "--eps", eps,
        "Finite-difference step: theta +- eps*v, v with i.i.d. standard-normal elements (vertex positions: one "
        "per welded position) (default 1e-2)");
    app->add_option("--tolerance", tolerance,
                    "Largest accepted |adjoint - finite difference|, relative to the RMS of the finite differences "
                    "over the directions; exit 1 above it (default 1e-2)");
    app->add_option("--method", method, "prb (default), rb or taped");
    app->add_option("--loss", loss, "l2 (default), l1 or rel_l2 (with --target)")->excludes(adjoint);
    app->add_option("--direction-seed", direction_seed, "Seed of the random directions (default 1)")->transform(kSeed);
    app->add_option("--adjoint-seed", adjoint_seed,
                    "Seed of the adjoint pass (default: --seed; with --seeds N, seed + k for the k-th, as the renders)")
        ->transform(kSeed);
    app->add_option(
           "--seeds", seeds,
           "Average both sides over N render seeds (seed, seed+1, ...) and accept |z| of their paired "
           "differences below Student's t quantile of the normal's 4-sigma tail for N - 1 degrees of "
           "freedom (or the means within --tolerance); INCONCLUSIVE, exit 1, when some direction could "
           "not have seen an error of 25% of the derivatives' RMS. For parameters sampling depends on (roughness, "
           "metallic, media density, scale and g) and for geometry (default 1: same-seed comparison)")
        ->transform(kCount);
  }
};

GradientRequest make_request(const SceneFlags& f, const Scene& scene, const std::string& method,
                             const std::string& loss, const std::string& target, const std::string& adjoint_image,
                             Image& target_img, Image& adjoint_img) {
  GradientRequest rq;
  auto flag = [](const char* name, auto parse) {  // errors name the flag
    try {
      return parse();
    } catch (const InputError& e) {
      throw InputError(std::string(name) + ": " + e.what());
    }
  };
  rq.method = flag("--method", [&] { return parse_method(method); });
  rq.loss = flag("--loss", [&] { return parse_loss(loss); });
  rq.pass = f.pass(scene);
  rq.adjoint_seed = rq.pass.seed;
  const Camera& cam = scene.cameras.at(size_t(f.camera));
  if (!target.empty() == !adjoint_image.empty()) throw InputError("give exactly one of --target and --adjoint-image");
  if (!target.empty()) {
    target_img = read_target(target, cam, "target");
    rq.target = &target_img;
  } else {
    adjoint_img = read_image(adjoint_image, false);
    if (adjoint_img.width != cam.width || adjoint_img.height != cam.height || adjoint_img.channels != 3)
      throw file_error(adjoint_image, "adjoint image must be " + std::to_string(cam.width) + "x" +
                                          std::to_string(cam.height) + " RGB");
    rq.adjoint_image = &adjoint_img;
  }
  return rq;
}

}  // namespace

int cmd_grad(SceneFlags& f, const GradFlags& g) {
  auto limit = thread_limit(f.threads);
  if (dist::is_root()) check_output_folder(g.out);  // before the work: a bad --out is reported at once
  auto scene = f.load();
  Image target, adjoint;
  GradientRequest rq = make_request(f, *scene, g.method, g.loss, g.target, g.adjoint_image, target, adjoint);
  if (g.adjoint_seed) rq.adjoint_seed = *g.adjoint_seed;
  if (!g.memory_budget.empty()) rq.memory_budget = parse_memory_size(g.memory_budget);
  rq.pass.replay_whole_paths = g.replay_whole_paths;
  // Flags of one method given to another were ignored without a word. Scripts that run every
  // method with the same flags (bench/memory_speed, bench/volume) keep working: a warning.
  if (dist::is_root() && !g.memory_budget.empty() && rq.method != GradientMethod::Taped)
    std::fprintf(stderr, "warning: --memory-budget limits the taped mode's tape; --method %s keeps none (ignored)\n",
                 method_name(rq.method));
  if (dist::is_root() && g.replay_whole_paths && rq.method == GradientMethod::Taped)
    std::fprintf(stderr,
                 "warning: --replay-whole-paths applies to --method prb and rb; taped replays nothing (ignored)\n");
  scene->params.require_grad(g.params);
  GradientResult r = compute_gradient(*scene, rq);
  const double mpi_seconds = dist::mpi_seconds();
  r.peak_rss_bytes = dist::gather(dist::peak_rss_bytes());
  r.mpi_seconds = dist::gather(mpi_seconds);
  if (!dist::is_root()) return 0;
  write_gradient_outputs(*scene, rq, r, g.out);
  std::fprintf(stderr, "grad: %s, %s %.6g, primal %.2f s, adjoint %.2f s -> %s\n", method_name(rq.method),
               rq.adjoint_image ? "functional" : loss_name(rq.loss), r.loss, r.primal_seconds, r.adjoint_seconds,
               g.out.c_str());
  return 0;
}

int cmd_check(SceneFlags& f, const CheckFlags& c) {
  auto limit = thread_limit(f.threads);
  auto scene = f.load();
  Image target, adjoint;
  GradientRequest rq = make_request(f, *scene, c.method, c.loss, c.target, c.adjoint_image, target, adjoint);
  if (c.adjoint_seed) rq.adjoint_seed = *c.adjoint_seed;  // as backlight.check's adjoint_seed
  if (c.directions < 1) throw InputError("--directions must be ≥ 1");
  limits::require_at_most("--directions", "direction count", uint64_t(c.directions), limits::kCheckDirections);
  if (!(c.eps > 0) || !std::isfinite(c.eps)) throw InputError("--eps must be a finite number > 0");
  if (!(c.tolerance >= 0) || !std::isfinite(c.tolerance)) throw InputError("--tolerance must be a finite number ≥ 0");
  if (scene->params.find(c.param) < 0) throw InputError("unknown parameter '" + c.param + "' (see `backlight params`)");
  if (c.seeds < 1 || c.seeds > 1 << 16) throw InputError("--seeds must be in 1 .. 65536");
  check_eps_range(scene->params[scene->params.find(c.param)], c.eps);
  // Notes on reading the result, printed after the renders: an error found by them (a step that
  // makes a vertex non-finite) is then the one line on stderr, not the last line after a note.
  std::string notes;
  const auto note = [&notes](const char* format, auto... args) {
    const int n = std::snprintf(nullptr, 0, format, args...);
    std::string text(size_t(std::max(n, 0)) + 1, '\0');
    std::snprintf(text.data(), text.size(), format, args...);
    text.resize(size_t(std::max(n, 0)));
    notes += text;
  };
  if (scene->settings.rr_depth > 0 &&
      (scene->settings.max_depth < 0 || scene->settings.max_depth > scene->settings.rr_depth))
    note(
        "note: Russian roulette is on (--rr-depth %d). Its continuation probability depends on the path\n"
        "throughput; same-seed differences see that dependence, the adjoint treats it as a constant\n"
        "(it vanishes in expectation). Use --rr-depth 0 for a tight comparison.\n",
        scene->settings.rr_depth);
  if (scene->params[scene->params.find(c.param)].geometry)
    note(
        "note: '%s' moves geometry: silhouettes and shadow edges jump between the two renders of one\n"
        "seed, and the adjoint's boundary terms estimate their effect in expectation. Expect agreement\n"
        "on the mean over many seeds (--seeds N), not per seed. Central differences are off by\n"
        "eps^2/6 F''' along v, large where the loss has edges near the silhouettes: a step is small\n"
        "enough when half of it gives the same means.\n",
        c.param.c_str());
  {
    // Appearance parameters that move sampling: the BSDF's lobe and microfacet sampling, free-flight
    // and phase sampling (helper-39: they failed at one seed without a word).
    const std::string& name = c.param;
    const auto ends_with = [&](const char* suffix) {
      const std::string s(suffix);
      return name.size() > s.size() && name.compare(name.size() - s.size(), s.size(), s) == 0;
    };
    const bool medium = std::any_of(scene->media.begin(), scene->media.end(),
                                    [&](const Medium& m) { return name.rfind(m.name + ".", 0) == 0; });
    if (ends_with(".roughness") || ends_with(".metallic") ||
        (medium && (ends_with(".density") || ends_with(".scale") || ends_with(".g"))))
      note(
          "note: '%s' moves sampling (microfacet or lobe choice, free flights, phase sampling): same-seed\n"
          "differences jump where a sample's choice flips, and the adjoint holds sampling fixed, so they\n"
          "agree in expectation: use --seeds N with --adjoint-image.\n",
          name.c_str());
  }
  if (rq.method == GradientMethod::Rb && c.seeds == 1)  // helper-41: a bare FAIL, without a word
    note(
        "note: rb carries the adjoint along paths of its own (it does not replay the render's), so its\n"
        "gradient agrees with same-seed differences in expectation, not per seed: use --seeds N\n"
        "(prb and taped agree per seed).\n");
  if (c.seeds > 1 && c.adjoint_image.empty())
    note(
        "note: with a loss, the mean over seeds of same-seed differences is the derivative of the expected\n"
        "loss; the adjoint's mean is that only for parameters that do not move sampling (for roughness,\n"
        "density, geometry or any albedo under roulette the loss gradient correlates with the sampling\n"
        "terms). To test those in expectation, use --adjoint-image (a linear functional).\n");
  auto rows = directional_check(*scene, c.param, rq, c.directions, c.eps, c.direction_seed, c.seeds);
  std::fputs(notes.c_str(), stderr);
  // Errors are measured against the RMS over the directions of the finite differences (the typical
  // ⟨∇, v⟩): a direction nearly orthogonal to the gradient has a tiny derivative whose relative
  // error is the finite difference's own truncation and rounding (summarize_check).
  const CheckSummary verdict = summarize_check(rows, c.seeds, c.tolerance);
  if (verdict.nothing_compared) {
    std::printf(
        "nothing compared: neither the adjoint nor the renders change with '%s' in %zu direction(s) (it does "
        "not reach this image, or sits where no derivative is estimated: a density at exactly 0, README \"Zero "
        "factors\")\n",
        c.param.c_str(), rows.size());
    return 1;
  }
  // An albedo at exactly (0, 0, 0) ends its paths, so no gradient is estimated there, while the
  // finite differences step off 0 and the renders change: a FAIL whose cause the table does not say.
  const bool zero_adjoint = std::all_of(rows.begin(), rows.end(), [](const CheckRow& r) { return r.adjoint == 0; });
  auto zero_note = [&] {
    if (!verdict.passed && zero_adjoint)
      std::fprintf(stderr,
                   "note: the adjoint is 0 in every direction while the renders change: '%s' sits where no "
                   "derivative is estimated (an albedo at exactly (0, 0, 0) ends its paths, README \"Zero "
                   "factors\"); start it off 0, e.g. bounds [0.001, 1]\n",
                   c.param.c_str());
  };
  if (c.seeds == 1) {
    std::printf("%-4s %16s %16s %12s %12s\n", "dir", "adjoint", "finite_diff", "rel_error", "error/rms");
    for (size_t i = 0; i < rows.size(); ++i)
      std::printf("%-4zu %16.8e %16.8e %12.3e %12.3e%s\n", i, rows[i].adjoint, rows[i].finite_difference,
                  rows[i].relative_error, rows[i].rms_relative_error, verdict.ok[i] ? "" : "  FAIL");
    std::printf("%s: %zu direction(s), |adjoint − finite_diff| ≤ %.3g × the RMS of finite_diff over the directions\n",
                verdict.passed ? "ok" : "FAILED", rows.size(), c.tolerance);
    zero_note();
    return verdict.passed ? 0 : 1;
  }
  // Over seeds: means with their standard errors, and z of the paired differences, against the
  // t quantile of the 4σ tail for this many seeds (check_z_threshold).
  std::printf("%-4s %28s %28s %9s %12s\n", "dir", "adjoint (mean ± stderr)", "finite_diff (mean ± stderr)", "z",
              "resolution");
  for (size_t i = 0; i < rows.size(); ++i)
    std::printf("%-4zu %16.8e ± %9.2e %16.8e ± %9.2e %9.2f %11.2g%%%s\n", i, rows[i].adjoint, rows[i].adjoint_stderr,
                rows[i].finite_difference, rows[i].fd_stderr, rows[i].z, 100 * verdict.resolution[i],
                verdict.ok[i] ? "" : "  FAIL");
  std::printf(
      "%s: %zu direction(s), %d seeds, |z| < %.3g (Student's t for %d seeds, the normal's 4σ tail) or "
      "|adjoint − finite_diff| of the means ≤ %.3g × their RMS over the directions\n",
      verdict.inconclusive ? "INCONCLUSIVE"
      : verdict.passed     ? "ok"
                           : "FAILED",
      rows.size(), c.seeds, verdict.threshold, c.seeds, c.tolerance);
  std::printf(
      "resolution: every direction fails an error of the adjoint's derivative along it above %.2g%% of the RMS "
      "(an adjoint off by a factor 1 + r fails for |r| above it)%s\n",
      100 * verdict.resolution_overall,
      verdict.resolution_overall > 0.25 ? " (more --seeds or --spp to tighten it below 25%)" : "");
  zero_note();
  if (verdict.inconclusive) return 1;
  return verdict.passed ? 0 : 1;
}

namespace {
int run(int argc, char** argv);
}

// Under mpirun every rank runs the same command (engine/dist/dist.h); exit codes and error lines
// follow the same rules as on one process.
int main(int argc, char** argv) {
  dist::Session session(argc, argv);
  try {
    const int code = run(argc, argv);
    dist::finish();
    return code;
  } catch (const dist::PeerFailed& e) {
    return e.code;  // another rank failed before any collective operation, and printed why
  } catch (const InputError& e) {
    return dist::fail(2, e.what());
  } catch (const std::filesystem::filesystem_error& e) {
    // A path the user gave (too long, not permitted, a file where a folder was meant).
    return dist::fail(2, e.path1().string().substr(0, 200) + ": " + e.code().message());
  } catch (const std::bad_alloc&) {
    // Inputs within every limit can still ask for more memory than the machine has (a 16384²
    // film, a schedule's 16384² texture): the request is too large, not a bug.
    return dist::fail(2,
                      "out of memory: the scene, resolution or parameters need more memory than this process can "
                      "get (lower the resolution, the parameters' sizes or the thread count)");
  } catch (const std::exception& e) {
    return dist::fail(3, std::string("internal error: ") + e.what());  // 1 is a failed check
  }
}

namespace {
int run(int argc, char** argv) {
  CLI::App app{"backlight: a differentiable path tracer with radiative backpropagation"};
  app.require_subcommand(1);
  app.set_help_all_flag("--help-all", "Help for every command");

  SceneFlags render_flags, params_flags, grad_flags, check_flags;
  std::string output;
  auto* render_cmd = app.add_subcommand("render", "Render an image (path tracer, NEE + MIS)");
  render_flags.add_to(render_cmd);
  render_cmd->add_option("-o,--output", output, "Output image (.exr float or .png sRGB)")->required();

  bool as_json = false;
  std::string dump;
  auto* params_cmd = app.add_subcommand("params", "List the scene's differentiable parameters");
  params_flags.add_to(params_cmd);
  params_cmd->add_flag("--json", as_json, "Print a JSON array of {name, shape, size, lower, upper}");
  params_cmd->add_option("--dump", dump,
                         "Write every value: image-shaped ones as DIR/<name>.exr, the rest in DIR/params.json");

  GradFlags gf;
  auto* grad_cmd = app.add_subcommand(
      "grad",
      "Gradient of an image loss (or of a linear functional) with respect to scene parameters.\n"
      "--adjoint-seed defaults to --seed, so by default the written gradient is the exact derivative of\n"
      "the estimator whose loss is reported (same random numbers) for parameters sampling does not depend\n"
      "on; for roughness-like ones it is exact in expectation (sampling is detached).");
  grad_flags.add_to(grad_cmd);
  gf.add_to(grad_cmd);

  CheckFlags cf;
  auto* check_cmd = app.add_subcommand(
      "check", "Compare adjoint directional derivatives with central finite differences of the primal renderer");
  check_flags.add_to(check_cmd);
  cf.add_to(check_cmd);

  std::string config;
  std::optional<std::string> resume;
  int opt_threads = 0;
  bool opt_quiet = false;
  auto* optimize_cmd =
      app.add_subcommand("optimize", "Gradient-descent optimization described by a JSON config (see README)");
  optimize_cmd->add_option("config", config, "Optimization config")->required();
  auto* resume_option =
      optimize_cmd->add_option("--resume", resume, "Continue from the last checkpoint in this output directory");
  bool resume_any_scene = false;
  optimize_cmd
      ->add_flag("--resume-any-scene", resume_any_scene,
                 "Resume a checkpoint made from another scene file with other content (refused otherwise)")
      ->needs(resume_option);
  optimize_cmd->add_option("--threads", opt_threads, kThreadsHelp)->transform(kCount);
  optimize_cmd->add_flag("--quiet,-q", opt_quiet, "No progress bar");

  if (argc > 1 && argv[1][0] != '-') {
    const std::string command = argv[1];
    bool known = false;
    for (const auto* sub : app.get_subcommands({})) known = known || sub->get_name() == command;
    if (!known) {
      throw InputError("unknown command '" + command + "' (expected render, params, grad, check or optimize)");
    }
  }
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::ArgumentMismatch& e) {
    // CLI11 says "--spp: At Most 1 required but received 2" for a flag given twice.
    const std::string what = e.what(), marker = ": At Most 1 required but received ";
    const size_t at = what.find(marker);
    if (at != std::string::npos)
      throw InputError(what.substr(0, at) + " is given " + what.substr(at + marker.size()) +
                       " times; give it once (see --help)");
    throw InputError(what + " (see --help)");
  } catch (const CLI::ParseError& e) {
    throw InputError(std::string(e.what()) + " (see --help)");
  }
  if (*render_cmd) return cmd_render(render_flags, output);
  if (*params_cmd) return cmd_params(params_flags, as_json, dump);
  if (*grad_cmd) return cmd_grad(grad_flags, gf);
  if (*check_cmd) return cmd_check(check_flags, cf);
  if (*optimize_cmd) {
    if (resume && resume->empty()) throw InputError("--resume: an empty directory name");
    return run_optimize(config, resume.value_or(""), opt_threads, opt_quiet, resume_any_scene);
  }
  return 0;
}
}  // namespace
