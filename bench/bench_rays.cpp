// Raw Embree throughput for a scene's ray distribution, to put the renderer's shading overhead in
// proportion. It casts the same mix of rays the path tracer does — camera rays (traced as the
// renderer traces them, 8 jittered rays of one pixel per Embree packet), cosine-weighted bounce
// rays from surface points, and shadow rays towards points on emitters — in a bare
// intersect/occlude loop over TBB tiles, with no shading. The mix is given as the fractions of all
// rays that are shadow and camera rays (the render prints them: bench/primal passes its own).
// With --single-camera the camera rays go through Embree one by one instead (the bench's loop
// before the renderer traced them in packets).
//   bench_rays SCENE RAYS [--threads T] [--shadow-fraction S] [--camera-fraction C] [--single-camera]
//     → prints JSON {rays, seconds, rays_per_second, hits, shadow_fraction, camera_fraction}
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
    std::fprintf(stderr,
                 "usage: bench_rays SCENE RAYS [--threads T] [--shadow-fraction S] [--camera-fraction C] "
                 "[--single-camera]\n");
    return 2;
  }
  const std::string path = argv[1];
  const uint64_t total = std::strtoull(argv[2], nullptr, 10);
  int threads = 0;
  double shadow_fraction = 0.45;  // about one shadow ray per bounce ray
  double camera_fraction = -1;    // default: one camera ray per path of ~6 segments
  bool single_camera = false;
  for (int i = 3; i < argc; ++i) {
    const std::string a = argv[i];
    const bool has_value = i + 1 < argc;
    if (a == "--single-camera")
      single_camera = true;
    else if (a == "--threads" && has_value)
      threads = std::atoi(argv[++i]);
    else if (a == "--shadow-fraction" && has_value)
      shadow_fraction = std::atof(argv[++i]);
    else if (a == "--camera-fraction" && has_value)
      camera_fraction = std::atof(argv[++i]);
    else {
      std::fprintf(stderr, "bench_rays: unknown or incomplete option '%s'\n", a.c_str());
      return 2;
    }
  }
  if (total == 0) {
    std::fprintf(stderr, "bench_rays: RAYS must be a positive count\n");
    return 2;
  }
  if (camera_fraction < 0) camera_fraction = (1.0 - shadow_fraction) / 6.0;
  if (!(shadow_fraction >= 0 && camera_fraction >= 0 && shadow_fraction + camera_fraction <= 1)) {
    std::fprintf(stderr, "bench_rays: the shadow and camera fractions must be in [0, 1] with a sum of at most 1\n");
    return 2;
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
    // 1. Generate a pool of casts (untimed), 2. time a bare loop casting them until `total` rays.
    // A cast is a packet of kPacket camera rays through one pixel (probability p, chosen so that
    // camera rays are camera_fraction of all rays: kPacket·p / (kPacket·p + 1 − p) = C), else one
    // bounce or shadow ray.
    constexpr int kPacket = Geometry::kPacket;
    const double c = camera_fraction, packet_probability = c / (kPacket - (kPacket - 1) * c);
    const double shadow_given_single = c < 1 ? shadow_fraction / (1 - c) : 0;
    struct PoolCast {
      enum Kind : uint8_t { Bounce, Shadow, Camera } kind = Bounce;
      Ray ray;
      uint32_t packet = 0;  // Camera: index into `packets`
    };
    struct PoolPacket {
      Ray rays[kPacket];
    };
    const uint64_t pool_size = std::min<uint64_t>(total, 1u << 20);
    std::vector<PoolCast> pool(pool_size);
    std::vector<PoolPacket> packets;
    for (uint64_t i = 0; i < pool_size; ++i)
      if (PathSampler(7, i, 0).get(0) < float(packet_probability)) {
        pool[i].kind = PoolCast::Camera;
        pool[i].packet = uint32_t(packets.size());
        packets.emplace_back();
      }
    tbb::parallel_for(uint64_t(0), pool_size, [&](uint64_t i) {
      PathSampler s(7, i, 0);
      PoolCast& out = pool[i];
      if (out.kind == PoolCast::Camera) {  // the renderer's camera rays for samples 0..7 of a pixel
        const int x = std::min(int(s.get(1) * float(cam.width)), cam.width - 1);
        const int y = std::min(int(s.get(2) * float(cam.height)), cam.height - 1);
        const uint64_t pixel = uint64_t(y) * uint64_t(cam.width) + uint64_t(x);
        for (int k = 0; k < kPacket; ++k) {
          const PathSampler ps(7, pixel, uint64_t(k));
          packets[out.packet].rays[k] = cam.generate(float(x) + ps.get(Dim::kPixelX), float(y) + ps.get(Dim::kPixelY));
        }
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
      if (!(s.get(10) < float(shadow_given_single)) || scene->area_emitters.empty()) {
        Vec3f d = Frame(n).to_world(sample_cosine_hemisphere({s.get(6), s.get(7)}));
        out.ray.origin = offset_origin(p, n, d);
        out.ray.direction = d;
        return;
      }
      EmitterSample es = scene->sample_area_emitter(0, p, s.get_double(8), s.get_double(9));
      if (es.pdf <= 0) {
        es.wi = normalize(Vec3f(0, 1, 0) - p);
        es.distance = 1;
      }
      out.kind = PoolCast::Shadow;
      out.ray.origin = offset_origin(p, n, es.wi);
      out.ray.direction = es.wi;
      out.ray.tmax = es.distance * (1 - 1e-3f);
    });
    // Chunks of casts in order, each chunk starting where the previous ones left off; a chunk's
    // casts are known in advance by their ray counts (prefix sums over one pass of the pool).
    std::vector<uint64_t> rays_before(pool_size + 1, 0);
    for (uint64_t i = 0; i < pool_size; ++i)
      rays_before[i + 1] = rays_before[i] + (pool[i].kind == PoolCast::Camera ? kPacket : 1);
    const uint64_t pool_rays = rays_before[pool_size];
    // Casts in the run: whole passes over the pool, then a prefix of it.
    const uint64_t passes = total / pool_rays, rest = total % pool_rays;
    const uint64_t rest_casts =
        uint64_t(std::lower_bound(rays_before.begin(), rays_before.end(), rest) - rays_before.begin());
    const uint64_t casts = passes * pool_size + rest_casts;
    const uint64_t cast_rays = passes * pool_rays + rays_before[rest_casts];
    std::atomic<uint64_t> hits{0};
    const uint64_t chunk = 4096, chunks = (casts + chunk - 1) / chunk;
    auto t0 = std::chrono::steady_clock::now();
    tbb::parallel_for(uint64_t(0), chunks, [&](uint64_t ci) {
      uint64_t local_hits = 0;
      Hit packet_hits[kPacket];
      for (uint64_t i = ci * chunk; i < std::min(casts, (ci + 1) * chunk); ++i) {
        const PoolCast& r = pool[i % pool_size];
        if (r.kind == PoolCast::Shadow) {
          local_hits += scene->geometry->occluded(r.ray.origin, r.ray.direction, r.ray.tmax);
        } else if (r.kind == PoolCast::Bounce) {
          local_hits += scene->geometry->intersect(r.ray).mesh >= 0;
        } else if (single_camera) {
          for (const Ray& ray : packets[r.packet].rays) local_hits += scene->geometry->intersect(ray).mesh >= 0;
        } else {
          scene->geometry->intersect_packet(packets[r.packet].rays, kPacket, packet_hits);
          for (const Hit& h : packet_hits) local_hits += h.mesh >= 0;
        }
      }
      hits += local_hits;
    });
    double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    uint64_t shadow = 0, camera = 0;
    for (uint64_t i = 0; i < casts; ++i) {
      const PoolCast& r = pool[i % pool_size];
      shadow += r.kind == PoolCast::Shadow;
      camera += r.kind == PoolCast::Camera ? kPacket : 0;
    }
    std::printf(
        "{\"rays\": %llu, \"seconds\": %.4f, \"rays_per_second\": %.1f, \"hits\": %llu, \"shadow_fraction\": %.4f, "
        "\"camera_fraction\": %.4f, \"camera_packets\": %s}\n",
        (unsigned long long)cast_rays, seconds, double(cast_rays) / seconds, (unsigned long long)hits.load(),
        double(shadow) / double(cast_rays), double(camera) / double(cast_rays), single_camera ? "false" : "true");
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_rays: %s\n", e.what());
    return 2;
  }
  return 0;
}
