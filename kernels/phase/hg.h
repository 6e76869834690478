#pragma once
// Henyey–Greenstein phase function (Henyey and Greenstein 1941).
// | parameter  | shape | range     | differentiable |
// | <medium>.g | [1]   | (−1, 1)   | yes (sampling depends on it; it is detached) |
// With μ = wi·wo (see phase.h: wi = −d_in, so μ = −cos θ for θ the angle between the
// propagation directions d_in and wo):
//   p(wi, wo) = (1 − g²) / (4π (1 + g² + 2gμ)^{3/2})
// g > 0 favours wo = d_in, i.e. forward scattering; g = 0 is isotropic, 1/(4π).
#include <algorithm>
#include <cmath>

#include "engine/core/dual.h"
#include "kernels/phase/phase.h"

namespace bl {

// |g| is kept below 1: at |g| = 1 the function is a delta and its normalisation breaks down.
inline constexpr float kHgMaxAbsG = 0.999f;

template <class T>
struct HgParams {
  T g;
};

template <class T>
T hg_clamp_g(const T& g) {
  if (g > kHgMaxAbsG) return T(kHgMaxAbsG);
  if (g < -kHgMaxAbsG) return T(-kHgMaxAbsG);
  return g;
}

// p = (1 − g²) / (4π (1 + g² + 2gμ)^1.5), μ = wi·wo. The denominator is written as a sum of
// positive terms, (1 − g)² + g|wi + wo|² for g ≥ 0 (1 + μ = |wi + wo|²/2 for unit vectors) and
// (1 + g)² − g|wi − wo|² for g < 0: 1 + g² + 2gμ cancels in float where the function peaks
// (its value there ~(1 − |g|)², against a rounding of μ near ±1 of ~6e-8), which put the value
// off by 0.6% at g = 0.99 and 55% at 0.999 on sampled directions, its derivative by 14% and 6×;
// now 2e-6 / 2e-4 and 2e-5 / 1.3e-3 (a small error in the vectors' lengths enters squared).
template <class T>
T hg_eval(const HgParams<T>& p, const Vec3f& wi, const Vec3f& wo) {
  const T g = hg_clamp_g(p.g);
  T denom;
  if (value_of(g) >= 0.f) {
    const Vec3f s = wi + wo;
    denom = (T(1.f) - g) * (T(1.f) - g) + g * dot(s, s);
  } else {
    const Vec3f d = wi - wo;
    denom = (T(1.f) + g) * (T(1.f) + g) - g * dot(d, d);
  }
  return (T(1.f) - g * g) / (4.f * kPi * denom * sqrt(denom));
}

// Exact inversion of the CDF of cos θ = d_in·wo (θ between the propagation directions):
// cos θ = (1 + g² − s²)/(2g), s = (1 − g²)/t, t = 1 − g + 2gξ. Written as products of positive
// terms, 1 − cos θ = 2(1 − g)²(1 − ξ)(1 + gξ)/t² and 1 + cos θ = 2(1 + g)²ξ(1 − g(1 − ξ))/t², with
// sin θ = sqrt((1 − cos θ)(1 + cos θ)): the textbook form cancels in float near the peak (1 − cos θ
// ~ (1 − g)², 1e-6 at g = 0.999, against a rounding of 6e-8), so at g = 0.999 the cone θ < 0.1(1 − g)
// drew 12× its share and the score E[∂g log p] was 44 instead of 0; it also divided by g, which
// cancelled for small |g|. Now 2e-5 of 1 − cos θ at 0.999 and 1e-7 at small g.
inline PhaseSample hg_sample(const HgParams<float>& p, const Vec3f& wi, Vec2f u) {
  const float g = hg_clamp_g(p.g);
  float cos_theta, sin_theta;
  if (g == 0.f) {  // the general form gives 2ξ − 1 here: the same distribution, kept for the samples it drew
    cos_theta = 1.f - 2.f * u.x;
    sin_theta = std::sqrt(std::max(0.f, 1.f - cos_theta * cos_theta));
  } else {
    const float xi = u.x;
    const float t = g > 0.f ? (1.f - g) + 2.f * g * xi : (1.f + g) - 2.f * g * (1.f - xi);  // 1 − g + 2gξ > 0
    const float one_minus = 2.f * (1.f - g) * (1.f - g) * (1.f - xi) * (1.f + g * xi) / (t * t);
    const float one_plus = 2.f * (1.f + g) * (1.f + g) * xi * (1.f - g * (1.f - xi)) / (t * t);
    cos_theta = std::clamp(one_minus < 1.f ? 1.f - one_minus : one_plus - 1.f, -1.f, 1.f);
    sin_theta = std::sqrt(std::max(0.f, one_minus * one_plus));
  }
  const float phi = 2.f * kPi * u.y;
  const Frame frame(-wi);  // around the propagation direction d_in
  const Vec3f wo = normalize(frame.to_world({sin_theta * std::cos(phi), sin_theta * std::sin(phi), cos_theta}));
  return {wo, hg_eval(p, wi, wo)};
}

inline float hg_pdf(const HgParams<float>& p, const Vec3f& wi, const Vec3f& wo) { return hg_eval(p, wi, wo); }

// adjoint · ∂p/∂g, on a forward dual through hg_eval itself. Outside (−0.999, 0.999) the clamp
// holds g fixed and the derivative is 0, as for eval.
inline HgParams<float> hg_backprop(const HgParams<float>& p, const Vec3f& wi, const Vec3f& wo, float adjoint) {
  using D = Dual<float, 1>;
  const D value = hg_eval(HgParams<D>{D::variable(p.g, 0)}, wi, wo);
  return {adjoint * value.d[0]};
}

}  // namespace bl
