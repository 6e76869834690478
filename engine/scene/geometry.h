#pragma once
// Embree 3 wrapper: one RTCScene of triangle meshes, closest-hit and shadow queries.
#include <embree3/rtcore.h>

#include <vector>

#include "engine/core/math.h"
#include "engine/scene/camera.h"

namespace bl {

struct Mesh;

struct Hit {
  float t = 0.f;
  int mesh = -1;  // -1: the ray escaped
  int triangle = -1;
  float b1 = 0.f, b2 = 0.f;  // barycentrics of vertices 1 and 2
};

class Geometry {
 public:
  Geometry();
  ~Geometry();
  Geometry(const Geometry&) = delete;
  Geometry& operator=(const Geometry&) = delete;

  // Builds the BVH over the meshes' world-space positions (shared, not copied: the meshes must
  // outlive the geometry and keep one float of padding after the last vertex, see Mesh).
  void build(const std::vector<Mesh>& meshes);
  Hit intersect(const Ray& ray) const;
  // intersect() for a piece of a shadow ray (a walk across null surfaces): counted as a shadow ray.
  Hit intersect_shadow(const Ray& ray) const;
  bool occluded(const Vec3f& origin, const Vec3f& direction, float tmax) const;
  // Up to kPacket coherent rays (e.g. one pixel's camera rays) traced together through Embree's
  // packet traversal, in less time than one by one. out[i] is what intersect(rays[i]) returns,
  // bitwise, except that a ray meeting an edge shared by two triangles at one distance may get
  // the other triangle (a tie broken differently: 5 in 14 M camera rays; test_determinism).
  static constexpr int kPacket = 8;
  void intersect_packet(const Ray* rays, int count, Hit* out) const;
  // Rays (closest-hit and shadow) cast so far by the calling thread; callers take differences.
  static uint64_t thread_ray_count();
  // The same count by kind: shadow rays (occlusion queries and the pieces of shadow walks) and
  // closest-hit rays traced in packets (a pixel's camera rays), the rest being single closest-hit
  // rays. bench/primal casts this mix.
  struct RayCounts {
    uint64_t all = 0, shadow = 0, packet = 0;
    RayCounts operator-(const RayCounts& o) const { return {all - o.all, shadow - o.shadow, packet - o.packet}; }
  };
  static RayCounts thread_ray_counts();

 private:
  RTCDevice device_ = nullptr;
  RTCScene scene_ = nullptr;
};

}  // namespace bl
