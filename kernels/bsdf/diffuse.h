#pragma once
// Lambertian diffuse BSDF, f = albedo / π.
// | parameter | type | differentiable |
// | albedo    | RGB  | yes            |
#include "kernels/bsdf/bsdf.h"

namespace bl {

template <class T>
struct DiffuseParams {
  Spectrum<T> albedo;
};

template <class T>
Spectrum<T> diffuse_eval(const DiffuseParams<T>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return Spectrum<T>(T(0.f));
  return p.albedo * (kInvPi * wi.z);
}

inline BsdfSample diffuse_sample(const DiffuseParams<float>&, const Vec3f& wo, float, Vec2f u) {
  if (wo.z <= 0.f) return {};
  Vec3f wi = sample_cosine_hemisphere(u);
  return {wi, wi.z * kInvPi};
}

inline float diffuse_pdf(const DiffuseParams<float>&, const Vec3f& wo, const Vec3f& wi) {
  return (wo.z <= 0.f || wi.z <= 0.f) ? 0.f : wi.z * kInvPi;
}

// eval is linear in the albedo: ∂eval_c/∂albedo_c = cos θi / π.
inline DiffuseParams<float> diffuse_backprop(const DiffuseParams<float>&, const Vec3f& wo, const Vec3f& wi,
                                             const Vec3f& adjoint) {
  if (wo.z <= 0.f || wi.z <= 0.f) return {Vec3f(0.f)};
  return {adjoint * (kInvPi * wi.z)};
}

}  // namespace bl
