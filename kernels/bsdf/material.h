#pragma once
// A material evaluates its textures at the hit's uv into a plain BSDF value (pbrt-v4's
// Material::GetBxDF idea), once per path vertex. Its backprop runs the BSDF's derivative
// shader and applies the chain rule into the texture gradient buffers, so texture derivative code
// exists once (kernels/texture/).
//
// Vertex colours (glTF's COLOR_0) tint the base colour: the colour a BSDF reads is the texture
// times the tint interpolated at the hit (white for meshes without colours). The tint is a
// constant of differentiation, so the texture receives the BSDF's colour gradient times the tint
// (the chain rule through a product with a constant). Multiplying by 1 is exact in float and
// records nothing on the tape, so untinted meshes render and differentiate bit for bit as before.
#include <string>
#include <type_traits>

#include "kernels/bsdf/diffuse.h"
#include "kernels/bsdf/metallic_roughness.h"
#include "kernels/bsdf/roughconductor.h"
#include "kernels/bsdf/roughplastic.h"
#include "kernels/texture/texture.h"

namespace bl {

enum class BsdfType { Diffuse, RoughConductor, RoughPlastic, MetallicRoughness };

// A colour texture's value times a vertex-colour tint, per channel.
template <class T>
Spectrum<T> tinted(const Spectrum<T>& colour, const Vec3f& tint) {
  return {colour.x * tint.x, colour.y * tint.y, colour.z * tint.z};
}

// A material's textures evaluated at one surface point: a plain BSDF of scalar type T. The path
// loop builds it once per vertex and uses it for NEE, sampling and the continuation weight.
template <class T>
struct BsdfValue {
  BsdfType type = BsdfType::Diffuse;
  Spectrum<T> albedo, specular;  // albedo: diffuse, roughplastic, and metallic_roughness's base colour
  T roughness{};
  float ior = 1.5f;
  T metallic{};  // metallic_roughness only

  Spectrum<T> eval(const Vec3f& wo, const Vec3f& wi) const {
    switch (type) {
      case BsdfType::Diffuse:
        return diffuse_eval(DiffuseParams<T>{albedo}, wo, wi);
      case BsdfType::RoughConductor:
        return roughconductor_eval(RoughConductorParams<T>{specular, roughness}, wo, wi);
      case BsdfType::RoughPlastic:
        return roughplastic_eval(RoughPlasticParams<T>{albedo, roughness, ior}, wo, wi);
      case BsdfType::MetallicRoughness:
        return metallic_roughness_eval(MetallicRoughnessParams<T>{albedo, roughness, metallic}, wo, wi);
    }
    return Spectrum<T>(T(0.f));
  }
  // Sampling and pdfs are detached: they read plain float values.
  BsdfValue<float> detached() const {
    return {type, value_of(albedo), value_of(specular), value_of(roughness), ior, value_of(metallic)};
  }
  BsdfSample sample(const Vec3f& wo, float u_lobe, Vec2f u) const {
    static_assert(std::is_same_v<T, float>, "sample a detached BsdfValue");
    switch (type) {
      case BsdfType::Diffuse:
        return diffuse_sample({albedo}, wo, u_lobe, u);
      case BsdfType::RoughConductor:
        return roughconductor_sample({specular, roughness}, wo, u_lobe, u);
      case BsdfType::RoughPlastic:
        return roughplastic_sample({albedo, roughness, ior}, wo, u_lobe, u);
      case BsdfType::MetallicRoughness:
        return metallic_roughness_sample({albedo, roughness, metallic}, wo, u_lobe, u);
    }
    return {};
  }
  float pdf(const Vec3f& wo, const Vec3f& wi) const {
    static_assert(std::is_same_v<T, float>, "take pdfs of a detached BsdfValue");
    switch (type) {
      case BsdfType::Diffuse:
        return diffuse_pdf({albedo}, wo, wi);
      case BsdfType::RoughConductor:
        return roughconductor_pdf({specular, roughness}, wo, wi);
      case BsdfType::RoughPlastic:
        return roughplastic_pdf({albedo, roughness, ior}, wo, wi);
      case BsdfType::MetallicRoughness:
        return metallic_roughness_pdf({albedo, roughness, metallic}, wo, wi);
    }
    return 0.f;
  }
};

// Gradient of ⟨adjoint, eval⟩ with respect to a BsdfValue's inputs (what a BSDF's derivative
// shader returns). Sums of them are meaningful: the chain rule into textures is linear.
struct BsdfGradient {
  Vec3f albedo{0.f}, specular{0.f};
  float roughness = 0.f, metallic = 0.f;
  BsdfGradient& operator+=(const BsdfGradient& o) {
    albedo += o.albedo;
    specular += o.specular;
    roughness += o.roughness;
    metallic += o.metallic;
    return *this;
  }
};

struct Material {
  std::string name;
  BsdfType type = BsdfType::Diffuse;
  TextureSlot albedo;     // diffuse, roughplastic; metallic_roughness's base_color
  TextureSlot specular;   // roughconductor
  TextureSlot roughness;  // roughconductor, roughplastic, metallic_roughness
  TextureSlot metallic;   // metallic_roughness (scalar)
  float ior = 1.5f;
  bool two_sided = true;
  // A null material: an invisible, index-matched boundary. Rays pass straight through with
  // weight 1; it is not a path vertex (no depth, no light sample) and only switches media.
  bool is_null = false;

  // Evaluates the textures this material's BSDF reads at uv (only those); the colour (albedo,
  // specular or base colour) is tinted by the vertex colour.
  template <class T>
  BsdfValue<T> at(const ParamStore& s, Vec2f uv, const Vec3f& tint = Vec3f(1.f)) const {
    BsdfValue<T> v;
    v.type = type;
    v.ior = ior;
    if (type != BsdfType::RoughConductor) v.albedo = tinted(albedo.eval<T>(s, uv), tint);
    if (type == BsdfType::RoughConductor) v.specular = tinted(specular.eval<T>(s, uv), tint);
    if (type != BsdfType::Diffuse) v.roughness = roughness.eval_scalar<T>(s, uv);
    if (type == BsdfType::MetallicRoughness) v.metallic = metallic.eval_scalar<T>(s, uv);
    return v;
  }

  // Convenience for tests and tools: textures and BSDF in one call.
  template <class T>
  Spectrum<T> eval(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi,
                   const Vec3f& tint = Vec3f(1.f)) const {
    return at<T>(s, uv, tint).eval(wo, wi);
  }
  BsdfSample sample(const ParamStore& s, Vec2f uv, const Vec3f& wo, float u_lobe, Vec2f u) const {
    return at<float>(s, uv).sample(wo, u_lobe, u);
  }
  float pdf(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi) const {
    return at<float>(s, uv).pdf(wo, wi);
  }

  // The BSDF's derivative shader at an already evaluated value: ⟨adjoint, ∂eval/∂input⟩.
  BsdfGradient bsdf_backprop(const BsdfValue<float>& v, const Vec3f& wo, const Vec3f& wi, const Vec3f& adjoint) const {
    BsdfGradient g;
    switch (type) {
      case BsdfType::Diffuse:
        g.albedo = diffuse_backprop({v.albedo}, wo, wi, adjoint).albedo;
        break;
      case BsdfType::RoughConductor: {
        auto c = roughconductor_backprop({v.specular, v.roughness}, wo, wi, adjoint);
        g.specular = c.specular, g.roughness = c.roughness;
        break;
      }
      case BsdfType::RoughPlastic: {
        auto c = roughplastic_backprop({v.albedo, v.roughness, ior}, wo, wi, adjoint);
        g.albedo = c.albedo, g.roughness = c.roughness;
        break;
      }
      case BsdfType::MetallicRoughness: {
        auto c = metallic_roughness_backprop({v.albedo, v.roughness, v.metallic}, wo, wi, adjoint);
        g.albedo = c.base_color, g.roughness = c.roughness, g.metallic = c.metallic;
        break;
      }
    }
    return g;
  }

  // The chain rule from a BSDF gradient into the textures read at uv (with the tint `at` applied).
  void texture_backprop(const ParamStore& s, Vec2f uv, const BsdfGradient& g, GradientAccumulator& grads,
                        const Vec3f& tint = Vec3f(1.f)) const {
    if (type != BsdfType::RoughConductor) albedo.backprop(s, uv, g.albedo * tint, grads);
    if (type == BsdfType::RoughConductor) specular.backprop(s, uv, g.specular * tint, grads);
    if (type != BsdfType::Diffuse) roughness.backprop_scalar(s, uv, g.roughness, grads);
    if (type == BsdfType::MetallicRoughness) metallic.backprop_scalar(s, uv, g.metallic, grads);
  }

  // Adds ⟨adjoint, ∂eval/∂θ⟩ into the gradient of every texel/constant this material read: the
  // BSDF's derivative shader, then the chain rule into the textures.
  void backprop(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi, const Vec3f& adjoint,
                GradientAccumulator& grads, const Vec3f& tint = Vec3f(1.f)) const {
    texture_backprop(s, uv, bsdf_backprop(at<float>(s, uv, tint), wo, wi, adjoint), grads, tint);
  }

  // Whether any parameter this material reads wants a gradient (skips needless shader work).
  bool wants_grad(const GradientAccumulator& grads) const {
    switch (type) {
      case BsdfType::Diffuse:
        return grads.wants(albedo.param);
      case BsdfType::RoughConductor:
        return grads.wants(specular.param) || grads.wants(roughness.param);
      case BsdfType::RoughPlastic:
        return grads.wants(albedo.param) || grads.wants(roughness.param);
      case BsdfType::MetallicRoughness:
        return grads.wants(albedo.param) || grads.wants(roughness.param) || grads.wants(metallic.param);
    }
    return false;
  }
};

}  // namespace bl
