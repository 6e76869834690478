#pragma once
// Counter-based random numbers: every number is a pure function of
// (seed, pixel, sample index, dimension), so any path can be regenerated exactly — by the
// adjoint pass (path replay), on another thread, or in a test — without storing anything.
#include <cstdint>

namespace bl {

// SplitMix64 finaliser (Steele et al. 2014): a bijective 64-bit mixer with full avalanche.
inline uint64_t mix64(uint64_t z) {
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Top 24 bits → float in [0, 1): exactly representable, never 1.
inline float bits_to_unit_float(uint64_t h) { return float(h >> 40) * (1.0f / 16777216.0f); }
// Top 53 bits → double in [0, 1): the same leading 24 bits as bits_to_unit_float, 29 more.
inline double bits_to_unit_double(uint64_t h) { return double(h >> 11) * (1.0 / 9007199254740992.0); }

// The random stream of one camera path.
class PathSampler {
 public:
  PathSampler(uint64_t seed, uint64_t pixel, uint64_t sample_index)
      : key_(mix64(mix64(seed * 0x9e3779b97f4a7c15ull + pixel) ^ (sample_index + 0x632be59bd9b4e019ull))) {}
  // The dimension-th number of this path.
  float get(uint32_t dimension) const {
    return bits_to_unit_float(mix64(key_ ^ (uint64_t(dimension) * 0xd1b54a32d192ed03ull)));
  }
  // The same number to 53 bits, for choices among many bins (Distribution1D): a float's 24 bits
  // cannot tell apart bins of probability ~1e-7.
  double get_double(uint32_t dimension) const {
    return bits_to_unit_double(mix64(key_ ^ (uint64_t(dimension) * 0xd1b54a32d192ed03ull)));
  }
  uint64_t key() const { return key_; }

 private:
  uint64_t key_;
};

// Fixed dimension layout: the camera uses 0-1, and surface vertex k (1-based) owns the block
// [2 + 8(k−1), 2 + 8k). Fixed slots make the replay independent of which branches a path took.
struct Dim {
  static constexpr uint32_t kPixelX = 0, kPixelY = 1;
  static constexpr uint32_t kPerVertex = 8;
  static constexpr uint32_t kLightSelect = 0, kLightU = 1, kLightV = 2, kLobe = 3, kBsdfU = 4, kBsdfV = 5,
                            kRoulette = 6;
  static uint32_t at(int vertex, uint32_t slot) { return 2 + kPerVertex * uint32_t(vertex - 1) + slot; }
};

}  // namespace bl
