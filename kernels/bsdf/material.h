#pragma once
// A material evaluates its textures at the hit's uv into a plain BSDF parameter struct and then
// calls the BSDF (pbrt-v4's Material::GetBxDF idea). Its backprop runs the BSDF's derivative
// shader and applies the chain rule into the texture gradient buffers, so texture derivative code
// exists once (kernels/texture/).
#include <string>

#include "kernels/bsdf/diffuse.h"
#include "kernels/bsdf/roughconductor.h"
#include "kernels/bsdf/roughplastic.h"
#include "kernels/texture/texture.h"

namespace bl {

enum class BsdfType { Diffuse, RoughConductor, RoughPlastic };

struct Material {
  std::string name;
  BsdfType type = BsdfType::Diffuse;
  TextureSlot albedo;     // diffuse, roughplastic
  TextureSlot specular;   // roughconductor
  TextureSlot roughness;  // roughconductor, roughplastic
  float ior = 1.5f;
  bool two_sided = true;

  template <class T>
  Spectrum<T> eval(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi) const {
    switch (type) {
      case BsdfType::Diffuse: return diffuse_eval(DiffuseParams<T>{albedo.eval<T>(s, uv)}, wo, wi);
      case BsdfType::RoughConductor:
        return roughconductor_eval(
            RoughConductorParams<T>{specular.eval<T>(s, uv), roughness.eval_scalar<T>(s, uv)}, wo, wi);
      case BsdfType::RoughPlastic:
        return roughplastic_eval(
            RoughPlasticParams<T>{albedo.eval<T>(s, uv), roughness.eval_scalar<T>(s, uv), ior}, wo, wi);
    }
    return Spectrum<T>(T(0.f));
  }

  BsdfSample sample(const ParamStore& s, Vec2f uv, const Vec3f& wo, float u_lobe, Vec2f u) const {
    switch (type) {
      case BsdfType::Diffuse: return diffuse_sample({}, wo, u_lobe, u);
      case BsdfType::RoughConductor: return roughconductor_sample(conductor_params(s, uv), wo, u_lobe, u);
      case BsdfType::RoughPlastic: return roughplastic_sample(plastic_params(s, uv), wo, u_lobe, u);
    }
    return {};
  }

  float pdf(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi) const {
    switch (type) {
      case BsdfType::Diffuse: return diffuse_pdf({}, wo, wi);
      case BsdfType::RoughConductor: return roughconductor_pdf(conductor_params(s, uv), wo, wi);
      case BsdfType::RoughPlastic: return roughplastic_pdf(plastic_params(s, uv), wo, wi);
    }
    return 0.f;
  }

  // Adds ⟨adjoint, ∂eval/∂θ⟩ into the gradient of every texel/constant this material read.
  void backprop(const ParamStore& s, Vec2f uv, const Vec3f& wo, const Vec3f& wi, const Vec3f& adjoint,
                GradientAccumulator& grads) const {
    switch (type) {
      case BsdfType::Diffuse: {
        auto g = diffuse_backprop({albedo.eval<float>(s, uv)}, wo, wi, adjoint);
        albedo.backprop(s, uv, g.albedo, grads);
        break;
      }
      case BsdfType::RoughConductor: {
        auto g = roughconductor_backprop(conductor_params(s, uv), wo, wi, adjoint);
        specular.backprop(s, uv, g.specular, grads);
        roughness_backprop(s, uv, g.roughness, grads);
        break;
      }
      case BsdfType::RoughPlastic: {
        auto g = roughplastic_backprop(plastic_params(s, uv), wo, wi, adjoint);
        albedo.backprop(s, uv, g.albedo, grads);
        roughness_backprop(s, uv, g.roughness, grads);
        break;
      }
    }
  }

  // Whether any parameter this material reads wants a gradient (skips needless shader work).
  bool wants_grad(const GradientAccumulator& grads) const {
    switch (type) {
      case BsdfType::Diffuse: return grads.wants(albedo.param);
      case BsdfType::RoughConductor: return grads.wants(specular.param) || grads.wants(roughness.param);
      case BsdfType::RoughPlastic: return grads.wants(albedo.param) || grads.wants(roughness.param);
    }
    return false;
  }

 private:
  RoughConductorParams<float> conductor_params(const ParamStore& s, Vec2f uv) const {
    return {specular.eval<float>(s, uv), roughness.eval_scalar<float>(s, uv)};
  }
  RoughPlasticParams<float> plastic_params(const ParamStore& s, Vec2f uv) const {
    return {albedo.eval<float>(s, uv), roughness.eval_scalar<float>(s, uv), ior};
  }
  // Below the α clamp the BSDF does not depend on the parameter (its derivative is 0, which
  // forward mode through clamp_alpha already yields).
  void roughness_backprop(const ParamStore& s, Vec2f uv, float g, GradientAccumulator& grads) const {
    roughness.backprop_scalar(s, uv, g, grads);
  }
};

}  // namespace bl
