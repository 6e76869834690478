// Raw Embree throughput for a scene's ray distribution, to put the renderer's shading overhead in
// proportion. It casts the same mix of rays the path tracer does — camera rays, cosine-weighted
// bounce rays from surface points, and shadow rays towards points on emitters — in a bare
// intersect/occlude loop over TBB tiles, with no shading.
//   bench_rays SCENE RAYS [--threads T]   → prints JSON {rays, seconds, rays_per_second}
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "engine/core/sampler.h"
#include "engine/scene/scene_load.h"
#include "kernels/bsdf/bsdf.h"

using namespace bl;

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr, "usage: bench_rays SCENE RAYS [--threads T] [--shadow-fraction F]\n");
    return 2;
  }
  const std::string path = argv[1];
  const uint64_t total = std::strtoull(argv[2], nullptr, 10);
  int threads = 0;
  double shadow_fraction = 0.45;  // the path tracer casts about one shadow ray per bounce ray
  for (int i = 3; i + 1 < argc; i += 2) {
    if (std::string(argv[i]) == "--threads") threads = std::atoi(argv[i + 1]);
    if (std::string(argv[i]) == "--shadow-fraction") shadow_fraction = std::atof(argv[i + 1]);
  }
  std::unique_ptr<tbb::global_control> limit;
  if (threads > 0)
    limit = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, size_t(threads));
  try {
    auto scene = load_scene(path);
    const Camera& cam = scene->cameras[0];
    // Surface sampling table over all triangles, by area.
    std::vector<std::pair<int, size_t>> tris;
    std::vector<double> cdf;
    double area = 0;
    for (size_t m = 0; m < scene->meshes.size(); ++m)
      for (size_t t = 0; t < scene->meshes[m].triangle_count(); ++t) {
        tris.push_back({int(m), t});
        cdf.push_back(area += scene->meshes[m].triangle_area(t));
      }
    // 1. Generate a pool of rays (untimed), 2. time a bare loop casting them until `total`.
    struct PoolRay {
      Ray ray;
      bool shadow;
    };
    const uint64_t pool_size = std::min<uint64_t>(total, 1u << 20);
    std::vector<PoolRay> pool(pool_size);
    tbb::parallel_for(uint64_t(0), pool_size, [&](uint64_t i) {
      PathSampler s(7, i, 0);
      const float kind = s.get(0);
      PoolRay& out = pool[i];
      out.shadow = false;
      if (kind < (1.0 - shadow_fraction) / 6.0) {  // camera rays: one per path of ~6 segments
        out.ray = cam.generate(s.get(1) * float(cam.width), s.get(2) * float(cam.height));
        return;
      }
      // A surface point, by area.
      double u = double(s.get(3)) * area;
      size_t k = size_t(std::lower_bound(cdf.begin(), cdf.end(), u) - cdf.begin());
      k = std::min(k, tris.size() - 1);
      const Mesh& mesh = scene->meshes[size_t(tris[k].first)];
      const size_t t = tris[k].second;
      const Vec3f a = mesh.positions[mesh.indices[3 * t]], b = mesh.positions[mesh.indices[3 * t + 1]],
                  cc = mesh.positions[mesh.indices[3 * t + 2]];
      float su = std::sqrt(s.get(4)), b1 = 1 - su, b2 = s.get(5) * su;
      Vec3f p = a * (1 - b1 - b2) + b * b1 + cc * b2;
      Vec3f n = normalize(cross(b - a, cc - a));
      if (kind < 1.0 - shadow_fraction || scene->area_emitters.empty()) {
        Vec3f d = Frame(n).to_world(sample_cosine_hemisphere({s.get(6), s.get(7)}));
        out.ray.origin = offset_origin(p, n, d);
        out.ray.direction = d;
        return;
      }
      EmitterSample es = scene->sample_area_emitter(0, p, {s.get(8), s.get(9)});
      if (es.pdf <= 0) {
        es.wi = normalize(Vec3f(0, 1, 0) - p);
        es.distance = 1;
      }
      out.shadow = true;
      out.ray.origin = offset_origin(p, n, es.wi);
      out.ray.direction = es.wi;
      out.ray.tmax = es.distance * (1 - 1e-3f);
    });
    std::atomic<uint64_t> hits{0};
    const uint64_t chunk = 4096, chunks = (total + chunk - 1) / chunk;
    auto t0 = std::chrono::steady_clock::now();
    tbb::parallel_for(uint64_t(0), chunks, [&](uint64_t c) {
      uint64_t local_hits = 0;
      for (uint64_t i = c * chunk; i < std::min(total, (c + 1) * chunk); ++i) {
        const PoolRay& r = pool[i % pool_size];
        if (r.shadow)
          local_hits += scene->geometry->occluded(r.ray.origin, r.ray.direction, r.ray.tmax);
        else
          local_hits += scene->geometry->intersect(r.ray).mesh >= 0;
      }
      hits += local_hits;
    });
    double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::printf("{\"rays\": %llu, \"seconds\": %.4f, \"rays_per_second\": %.1f, \"hits\": %llu}\n",
                (unsigned long long)total, seconds, double(total) / seconds, (unsigned long long)hits.load());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_rays: %s\n", e.what());
    return 2;
  }
  return 0;
}
