#include "engine/scene/geometry.h"

#include <cstdio>
#include <stdexcept>
#include <string>

#include "engine/scene/scene.h"

namespace bl {

namespace {
// Embree reports API misuse and allocation failures through this callback. It must not throw
// (it is called from C code), so it prints; build() then turns the device's error into an exception.
void embree_error(void*, RTCError code, const char* message) {
  if (code == RTC_ERROR_NONE) return;
  std::fprintf(stderr, "backlight: Embree error %d: %s\n", int(code), message ? message : "");
}
thread_local uint64_t tls_ray_count = 0;
thread_local uint64_t tls_shadow_ray_count = 0, tls_packet_ray_count = 0;
}  // namespace

uint64_t Geometry::thread_ray_count() { return tls_ray_count; }
Geometry::RayCounts Geometry::thread_ray_counts() {
  return {tls_ray_count, tls_shadow_ray_count, tls_packet_ray_count};
}

Geometry::Geometry() {
  device_ = rtcNewDevice("verbose=0");
  if (!device_) throw std::runtime_error("cannot create an Embree device");
  rtcSetDeviceErrorFunction(device_, embree_error, nullptr);
}

Geometry::~Geometry() {
  if (scene_) rtcReleaseScene(scene_);
  if (device_) rtcReleaseDevice(device_);
}

void Geometry::build(const std::vector<Mesh>& meshes) {
  if (scene_) rtcReleaseScene(scene_);
  scene_ = rtcNewScene(device_);
  // Robust traversal avoids missed hits on shared edges of the box walls at a small cost.
  rtcSetSceneFlags(scene_, RTC_SCENE_FLAG_ROBUST);
  rtcSetSceneBuildQuality(scene_, RTC_BUILD_QUALITY_HIGH);
  for (size_t i = 0; i < meshes.size(); ++i) {
    const Mesh& m = meshes[i];
    RTCGeometry g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
    // Shared buffers: Embree reads our arrays in place (positions are padded by one element).
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, m.positions.data(), 0, sizeof(Vec3f),
                               m.vertex_count());
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, m.indices.data(), 0, 3 * sizeof(uint32_t),
                               m.triangle_count());
    rtcCommitGeometry(g);
    // geomID == index into meshes, so hits map straight back to our data.
    rtcAttachGeometryByID(scene_, g, unsigned(i));
    rtcReleaseGeometry(g);
  }
  rtcCommitScene(scene_);
  if (RTCError e = rtcGetDeviceError(device_); e != RTC_ERROR_NONE)
    throw std::runtime_error("Embree failed to build the scene (error " + std::to_string(int(e)) + ")");
}

Hit Geometry::intersect(const Ray& ray) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRayHit rh;
  rh.ray.org_x = ray.origin.x;
  rh.ray.org_y = ray.origin.y;
  rh.ray.org_z = ray.origin.z;
  rh.ray.dir_x = ray.direction.x;
  rh.ray.dir_y = ray.direction.y;
  rh.ray.dir_z = ray.direction.z;
  rh.ray.tnear = ray.tmin;
  rh.ray.tfar = ray.tmax;
  rh.ray.mask = 0xffffffffu;
  rh.ray.flags = 0;
  rh.ray.time = 0.f;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(scene_, &context, &rh);
  ++tls_ray_count;
  Hit h;
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return h;
  h.t = rh.ray.tfar;
  h.mesh = int(rh.hit.geomID);
  h.triangle = int(rh.hit.primID);
  h.b1 = rh.hit.u;
  h.b2 = rh.hit.v;
  return h;
}

Hit Geometry::intersect_shadow(const Ray& ray) const {
  ++tls_shadow_ray_count;
  return intersect(ray);
}

void Geometry::intersect_packet(const Ray* rays, int count, Hit* out) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  alignas(32) int valid[kPacket];
  alignas(32) RTCRayHit8 rh;
  for (int i = 0; i < kPacket; ++i) {
    const bool active = i < count;
    valid[i] = active ? -1 : 0;
    const Ray& r = rays[active ? i : 0];
    rh.ray.org_x[i] = r.origin.x;
    rh.ray.org_y[i] = r.origin.y;
    rh.ray.org_z[i] = r.origin.z;
    rh.ray.dir_x[i] = r.direction.x;
    rh.ray.dir_y[i] = r.direction.y;
    rh.ray.dir_z[i] = r.direction.z;
    rh.ray.tnear[i] = r.tmin;
    rh.ray.tfar[i] = r.tmax;
    rh.ray.mask[i] = 0xffffffffu;
    rh.ray.flags[i] = 0;
    rh.ray.time[i] = 0.f;
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  rtcIntersect8(valid, scene_, &context, &rh);
  tls_ray_count += uint64_t(count);
  tls_packet_ray_count += uint64_t(count);
  for (int i = 0; i < count; ++i) {
    Hit h;
    if (rh.hit.geomID[i] != RTC_INVALID_GEOMETRY_ID) {
      h.t = rh.ray.tfar[i];
      h.mesh = int(rh.hit.geomID[i]);
      h.triangle = int(rh.hit.primID[i]);
      h.b1 = rh.hit.u[i];
      h.b2 = rh.hit.v[i];
    }
    out[i] = h;
  }
}

bool Geometry::occluded(const Vec3f& o, const Vec3f& d, float tmax) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRay r;
  r.org_x = o.x;
  r.org_y = o.y;
  r.org_z = o.z;
  r.dir_x = d.x;
  r.dir_y = d.y;
  r.dir_z = d.z;
  r.tnear = 0.f;
  r.tfar = tmax;
  r.mask = 0xffffffffu;
  r.flags = 0;
  r.time = 0.f;
  rtcOccluded1(scene_, &context, &r);
  ++tls_ray_count;
  ++tls_shadow_ray_count;
  // Embree sets tfar to -inf when the ray is blocked.
  return r.tfar < 0.f;
}

}  // namespace bl
