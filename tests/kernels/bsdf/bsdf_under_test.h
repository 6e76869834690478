#pragma once
// One BSDF with fixed parameters behind a common interface, so that the sampling, reciprocity and
// white-furnace tests run the same code over every BSDF of kernels/bsdf/.
#include <sstream>
#include <string>

#include "kernels/bsdf/material.h"

namespace bl::test {

enum class BsdfKind { Diffuse, RoughConductor, RoughPlastic, MetallicRoughness };

struct BsdfUnderTest {
  BsdfKind kind = BsdfKind::Diffuse;
  // albedo (diffuse, roughplastic), specular (roughconductor) or base colour (metallic_roughness)
  Vec3f color{1.f, 1.f, 1.f};
  float roughness = 0.5f;
  float ior = 1.5f;       // roughplastic (metallic_roughness's dielectric is fixed at 1.5)
  float metallic = 0.5f;  // metallic_roughness

  // The BSDF as the renderer sees it: a BsdfValue (kernels/bsdf/material.h), whose dispatch
  // over BSDF types is the one under test.
  template <class T>
  BsdfValue<T> value() const {
    const Spectrum<T> c(T(color.x), T(color.y), T(color.z));
    BsdfValue<T> v;
    v.type = kind == BsdfKind::Diffuse          ? BsdfType::Diffuse
             : kind == BsdfKind::RoughConductor ? BsdfType::RoughConductor
             : kind == BsdfKind::RoughPlastic   ? BsdfType::RoughPlastic
                                                : BsdfType::MetallicRoughness;
    (kind == BsdfKind::RoughConductor ? v.specular : v.albedo) = c;
    v.roughness = T(roughness);
    v.ior = ior;
    v.metallic = T(metallic);
    return v;
  }
  template <class T>
  Spectrum<T> eval(const Vec3f& wo, const Vec3f& wi) const {
    return value<T>().eval(wo, wi);
  }
  BsdfSample sample(const Vec3f& wo, float u_lobe, Vec2f u) const { return value<float>().sample(wo, u_lobe, u); }
  float pdf(const Vec3f& wo, const Vec3f& wi) const { return value<float>().pdf(wo, wi); }

  std::string name() const {
    switch (kind) {
      case BsdfKind::Diffuse:
        return "diffuse";
      case BsdfKind::RoughConductor:
        return "roughconductor";
      case BsdfKind::RoughPlastic:
        return "roughplastic";
      case BsdfKind::MetallicRoughness:
        return "metallic_roughness";
    }
    return "?";
  }
  // Everything needed to reproduce a failure.
  std::string describe(const Vec3f& wo) const {
    std::ostringstream o;
    o.precision(9);
    o << name() << " color (" << color.x << ", " << color.y << ", " << color.z << ")";
    if (kind != BsdfKind::Diffuse) o << " roughness " << roughness;
    if (kind == BsdfKind::RoughPlastic) o << " ior " << ior;
    if (kind == BsdfKind::MetallicRoughness) o << " metallic " << metallic;
    o << " wo (" << wo.x << ", " << wo.y << ", " << wo.z << ")";
    return o.str();
  }
};

}  // namespace bl::test
