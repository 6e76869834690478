#pragma once
// Environment emitters: an importance-sampled latitude-longitude map, or a constant.
// | parameter            | type              | differentiable |
// | environment.radiance | [H, W, 3] or RGB  | yes            |
// | scale                | float             | no             |
// Direction d (+y up) ↔ (u, v): u = 0.5 + atan2(d.x, −d.z)/(2π), v = acos(d.y)/π; row 0 is the
// zenith. A texel is constant over its (u, v) cell (nearest lookup), so sampling a texel with
// probability ∝ luminance · sin θ and then uniformly in its cell gives a pdf proportional to the
// emitted luminance: the sampler is exact, which the chi-square test checks.
#include <utility>
#include <vector>

#include "kernels/emitter/emitter.h"
#include "kernels/texture/texture.h"

namespace bl {

// Piecewise-constant 1D distribution: sample by inverting the CDF.
struct Distribution1D {
  std::vector<float> cdf;  // size n + 1, cdf[0] = 0, cdf[n] = 1
  std::vector<float> pmf;  // probability of each bin
  float total = 0.f;
  void build(const std::vector<double>& weights);
  int sample(float u, float* u_remapped) const;  // bin index; u rescaled to [0,1) within the bin
  size_t size() const { return pmf.size(); }
};

struct Environment {
  bool present = false;
  bool is_map = false;
  int param = -1;  // environment.radiance
  float scale = 1.f;
  int width = 1, height = 1;
  Distribution1D rows;               // marginal over rows
  std::vector<Distribution1D> cols;  // conditional over columns in each row

  // Rebuilds the sampling distribution from the current parameter values (detached).
  void prepare(const ParamStore& s);

  template <class T>
  Spectrum<T> eval(const ParamStore& s, const Vec3f& dir) const {
    const Param& p = s[param];
    if (!is_map) return constant_eval<T>(p) * scale;
    size_t base = texel_index(dir) * 3;
    return Spectrum<T>{ParamLoad<T>::load(p, base), ParamLoad<T>::load(p, base + 1), ParamLoad<T>::load(p, base + 2)} *
           scale;
  }
  void backprop(const ParamStore& s, const Vec3f& dir, const Vec3f& adjoint, GradientAccumulator& grads) const {
    if (!grads.wants(param)) return;
    if (!is_map) {
      constant_backprop(s[param], param, adjoint * scale, grads);
      return;
    }
    size_t base = texel_index(dir) * 3;
    for (int c = 0; c < 3; ++c) grads.add(param, base + size_t(c), adjoint[c] * scale);
  }
  EmitterSample sample(Vec2f u) const;
  float pdf(const Vec3f& dir) const;

  size_t texel_index(const Vec3f& dir) const;
  std::pair<int, int> texel_of(const Vec3f& dir) const;  // (row, col) of the texel seen along dir
  static Vec2f direction_to_uv(const Vec3f& d);
  static Vec3f uv_to_direction(Vec2f uv);
};

}  // namespace bl
