#pragma once
// Environment emitters: an importance-sampled latitude-longitude map, or a constant.
// | parameter            | type              | differentiable |
// | environment.radiance | [H, W, 3] or RGB  | yes            |
// | scale                | float             | no             |
// Direction d (+y up) ↔ (u, v): u = 0.5 + atan2(d.x, −d.z)/(2π), v = θ/π (θ = atan2(√(x² + z²), y)); row 0 is the
// zenith. A texel is constant over its (u, v) cell (nearest lookup), so sampling a texel with
// probability ∝ luminance · sin θ and then uniformly in its cell gives a pdf proportional to the
// emitted luminance: the sampler is exact, which the chi-square test checks.
//
// `bilinear` is Mitsuba 3's `envmap` convention (scenes read from Mitsuba XML): texel (row r,
// column c) is a sample at u' = c/W, v = r/(H−1) with u' = atan2(d.x, −d.z)/(2π) wrapped to
// [0, 1) (= u − ½), and radiance is interpolated bilinearly between the four samples around d
// (columns wrap, rows 0 and H−1 lie on the poles; H ≥ 2). Sampling picks a cell between four
// samples with probability ∝ max of their luminances · sin θ, then a point uniformly in it: the
// pdf is positive wherever the radiance is (an upper bound, not proportional like Mitsuba's
// bilinear warp, so somewhat noisier on sharp maps), and exact for the sample/pdf pair.
#include <tuple>
#include <utility>
#include <vector>

#include "engine/core/distribution.h"
#include "kernels/emitter/emitter.h"
#include "kernels/texture/texture.h"

namespace bl {

struct Environment {
  bool present = false;
  bool is_map = false;
  int param = -1;  // environment.radiance
  float scale = 1.f;
  bool bilinear = false;  // Mitsuba 3's lookup (see above)
  // An orientation (Mitsuba's to_world): the map's own frame turned by the rotation R, so a world
  // direction d reads the map at R⁻¹d = Rᵀd and a sample drawn in the map's frame goes out along R·d.
  // Identity unless rotated (a rotation: the loader refuses scale, shear and reflections).
  bool rotated = false;
  float rotation[3][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  Vec3f to_local(const Vec3f& d) const {
    if (!rotated) return d;
    return {rotation[0][0] * d.x + rotation[1][0] * d.y + rotation[2][0] * d.z,
            rotation[0][1] * d.x + rotation[1][1] * d.y + rotation[2][1] * d.z,
            rotation[0][2] * d.x + rotation[1][2] * d.y + rotation[2][2] * d.z};
  }
  Vec3f to_world(const Vec3f& d) const {
    if (!rotated) return d;
    return {rotation[0][0] * d.x + rotation[0][1] * d.y + rotation[0][2] * d.z,
            rotation[1][0] * d.x + rotation[1][1] * d.y + rotation[1][2] * d.z,
            rotation[2][0] * d.x + rotation[2][1] * d.y + rotation[2][2] * d.z};
  }
  int width = 1, height = 1;
  Distribution1D rows;               // marginal over rows
  std::vector<Distribution1D> cols;  // conditional over columns in each row

  // Rebuilds the sampling distribution from the current parameter values (detached).
  void prepare(const ParamStore& s);

  // Where dir reads the map: one direction → (u, v) conversion (two atan2) that eval, pdf
  // and backprop of the same direction can share.
  EnvLookup lookup(const Vec3f& dir) const {
    EnvLookup l;
    if (!is_map) return l;
    const Vec3f d = to_local(dir);
    std::tie(l.row, l.col) = bilinear ? cell_of(d, &l.fx, &l.fy) : texel_of(d);
    return l;
  }

  template <class T>
  Spectrum<T> eval(const ParamStore& s, const Vec3f& dir) const {
    return eval<T>(s, lookup(dir));
  }
  template <class T>
  Spectrum<T> eval(const ParamStore& s, const EnvLookup& l) const {
    const Param& p = s[param];
    if (!is_map) return constant_eval<T>(p) * scale;
    if (bilinear) {
      const Taps taps = bilinear_taps(l);
      Spectrum<T> sum(T(0.f));
      for (int k = 0; k < 4; ++k) {
        const size_t b = taps.texel[k] * 3;
        sum += Spectrum<T>{ParamLoad<T>::load(p, b), ParamLoad<T>::load(p, b + 1), ParamLoad<T>::load(p, b + 2)} *
               taps.weight[k];
      }
      return sum * scale;
    }
    const size_t base = texel_index(l) * 3;
    return Spectrum<T>{ParamLoad<T>::load(p, base), ParamLoad<T>::load(p, base + 1), ParamLoad<T>::load(p, base + 2)} *
           scale;
  }
  void backprop(const ParamStore& s, const Vec3f& dir, const Vec3f& adjoint, GradientAccumulator& grads) const {
    if (!grads.wants(param)) return;
    if (!is_map) {
      constant_backprop(s[param], param, adjoint * scale, grads);
      return;
    }
    const EnvLookup l = lookup(dir);
    if (bilinear) {
      const Taps taps = bilinear_taps(l);
      for (int k = 0; k < 4; ++k)
        for (int c = 0; c < 3; ++c)
          grads.add(param, taps.texel[k] * 3 + size_t(c), adjoint[c] * (scale * taps.weight[k]));
      return;
    }
    const size_t base = texel_index(l) * 3;
    for (int c = 0; c < 3; ++c) grads.add(param, base + size_t(c), adjoint[c] * scale);
  }
  // ∇_d ⟨adjoint, eval(d)⟩ for the bilinear lookup, in world space: how the radiance seen along d
  // changes as d turns (a rotating camera's view of the sky). The lookup reads d's direction only,
  // so the gradient is orthogonal to d. Zero for a constant environment (nothing changes) and for
  // the nearest lookup, whose changes are jumps at texel edges, not a gradient. Zero at the poles.
  Vec3d direction_gradient(const ParamStore& s, const Vec3f& dir, const Vec3d& adjoint) const;
  // u0 picks the column, u1 the row: 53-bit uniforms (PathSampler::get_double).
  EmitterSample sample(double u0, double u1) const;
  float pdf(const Vec3f& dir) const { return pdf(dir, lookup(dir)); }
  float pdf(const Vec3f& dir, const EnvLookup& l) const;  // l = lookup(dir)

  size_t texel_index(const Vec3f& dir) const { return texel_index(lookup(dir)); }
  size_t texel_index(const EnvLookup& l) const { return size_t(l.row) * size_t(width) + size_t(l.col); }
  // The bilinear lookup: four texels and their weights (summing to 1).
  struct Taps {
    size_t texel[4];
    float weight[4];
  };
  Taps bilinear_taps(const Vec3f& dir) const { return bilinear_taps(lookup(dir)); }
  Taps bilinear_taps(const EnvLookup& l) const;
  // The bilinear mode's sampling cell (row, col) around dir, and its continuous sample position;
  // dir in the map's own frame (to_local).
  std::pair<int, int> cell_of(const Vec3f& dir, float* fx = nullptr, float* fy = nullptr) const;
  std::pair<int, int> texel_of(const Vec3f& dir) const;  // (row, col) of the texel along dir (map frame)
  static Vec2f direction_to_uv(const Vec3f& d);
  static Vec3f uv_to_direction(Vec2f uv);
};

}  // namespace bl
