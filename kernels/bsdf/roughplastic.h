#pragma once
// Rough plastic: a Lambertian base under a GGX dielectric coat (no internal scattering).
// | parameter | type           | differentiable |
// | albedo    | RGB            | yes            |
// | roughness | GGX α (scalar) | yes (sampling depends on it; it is detached) |
// | ior       | float          | no             |
// f·cos = Fr(wo·h) D G1 G1 / (4 cos θo)  +  albedo/π · cos θi · (1 − Fr(cos θi)) (1 − Fr(cos θo)).
// Light transmitted into the base and back out loses (1 − Fr) at each crossing, so the sum never
// exceeds the incident energy; the white-furnace test checks it.
#include "engine/core/dual.h"
#include "kernels/bsdf/bsdf.h"
#include "kernels/bsdf/microfacet.h"

namespace bl {

template <class T>
struct RoughPlasticParams {
  Spectrum<T> albedo;
  T roughness;
  float ior = 1.5f;
};

template <class T>
Spectrum<T> roughplastic_eval(const RoughPlasticParams<T>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return Spectrum<T>(T(0.f));
  Vec3f h = normalize(wo + wi);
  T alpha = clamp_alpha(p.roughness);
  float coat = fresnel_dielectric(dot(wo, h), p.ior);
  T specular = ggx_distribution(h, alpha) * smith_g1(wo, alpha) * smith_g1(wi, alpha) * (coat / (4.f * wo.z));
  float transmitted = (1.f - fresnel_dielectric(wi.z, p.ior)) * (1.f - fresnel_dielectric(wo.z, p.ior));
  return p.albedo * (kInvPi * wi.z * transmitted) + Spectrum<T>(specular);
}

// Lobe choice depends on the coat's Fresnel only (never on the albedo), so albedo changes do not
// move sampling.
inline float roughplastic_specular_probability(const Vec3f& wo, float ior) {
  float f = fresnel_dielectric(wo.z, ior);
  return std::clamp(f / (f + 0.5f * (1.f - f)), 0.05f, 0.95f);
}

inline float roughplastic_pdf(const RoughPlasticParams<float>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return 0.f;
  float ps = roughplastic_specular_probability(wo, p.ior);
  return ps * ggx_reflection_pdf(wo, wi, clamp_alpha(p.roughness)) + (1.f - ps) * wi.z * kInvPi;
}

inline BsdfSample roughplastic_sample(const RoughPlasticParams<float>& p, const Vec3f& wo, float u_lobe, Vec2f u) {
  if (wo.z <= 0.f) return {};
  float ps = roughplastic_specular_probability(wo, p.ior);
  Vec3f wi = u_lobe < ps ? reflect(wo, ggx_sample_normal(clamp_alpha(p.roughness), u)) : sample_cosine_hemisphere(u);
  if (wi.z <= 0.f) return {};
  return {wi, roughplastic_pdf(p, wo, wi)};
}

// Forward mode through eval itself, with 4 tangents (albedo RGB, α).
inline RoughPlasticParams<float> roughplastic_backprop(const RoughPlasticParams<float>& p, const Vec3f& wo,
                                                       const Vec3f& wi, const Vec3f& adjoint) {
  using D = Dual<float, 4>;
  RoughPlasticParams<D> pd{{D::variable(p.albedo.x, 0), D::variable(p.albedo.y, 1), D::variable(p.albedo.z, 2)},
                           D::variable(p.roughness, 3),
                           p.ior};
  Spectrum<D> f = roughplastic_eval(pd, wo, wi);
  float g[4];
  for (int k = 0; k < 4; ++k) g[k] = adjoint.x * f.x.d[k] + adjoint.y * f.y.d[k] + adjoint.z * f.z.d[k];
  return {{g[0], g[1], g[2]}, g[3], p.ior};
}

}  // namespace bl
