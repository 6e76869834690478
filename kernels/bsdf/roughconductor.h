#pragma once
// Rough conductor: GGX microfacet reflection with Schlick's Fresnel.
// | parameter | type           | differentiable |
// | specular  | RGB, F(0°)     | yes            |
// | roughness | GGX α (scalar) | yes (sampling depends on it; it is detached) |
// f = F(wo·h) D(h) G1(wo) G1(wi) / (4 cos θo cos θi), F = s + (1 − s)(1 − wo·h)⁵.
#include "engine/core/dual.h"
#include "kernels/bsdf/bsdf.h"
#include "kernels/bsdf/microfacet.h"

namespace bl {

template <class T>
struct RoughConductorParams {
  Spectrum<T> specular;
  T roughness;
};

template <class T>
Spectrum<T> roughconductor_eval(const RoughConductorParams<T>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return Spectrum<T>(T(0.f));
  Vec3f h = normalize(wo + wi);
  float wo_h = std::max(0.f, dot(wo, h));
  float schlick = std::pow(1.f - wo_h, 5.f);
  Spectrum<T> fresnel = p.specular + (Spectrum<T>(T(1.f)) - p.specular) * schlick;
  T alpha = clamp_alpha(p.roughness);
  T dg = ggx_distribution(h, alpha) * smith_g1(wo, alpha) * smith_g1(wi, alpha) / (4.f * wo.z);
  return fresnel * dg;
}

inline BsdfSample roughconductor_sample(const RoughConductorParams<float>& p, const Vec3f& wo, float, Vec2f u) {
  if (wo.z <= 0.f) return {};
  float alpha = clamp_alpha(p.roughness);
  Vec3f wi = reflect(wo, ggx_sample_normal(alpha, u));
  if (wi.z <= 0.f) return {};
  return {wi, ggx_reflection_pdf(wo, wi, alpha)};
}

inline float roughconductor_pdf(const RoughConductorParams<float>& p, const Vec3f& wo, const Vec3f& wi) {
  return ggx_reflection_pdf(wo, wi, clamp_alpha(p.roughness));
}

// Forward mode through eval itself, with 4 tangents (specular RGB, α).
inline RoughConductorParams<float> roughconductor_backprop(const RoughConductorParams<float>& p, const Vec3f& wo,
                                                           const Vec3f& wi, const Vec3f& adjoint) {
  using D = Dual<float, 4>;
  RoughConductorParams<D> pd{{D::variable(p.specular.x, 0), D::variable(p.specular.y, 1), D::variable(p.specular.z, 2)},
                             D::variable(p.roughness, 3)};
  Spectrum<D> f = roughconductor_eval(pd, wo, wi);
  float g[4];
  for (int k = 0; k < 4; ++k) g[k] = adjoint.x * f.x.d[k] + adjoint.y * f.y.d[k] + adjoint.z * f.z.d[k];
  return {{g[0], g[1], g[2]}, g[3]};
}

}  // namespace bl
