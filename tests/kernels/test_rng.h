#pragma once
// Deterministic random numbers for kernel tests: a SplitMix64 stream (Steele et al. 2014). Tests
// own their randomness so that a failure reproduces from the seed printed with it, independently
// of the renderer's PathSampler (which has its own tests).
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "engine/core/math.h"
#include "engine/core/params.h"

namespace bl::test {

class TestRng {
 public:
  // The seed is mixed so that nearby seeds start far apart on the SplitMix64 cycle (otherwise
  // seeds s and s + 1 would give the same stream shifted by one).
  explicit TestRng(uint64_t seed) : state_(mix(seed ^ 0x2545f4914f6cdd1dull)) {}
  uint64_t next_u64() { return mix(state_ += 0x9e3779b97f4a7c15ull); }
  // Uniform in [0, 1), 24 random bits.
  float next_float() { return float(next_u64() >> 40) * (1.0f / 16777216.0f); }
  // Uniform in [0, 1), 53 random bits.
  double next_double() { return double(next_u64() >> 11) * (1.0 / 9007199254740992.0); }
  double uniform(double lo, double hi) { return lo + (hi - lo) * next_double(); }

  // A direction uniformly distributed over the upper hemisphere (z > 0), bounded away from the
  // horizon by cos θ ≥ min_cos.
  Vec3f upper_hemisphere(double min_cos = 1e-3) {
    const double z = uniform(min_cos, 1.0), phi = uniform(0.0, 2.0 * M_PI), r = std::sqrt(std::max(0.0, 1.0 - z * z));
    return {float(r * std::cos(phi)), float(r * std::sin(phi)), float(z)};
  }

 private:
  static uint64_t mix(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  uint64_t state_;
};

// A parameter of the given shape with values uniform in [lo, hi).
inline Param random_param(const std::string& name, std::vector<int> shape, double lo, double hi, TestRng& rng) {
  Param p;
  p.name = name;
  p.shape = std::move(shape);
  size_t size = 1;
  for (int s : p.shape) size *= size_t(s);
  for (size_t i = 0; i < size; ++i) p.value.push_back(float(rng.uniform(lo, hi)));
  return p;
}

// The direction at polar angle θ (from +z) and azimuth φ.
inline Vec3f spherical_direction(double theta, double phi) {
  return {float(std::sin(theta) * std::cos(phi)), float(std::sin(theta) * std::sin(phi)), float(std::cos(theta))};
}

}  // namespace bl::test
