#pragma once
// BSDF contract — read this once, every file in kernels/bsdf/ follows it.
//
// Frames: all directions are unit vectors in the local shading frame (normal = +z), pointing away
// from the surface. `wo` points towards the previous path vertex (the camera side), `wi` towards
// the next one (the light side). Directions are always plain floats: sampling is detached, so
// directions are constants of differentiation.
//
// eval<T>(params, wo, wi): f(wo, wi) · cos θi as RGB of scalar T — the cosine is INCLUDED. Zero
//   unless both directions are in the upper hemisphere (two-sided materials mirror the frame
//   before calling, see Material).
// sample(params, wo, u_lobe, u): a direction wi and its solid-angle pdf (pdf = 0: no sample).
//   It does not return a weight: the path loop always evaluates eval<T>/pdf, so the primal, the
//   taped mode and path replay perform exactly the same arithmetic.
// pdf(params, wo, wi): the solid-angle density of `sample`.
// backprop(params, wo, wi, adjoint): ⟨adjoint, ∂eval/∂p⟩ for every scalar input p, returned as a
//   params struct of gradients. The material applies the chain rule into texture buffers.
#include "engine/core/math.h"

namespace bl {

struct BsdfSample {
  Vec3f wi;
  float pdf = 0.f;
};

// Cosine-weighted hemisphere sample via the concentric disk map (Shirley & Chiu 1997).
inline Vec3f sample_cosine_hemisphere(Vec2f u) {
  float a = 2.f * u.x - 1.f, b = 2.f * u.y - 1.f;
  float r, phi;
  if (a == 0.f && b == 0.f) return {0.f, 0.f, 1.f};
  if (a * a > b * b) {
    r = a;
    phi = (kPi / 4.f) * (b / a);
  } else {
    r = b;
    phi = (kPi / 2.f) - (kPi / 4.f) * (a / b);
  }
  float x = r * std::cos(phi), y = r * std::sin(phi);
  return {x, y, std::sqrt(std::max(0.f, 1.f - x * x - y * y))};
}

// Exact unpolarised Fresnel reflectance of a dielectric interface (η = n_inside / n_outside),
// for light arriving from outside at cos θ = cos_i ≥ 0.
inline float fresnel_dielectric(float cos_i, float eta) {
  cos_i = std::clamp(cos_i, 0.f, 1.f);
  float sin_t2 = (1.f - cos_i * cos_i) / (eta * eta);
  if (sin_t2 >= 1.f) return 1.f;
  float cos_t = std::sqrt(1.f - sin_t2);
  float rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  float rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  return 0.5f * (rs * rs + rp * rp);
}

}  // namespace bl
