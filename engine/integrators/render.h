#pragma once
#include <atomic>
// Image-level passes: the primal render and the adjoint (gradient) pass.
#include <cstdint>
#include <functional>

#include "engine/io/image_io.h"
#include "engine/scene/scene.h"

namespace bl {

struct PassOptions {
  int camera = 0;
  int spp = 16;
  uint64_t seed = 0;
  bool progress = true;
  // Adjoint passes: replay every path to its end instead of stopping after its last vertex that
  // can produce a derivative (same gradient, slower; for tests and benchmarks).
  bool replay_whole_paths = false;
  // Set from another thread (Python's Ctrl-C): the pass skips its remaining tiles and returns
  // early with a partial result, which the caller discards.
  const std::atomic<bool>* cancel = nullptr;
};

struct PassStats {
  double seconds = 0;
  uint64_t samples = 0;
  uint64_t rays = 0;
  uint64_t shadow_rays = 0, packet_rays = 0;  // of `rays`: shadow rays, camera rays traced in packets
};

// Primal render: box filter, pixel value = mean of its samples. Bitwise identical for any
// thread count and any number of MPI ranks: each pixel's samples are summed in a fixed order by a
// single task. Under MPI, every rank returns the whole image; stats count all ranks' rays.
Image render(const Scene& scene, const PassOptions& options, PassStats* stats = nullptr);

enum class AdjointMethod { Prb, Rb };

// Supplies δI for a pixel given its freshly rendered value (a per-pixel loss gradient, or a
// lookup into a given adjoint image).
using PixelAdjoint = std::function<Vec3f(size_t pixel, const Vec3f& value)>;

// The adjoint pass. For every pixel it renders the pixel's samples (needed by path replay, and
// giving the pixel's value to `adjoint`), then transports δI = adjoint(pixel, value) back into
// the scene and accumulates parameter gradients into the ParamStore's grad buffers (which the
// caller zeroes; see ParamStore::require_grad). Memory: per-thread state only.
// `image_out`, when given, receives the pixel values rendered on the way.
// Under MPI a rank transports its own tiles' δI: its grad buffers hold its share until the
// caller sums them with dist::reduce_gradients (once, after all the passes of a gradient);
// `image_out` is completed on every rank.
PassStats backward(Scene& scene, const PassOptions& options, AdjointMethod method, const PixelAdjoint& adjoint,
                   Image* image_out = nullptr);

// Runs `tile_fn(x0, y0, x1, y1)` over 16×16 tiles in parallel (TBB): under MPI, over this
// rank's tiles only (engine/dist/dist.h).
void for_each_tile(int width, int height, const std::function<void(int, int, int, int)>& tile_fn,
                   const std::atomic<bool>* cancel = nullptr);
// Whether a pass was asked to stop (PassOptions::cancel). for_each_tile checks it per tile and
// the passes per pixel: at 2^20 spp one 16² tile is minutes of work.
inline bool cancelled(const std::atomic<bool>* cancel) { return cancel && cancel->load(std::memory_order_relaxed); }
// Pixels in this rank's tiles (all of them on one rank).
uint64_t owned_pixels(int width, int height);

}  // namespace bl
