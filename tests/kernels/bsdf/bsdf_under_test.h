#pragma once
// One BSDF with fixed parameters behind a common interface, so that the sampling, reciprocity and
// white-furnace tests run the same code over every BSDF of kernels/bsdf/.
#include <sstream>
#include <string>

#include "kernels/bsdf/diffuse.h"
#include "kernels/bsdf/roughconductor.h"
#include "kernels/bsdf/roughplastic.h"

namespace bl::test {

enum class BsdfKind { Diffuse, RoughConductor, RoughPlastic };

struct BsdfUnderTest {
  BsdfKind kind = BsdfKind::Diffuse;
  Vec3f color{1.f, 1.f, 1.f};  // albedo (diffuse, roughplastic) or specular (roughconductor)
  float roughness = 0.5f;
  float ior = 1.5f;

  template <class T>
  Spectrum<T> eval(const Vec3f& wo, const Vec3f& wi) const {
    const Spectrum<T> c(T(color.x), T(color.y), T(color.z));
    switch (kind) {
      case BsdfKind::Diffuse:
        return diffuse_eval(DiffuseParams<T>{c}, wo, wi);
      case BsdfKind::RoughConductor:
        return roughconductor_eval(RoughConductorParams<T>{c, T(roughness)}, wo, wi);
      case BsdfKind::RoughPlastic:
        return roughplastic_eval(RoughPlasticParams<T>{c, T(roughness), ior}, wo, wi);
    }
    return Spectrum<T>(T(0.f));
  }
  BsdfSample sample(const Vec3f& wo, float u_lobe, Vec2f u) const {
    switch (kind) {
      case BsdfKind::Diffuse:
        return diffuse_sample({color}, wo, u_lobe, u);
      case BsdfKind::RoughConductor:
        return roughconductor_sample({color, roughness}, wo, u_lobe, u);
      case BsdfKind::RoughPlastic:
        return roughplastic_sample({color, roughness, ior}, wo, u_lobe, u);
    }
    return {};
  }
  float pdf(const Vec3f& wo, const Vec3f& wi) const {
    switch (kind) {
      case BsdfKind::Diffuse:
        return diffuse_pdf({color}, wo, wi);
      case BsdfKind::RoughConductor:
        return roughconductor_pdf({color, roughness}, wo, wi);
      case BsdfKind::RoughPlastic:
        return roughplastic_pdf({color, roughness, ior}, wo, wi);
    }
    return 0.f;
  }

  std::string name() const {
    switch (kind) {
      case BsdfKind::Diffuse:
        return "diffuse";
      case BsdfKind::RoughConductor:
        return "roughconductor";
      case BsdfKind::RoughPlastic:
        return "roughplastic";
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
    o << " wo (" << wo.x << ", " << wo.y << ", " << wo.z << ")";
    return o.str();
  }
};

}  // namespace bl::test
