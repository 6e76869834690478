#pragma once
// glTF's metallic-roughness model: a linear blend, by metallic ∈ [0, 1], of the rough plastic
// (dielectric) and rough conductor of kernels/bsdf/, both reading the base colour. The glTF loader
// uses it for metallic factors strictly between 0 and 1 (the pure lobes otherwise).
// | parameter  | type           | differentiable |
// | base_color | RGB            | yes            |
// | roughness  | GGX α (scalar) | yes (sampling depends on it; it is detached) |
// | metallic   | scalar, [0, 1] | yes (lobe selection depends on it; it is detached) |
// f·cos = (1 − m) · roughplastic(albedo = base_color, α, ior 1.5) + m · roughconductor(specular =
// base_color, α). This is the glTF 2.0 specification's mix(dielectric_brdf, metal_brdf, metallic)
// with each lobe as backlight models it; ior 1.5 is glTF's dielectric (F0 = 0.04). Both lobes
// conserve energy, so their convex combination does too (the white-furnace test checks it).
// Sampling picks the conductor with probability m and the plastic otherwise; pdf is the mixture
// m · pdf_conductor + (1 − m) · pdf_plastic whichever lobe drew the direction, so eval/pdf is
// the usual unbiased one-sample estimator of a mixture.
#include "engine/core/dual.h"
#include "kernels/bsdf/bsdf.h"
#include "kernels/bsdf/roughconductor.h"
#include "kernels/bsdf/roughplastic.h"

namespace bl {

inline constexpr float kMetallicRoughnessIor = 1.5f;

template <class T>
struct MetallicRoughnessParams {
  Spectrum<T> base_color;
  T roughness;
  T metallic;
};

template <class T>
RoughPlasticParams<T> dielectric_lobe(const MetallicRoughnessParams<T>& p) {
  return {p.base_color, p.roughness, kMetallicRoughnessIor};
}
template <class T>
RoughConductorParams<T> metal_lobe(const MetallicRoughnessParams<T>& p) {
  return {p.base_color, p.roughness};
}

template <class T>
Spectrum<T> metallic_roughness_eval(const MetallicRoughnessParams<T>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return Spectrum<T>(T(0.f));
  const Spectrum<T> dielectric = roughplastic_eval(dielectric_lobe(p), wo, wi);
  const Spectrum<T> metal = roughconductor_eval(metal_lobe(p), wo, wi);
  return dielectric * (1.f - p.metallic) + metal * p.metallic;
}

inline float metallic_roughness_pdf(const MetallicRoughnessParams<float>& p, const Vec3f& wo, const Vec3f& wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return 0.f;
  const float m = std::clamp(p.metallic, 0.f, 1.f);
  float pdf = 0.f;
  if (m > 0.f) pdf += m * roughconductor_pdf(metal_lobe(p), wo, wi);
  if (m < 1.f) pdf += (1.f - m) * roughplastic_pdf(dielectric_lobe(p), wo, wi);
  return pdf;
}

// u_lobe < m picks the conductor. The chosen lobe receives u_lobe rescaled to [0, 1) within its
// own interval, so the plastic's own lobe choice (coat or base) still sees a uniform number.
inline BsdfSample metallic_roughness_sample(const MetallicRoughnessParams<float>& p, const Vec3f& wo, float u_lobe,
                                            Vec2f u) {
  if (wo.z <= 0.f) return {};
  const float m = std::clamp(p.metallic, 0.f, 1.f);
  constexpr float kBelowOne = 0x1.fffffep-1f;
  const BsdfSample lobe =
      u_lobe < m ? roughconductor_sample(metal_lobe(p), wo, std::min(u_lobe / m, kBelowOne), u)
                 : roughplastic_sample(dielectric_lobe(p), wo, std::min((u_lobe - m) / (1.f - m), kBelowOne), u);
  if (!(lobe.pdf > 0.f)) return {};
  return {lobe.wi, metallic_roughness_pdf(p, wo, lobe.wi)};
}

// Forward mode through eval itself, with 5 tangents (base colour RGB, α, metallic).
inline MetallicRoughnessParams<float> metallic_roughness_backprop(const MetallicRoughnessParams<float>& p,
                                                                  const Vec3f& wo, const Vec3f& wi,
                                                                  const Vec3f& adjoint) {
  using D = Dual<float, 5>;
  const MetallicRoughnessParams<D> pd{
      {D::variable(p.base_color.x, 0), D::variable(p.base_color.y, 1), D::variable(p.base_color.z, 2)},
      D::variable(p.roughness, 3),
      D::variable(p.metallic, 4)};
  const Spectrum<D> f = metallic_roughness_eval(pd, wo, wi);
  float g[5];
  for (int k = 0; k < 5; ++k) g[k] = adjoint.x * f.x.d[k] + adjoint.y * f.y.d[k] + adjoint.z * f.z.d[k];
  return {{g[0], g[1], g[2]}, g[3], g[4]};
}

}  // namespace bl
