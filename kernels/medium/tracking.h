#pragma once
// Null-collision tracking through a medium against its majorants (block majorants of a grid,
// grid.h, or one constant): delta tracking for free-flight sampling (Woodcock et al. 1965) and
// ratio tracking for the transmittance of shadow rays (Novák et al. 2014). The tracking loops are
// medium_free_flight and medium_transmittance (medium.h); this header holds what they share, the
// free flight's result and the tracking's random numbers.
//
// Differentiation (DESIGN.md, "Media"): the tentative collision distances depend only on the
// majorant, a detached constant, so medium_transmittance's estimate Π(1 − σ_t(x_i)/σ̄) is a smooth
// function of σ_t and its T-valued product differentiates correctly as written. medium_free_flight
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
#include <cstdint>

#include "engine/core/sampler.h"

namespace bl {

class TrackingSampler {
 public:
  // stream: which tracking of the vertex (0: free flight of the next segment, 1: the NEE
  // shadow ray, ...).
  TrackingSampler(uint64_t path_key, int vertex, uint32_t stream)
      : key_(mix64(path_key ^ mix64((uint64_t(uint32_t(vertex)) << 32 | stream) + 0x7472616b696e6721ull))) {}
  float next() { return bits_to_unit_float(mix64(key_ + (++counter_) * 0x9e3779b97f4a7c15ull)); }
  // The next number to 53 bits (a light sample's choice of triangle or texel: Distribution1D).
  double next_double() { return bits_to_unit_double(mix64(key_ + (++counter_) * 0x9e3779b97f4a7c15ull)); }
  uint64_t draws() const { return counter_; }

 private:
  uint64_t key_;
  uint64_t counter_ = 0;
};

template <class T>
struct FreeFlight {
  bool collided = false;  // a real collision at t (else the ray left [0, t_max) unscattered)
  float t = 0.f;
  T weight = T(1.f);  // 1 in value; carries the score terms of the null choices
  T real = T(1.f);    // 1 in value; the score term of the real choice (when collided)
  int null_collisions = 0;
};

}  // namespace bl
