#include "engine/integrators/render.h"

#include <tbb/parallel_for.h>

#include <atomic>

#include "engine/dist/dist.h"
#include "engine/integrators/path.h"
#include "engine/io/progress.h"

namespace bl {

uint64_t owned_pixels(int width, int height) {
  constexpr int kTile = dist::kTile;
  const int tiles_x = (width + kTile - 1) / kTile, tiles = dist::tile_count(width, height);
  uint64_t n = 0;
  for (int t = 0; t < tiles; ++t)
    if (dist::owns_tile(t, tiles)) {
      const int x0 = (t % tiles_x) * kTile, y0 = (t / tiles_x) * kTile;
      n += uint64_t(std::min(x0 + kTile, width) - x0) * uint64_t(std::min(y0 + kTile, height) - y0);
    }
  return n;
}

void for_each_tile(int width, int height, const std::function<void(int, int, int, int)>& tile_fn,
                   const std::atomic<bool>* cancel) {
  constexpr int kTile = dist::kTile;
  const int tiles_x = (width + kTile - 1) / kTile, tiles = dist::tile_count(width, height);
  tbb::parallel_for(0, tiles, [&](int t) {
    if (!dist::owns_tile(t, tiles)) return;  // another MPI rank's
    if (cancelled(cancel)) return;
    int x0 = (t % tiles_x) * kTile, y0 = (t / tiles_x) * kTile;
    tile_fn(x0, y0, std::min(x0 + kTile, width), std::min(y0 + kTile, height));
  });
}

Image render(const Scene& scene, const PassOptions& o, PassStats* stats) {
  const Camera& cam = scene.cameras.at(size_t(o.camera));
  Image image(cam.width, cam.height, 3);
  Progress progress("render", owned_pixels(cam.width, cam.height) * uint64_t(o.spp), "spp", o.progress);
  progress.set_ranks(dist::size());
  std::atomic<uint64_t> rays{0}, shadow_rays{0}, packet_rays{0};
  for_each_tile(
      cam.width, cam.height,
      [&](int x0, int y0, int x1, int y1) {
        const Geometry::RayCounts rays_before = Geometry::thread_ray_counts();
        NoObserver none;
        for (int y = y0; y < y1; ++y)
          for (int x = x0; x < x1; ++x) {
            if (cancelled(o.cancel)) continue;
            const uint64_t pixel = uint64_t(y) * uint64_t(cam.width) + uint64_t(x);
            Vec3d sum(0.0);  // double: the mean of many samples does not drift with spp
            CameraPacket packet;
            for (int s0 = 0; s0 < o.spp; s0 += Geometry::kPacket) {
              const int n = std::min(Geometry::kPacket, o.spp - s0);
              packet.trace(scene, cam, o.seed, x, y, n, [&](int k) { return s0 + k; });
              for (int k = 0; k < n; ++k) {
                const PathSampler sampler(o.seed, pixel, uint64_t(s0 + k));
                sum += Vec3d(trace_path<float>(scene, packet.start(k), sampler, none));
              }
            }
            const Vec3f mean(sum / double(o.spp));
            for (int c = 0; c < 3; ++c) image.at(x, y, c) = mean[c];
          }
        const Geometry::RayCounts cast = Geometry::thread_ray_counts() - rays_before;
        rays += cast.all;
        shadow_rays += cast.shadow;
        packet_rays += cast.packet;
        progress.advance(uint64_t(x1 - x0) * uint64_t(y1 - y0) * uint64_t(o.spp));
      },
      o.cancel);
  progress.finish();
  dist::complete_image(image);
  const uint64_t all_rays = dist::sum(rays.load());  // collective: every rank, stats or not
  const uint64_t all_shadow = dist::sum(shadow_rays.load()), all_packet = dist::sum(packet_rays.load());
  if (stats) {
    stats->seconds = progress.elapsed();
    stats->samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(o.spp);
    stats->rays = all_rays;
    stats->shadow_rays = all_shadow;
    stats->packet_rays = all_packet;
  }
  return image;
}

}  // namespace bl
