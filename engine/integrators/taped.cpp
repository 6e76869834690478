#include "engine/integrators/taped.h"

#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for_each.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>

#include "engine/core/errors.h"
#include "engine/core/tape.h"
#include "engine/dist/dist.h"
#include "engine/integrators/path.h"
#include "engine/io/progress.h"

namespace bl {

size_t cgroup_memory_limit(const std::string& proc_cgroup, const std::string& root) {
  std::ifstream self(proc_cgroup);
  std::string line, v2, v1;
  while (std::getline(self, line)) {
    if (line.rfind("0::", 0) == 0) v2 = line.substr(3);
    const size_t colon = line.find(':'), second = line.find(':', colon + 1);
    if (colon != std::string::npos && second != std::string::npos) {
      const std::string controllers = line.substr(colon + 1, second - colon - 1);
      if (("," + controllers + ",").find(",memory,") != std::string::npos) v1 = line.substr(second + 1);
    }
  }
  auto read = [](const std::string& path) -> size_t {
    std::ifstream f(path);
    std::string text;
    if (!(f >> text) || text.empty() || text.find_first_not_of("0123456789") != std::string::npos) return 0;  // "max"
    const double v = std::strtod(text.c_str(), nullptr);
    return v > 0 && v < 4e18 ? size_t(v) : 0;  // v1 says "no limit" with ~2^63
  };
  for (const std::string& path : {root + v2 + "/memory.max", root + "/memory" + v1 + "/memory.limit_in_bytes",
                                  root + "/memory/memory.limit_in_bytes"})
    if (size_t limit = read(path)) return limit;
  return 0;
}

size_t physical_memory_bytes() {
  const size_t ram = size_t(sysconf(_SC_PHYS_PAGES)) * size_t(sysconf(_SC_PAGE_SIZE));
  const size_t limit = cgroup_memory_limit("/proc/self/cgroup", "/sys/fs/cgroup");
  return limit ? std::min(ram, limit) : ram;
}

size_t parse_memory_size(const std::string& text) {
  char* end = nullptr;
  double v = std::strtod(text.c_str(), &end);
  std::string unit = end ? std::string(end) : "";
  for (auto& c : unit) c = char(std::toupper(c));
  double scale = unit.empty() || unit == "B"   ? 1.0
                 : unit == "K" || unit == "KB" ? 1e3
                 : unit == "KIB"               ? 1024.0
                 : unit == "M" || unit == "MB" ? 1e6
                 : unit == "MIB"               ? 1048576.0
                 : unit == "G" || unit == "GB" ? 1e9
                 : unit == "GIB"               ? 1073741824.0
                                               : -1;
  if (end == text.c_str() || scale < 0 || !(v > 0) || !std::isfinite(v))
    throw InputError("--memory-budget '" + text + "': expected a size such as 512MB or 4GB");
  // Converting a double beyond 2^64 to size_t is undefined; no machine has 2^62 bytes anyway.
  constexpr double kMaxBudget = double(uint64_t(1) << 62);
  if (v * scale > kMaxBudget)
    throw InputError("--memory-budget '" + text + "': " + std::to_string(v * scale) + " bytes exceeds the limit of " +
                     std::to_string(uint64_t(1) << 62));
  if (v * scale < 1)  // rounds to 0, which means "the default" (80% of RAM) to the taped mode
    throw InputError("--memory-budget '" + text + "': less than one byte");
  return size_t(v * scale);
}

namespace {

// Bytes the tape costs per entry: the entry itself plus the adjoint slot of the reverse sweep.
constexpr size_t kBytesPerEntry = sizeof(TapeEntry) + sizeof(float);
// A thread's tape addresses its entries with 32-bit indices below Tape::kLeaf; a packet of 8
// samples records far fewer than the margin left here.
constexpr size_t kMaxTapeEntries = size_t(Tape::kLeaf) - (size_t(1) << 28);

// Three digits ("13.1 MB", "0.001 MB": a budget of 1KB was "0 MB", and a projection of 13.2 MB
// against a budget of 13.1 MB read "13 MB ... budget of 13 MB"); whole megabytes from 1000 on.
std::string megabytes(double bytes) {
  char buf[32];
  std::snprintf(buf, sizeof buf, bytes < 1e9 ? "%.3g MB" : "%.0f MB", bytes / 1e6);
  return buf;
}

// "37%", or "0.4%" below one (the guard can trip after a few of a large render's samples).
std::string percent(uint64_t part, uint64_t whole) {
  char buf[32];
  const double p = 100.0 * double(part) / double(whole);
  std::snprintf(buf, sizeof buf, p < 1 ? "%.2g%%" : "%.0f%%", p);
  return buf;
}

struct PixelOutput {
  Tape* tape = nullptr;
  uint32_t index[3] = {Tape::kNone, Tape::kNone, Tape::kNone};
};

}  // namespace

GradientResult taped_gradient(Scene& scene, const GradientRequest& rq) {
  if (rq.adjoint_seed != rq.pass.seed)
    throw InputError("--method taped records one render and differentiates it: --adjoint-seed must equal --seed");
  const Camera& cam = scene.cameras.at(size_t(rq.pass.camera));
  const size_t pixels = size_t(cam.width) * size_t(cam.height);
  const size_t own_pixels = size_t(owned_pixels(cam.width, cam.height));  // this MPI rank's tiles
  const size_t budget = rq.memory_budget ? rq.memory_budget : size_t(0.8 * double(physical_memory_bytes()));
  GradientResult result;
  result.image = Image(cam.width, cam.height, 3);
  std::vector<PixelOutput> outputs(pixels);
  tbb::enumerable_thread_specific<Tape> tapes;
  std::atomic<uint64_t> entries{0}, samples_done{0};
  std::atomic<bool> over_budget{false};
  std::atomic<double> projected_bytes{0};  // or the recorded size, with actual_over
  std::atomic<uint64_t> trigger_samples{0};
  std::atomic<bool> actual_over{false};  // the recorded size itself passed the budget
  std::atomic<bool> index_over{false};   // a thread's tape reached kMaxTapeEntries
  const uint64_t own_samples = uint64_t(own_pixels) * uint64_t(rq.pass.spp);

  // Memory guard, after every packet of camera samples (a tile at 1024 spp recorded 400 MB before
  // a guard after each tile looked): projects the final size from the samples recorded so far and
  // stops as soon as the projection (after 5% of them) or the actual size passes the budget.
  auto guard = [&](uint64_t new_entries, uint64_t new_samples) {
    const uint64_t total = entries += new_entries;
    const uint64_t done = samples_done += new_samples;
    const double projected = double(total) * double(kBytesPerEntry) * double(own_samples) / double(done);
    const double actual = double(total) * double(kBytesPerEntry);
    if ((done * 20 >= own_samples && projected > double(budget)) || actual > double(budget)) {
      // Keep the projection that tripped the guard (other threads may project less meanwhile).
      bool expected = false;
      if (over_budget.compare_exchange_strong(expected, true)) {
        actual_over.store(actual > double(budget));
        projected_bytes.store(actual > double(budget) ? actual : projected);
        trigger_samples.store(done);
      }
    }
  };

  // 1. Record the whole render.
  Progress progress("taped record", own_samples, "spp", rq.pass.progress);
  progress.set_ranks(dist::size());
  for_each_tile(
      cam.width, cam.height,
      [&](int x0, int y0, int x1, int y1) {
        Tape& tape = tapes.local();
        current_tape = &tape;
        NoObserver none;
        for (int y = y0; y < y1; ++y)
          for (int x = x0; x < x1; ++x) {
            if (cancelled(rq.pass.cancel) || over_budget.load(std::memory_order_relaxed)) continue;
            const uint64_t pixel = uint64_t(y) * uint64_t(cam.width) + uint64_t(x);
            Spectrum<Var> sum(Var(0.f));
            CameraPacket packet;  // the camera rays as render() traces them
            for (int s0 = 0; s0 < rq.pass.spp; s0 += Geometry::kPacket) {
              const int n = std::min(Geometry::kPacket, rq.pass.spp - s0);
              const size_t before = tape.size();
              packet.trace(scene, cam, rq.pass.seed, x, y, n, [&](int k) { return s0 + k; });
              for (int k = 0; k < n; ++k) {
                const PathSampler sampler(rq.pass.seed, pixel, uint64_t(s0 + k));
                sum += trace_path<Var>(scene, packet.start(k), sampler, none);
              }
              guard(tape.size() - before, uint64_t(n));
              if (tape.size() >= kMaxTapeEntries) {
                index_over = true;
                over_budget = true;
              }
              if (over_budget.load(std::memory_order_relaxed)) break;
            }
            Spectrum<Var> mean = sum * (1.f / float(rq.pass.spp));
            PixelOutput& out = outputs[pixel];
            out.tape = &tape;
            for (int c = 0; c < 3; ++c) {
              result.image.at(x, y, c) = mean[c].v;
              out.index[c] = mean[c].index;
            }
            progress.advance(uint64_t(rq.pass.spp));
          }
        current_tape = nullptr;
      },
      rq.pass.cancel);
  // Throw before finishing the progress bar, so the error is the only line a failed run leaves.
  if (index_over)
    throw InputError("taped: one thread's tape reached " + std::to_string(kMaxTapeEntries) +
                     " entries, the most its 32-bit indices address (lower --spp / --resolution / --max-depth, or "
                     "use more threads)");
  if (over_budget)
    throw InputError("taped: the tape " +
                     (actual_over ? "already needs " + megabytes(projected_bytes.load()) + " after "
                                  : "is projected to need about " + megabytes(projected_bytes.load()) + " from ") +
                     percent(trigger_samples.load(), own_samples) + " of the samples, more than the memory budget of " +
                     megabytes(double(budget)) +
                     " (raise --memory-budget, or lower --spp / --resolution / --max-depth)");
  progress.finish();
  dist::complete_image(result.image);
  result.primal_seconds = progress.elapsed();

  // 2. Loss (or functional) on the finished image, and its image-space adjoint.
  Image adjoint;
  if (rq.adjoint_image) {
    adjoint = *rq.adjoint_image;
    result.loss = 0;
    for (size_t i = 0; i < adjoint.data.size(); ++i)
      result.loss += double(adjoint.data[i]) * double(result.image.data[i]);
  } else {
    LossResult lr = compute_loss(rq.loss, result.image, *rq.target);
    result.loss = lr.value;
    adjoint = std::move(lr.adjoint);
  }

  // 3. One reverse sweep per thread tape.
  auto t0 = std::chrono::steady_clock::now();
  ParamStore& store = scene.params;
  std::vector<size_t> offsets;
  for (const auto& p : store.all()) offsets.push_back(p.tape_offset);
  GradientSink sink(store);
  std::vector<Tape*> all_tapes;
  for (auto& t : tapes) all_tapes.push_back(&t);
  Progress sweep("taped sweep", entries.load(), "entries", rq.pass.progress);
  sweep.set_ranks(dist::size());
  tbb::parallel_for_each(all_tapes.begin(), all_tapes.end(), [&](Tape* tape) {
    std::vector<float> adj(tape->size(), 0.f);
    for (size_t p = 0; p < pixels; ++p)
      if (outputs[p].tape == tape)
        for (int c = 0; c < 3; ++c)
          if (outputs[p].index[c] != Tape::kNone) adj[outputs[p].index[c]] += adjoint.data[p * 3 + size_t(c)];
    GradientAccumulator& grads = sink.local();
    reverse_sweep(
        *tape, adj,
        [&](uint32_t flat, float g) {
          size_t handle = size_t(std::upper_bound(offsets.begin(), offsets.end(), size_t(flat)) - offsets.begin()) - 1;
          grads.add(int(handle), size_t(flat) - offsets[handle], g);
        },
        [&](size_t n) { sweep.advance(n); });
  });
  sweep.finish();
  sink.reduce();
  result.adjoint_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  result.tape_entries = entries.load();
  result.tape_bytes = result.tape_entries * sizeof(TapeEntry);
  result.tape_budget_bytes = result.tape_entries * kBytesPerEntry;
  return result;
}

}  // namespace bl
