#pragma once
// Null-collision tracking through a heterogeneous medium against block majorants (grid.h):
// delta tracking for free-flight sampling (Woodcock et al. 1965) and ratio tracking for the
// transmittance of shadow rays (Novák et al. 2014).
//
// Differentiation (DESIGN.md, "Media"): the tentative collision distances depend only on the
// majorant, a detached constant, so ratio tracking's estimate Π(1 − σ_t(x_i)/σ̄) is a smooth
// function of σ_t and its T-valued product differentiates correctly as written. Delta tracking
// *chooses* between a real and a null collision with probabilities σ_t/σ̄ and 1 − σ_t/σ̄, which
// depend on the parameters; differentiating only the returned weight would miss that. Each choice
// therefore multiplies the T-valued weight by its probability over the detached probability,
// σ_t/value_of(σ_t) or (σ̄ − σ_t)/(σ̄ − value_of(σ_t)): the value is 1, and the derivative is the
// score term of the choice (the differential delta tracking of Nimier-David et al. 2022), which
// makes the gradient unbiased for the derivative of the expectation. For float the factors are
// exactly 1 and cost nothing. The null choices' factors multiply FreeFlight::weight; the real
// choice's factor is returned apart (FreeFlight::real) for the caller to apply, so that the path
// loop can estimate part of its score term another way (medium_light_derivative in
// engine/integrators/path.h).
//
// Replay: tracking draws a variable number of random numbers. Each call gets its own
// counter-based stream (TrackingSampler), a pure function of the path's key, the vertex and a
// stream id, so a replay of the same path regenerates exactly the same draws however many there
// were, and the fixed per-vertex dimensions of engine/core/sampler.h are untouched.
#include <cmath>
#include <cstdint>

#include "engine/core/sampler.h"
#include "kernels/medium/grid.h"

namespace bl {

class TrackingSampler {
 public:
  // stream: which tracking of the vertex (0: free flight of the next segment, 1: the NEE
  // shadow ray, ...).
  TrackingSampler(uint64_t path_key, int vertex, uint32_t stream)
      : key_(mix64(path_key ^ mix64((uint64_t(uint32_t(vertex)) << 32 | stream) + 0x7472616b696e6721ull))) {}
  float next() { return bits_to_unit_float(mix64(key_ + (++counter_) * 0x9e3779b97f4a7c15ull)); }
  uint64_t draws() const { return counter_; }

 private:
  uint64_t key_;
  uint64_t counter_ = 0;
};

template <class T>
struct FreeFlight {
  bool collided = false;  // a real collision at t (else the ray left [t_min, t_max) unscattered)
  float t = 0.f;
  T weight = T(1.f);  // 1 in value; carries the score terms of the null choices
  T real = T(1.f);    // 1 in value; the score term of the real choice (when collided)
  int null_collisions = 0;
};

// Delta tracking along o + t·d (local grid coordinates; t is the caller's distance unit, the
// majorants are per unit of t). sigma_t(t) returns σ_t at the tentative point as T.
template <class T, class SigmaT>
FreeFlight<T> delta_tracking(const MajorantGrid& m, const Vec3f& o, const Vec3f& d, float t_min, float t_max,
                             SigmaT&& sigma_t, TrackingSampler& rng) {
  FreeFlight<T> out;
  traverse_majorants(m, o, d, t_min, t_max, [&](const MajorantSegment& seg) {
    if (!(seg.majorant > 0.f)) return true;
    float t = seg.t0;
    for (;;) {
      t -= std::log(1.f - rng.next()) / seg.majorant;
      if (!(t < seg.t1)) return true;  // memoryless: the next segment starts afresh
      const T sigma = sigma_t(t);
      const float sigma_value = value_of(sigma);
      if (rng.next() * seg.majorant < sigma_value) {
        out.collided = true;
        out.t = t;
        out.real = sigma / sigma_value;
        return false;
      }
      out.weight = out.weight * ((seg.majorant - sigma) / (seg.majorant - sigma_value));
      ++out.null_collisions;
    }
  });
  return out;
}

// Ratio tracking: an unbiased estimate of exp(−∫σ_t) over [t_min, t_max].
template <class T, class SigmaT>
T ratio_tracking(const MajorantGrid& m, const Vec3f& o, const Vec3f& d, float t_min, float t_max, SigmaT&& sigma_t,
                 TrackingSampler& rng) {
  T transmittance = T(1.f);
  traverse_majorants(m, o, d, t_min, t_max, [&](const MajorantSegment& seg) {
    if (!(seg.majorant > 0.f)) return true;
    float t = seg.t0;
    for (;;) {
      t -= std::log(1.f - rng.next()) / seg.majorant;
      if (!(t < seg.t1)) return true;
      transmittance = transmittance * (T(1.f) - sigma_t(t) / seg.majorant);
    }
  });
  return transmittance;
}

}  // namespace bl
