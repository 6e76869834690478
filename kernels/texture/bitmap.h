#pragma once
// Bitmap texture with bilinear filtering.
// | parameter     | shape     | differentiable |
// | <owner>.<key> | [H, W, C] | yes (every texel) |
// Texel (row i, column j) has its centre at uv = ((j + 0.5)/W, (i + 0.5)/H); row 0 is the file's
// first scanline (glTF's convention, and the neutral reference format's). A lookup blends the
// four texel centres around (u·W − 0.5, v·H − 0.5); indices wrap (repeat), clamp, or mirror
// (mirrored repeat: period 2W, the second copy reversed, as GL's MIRRORED_REPEAT and Mitsuba's
// "mirror").
#include <algorithm>
#include <cmath>

#include "engine/core/math.h"
#include "engine/core/params.h"

namespace bl {

enum class Wrap { Repeat, Clamp, Mirror };

// The four texels a lookup touches and their bilinear weights; eval and backprop share it, so the
// derivative shader is the exact transpose of the lookup.
struct BilinearFootprint {
  int rows[2], cols[2];
  float weights[2][2];  // [row][col]
  float tx, ty;         // the lookup's position within its cell (the weights' arguments)
};

inline int wrap_index(long i, int n, Wrap wrap) {
  if (i >= 0 && i < n) return int(i);  // the common case, without an integer division
  if (wrap == Wrap::Repeat) {
    long m = i % n;
    return int(m < 0 ? m + n : m);
  }
  if (wrap == Wrap::Mirror) {
    const long period = 2 * long(n);
    long m = i % period;
    if (m < 0) m += period;
    return int(m < n ? m : period - 1 - m);
  }
  return int(std::clamp(i, 0L, long(n - 1)));
}

inline BilinearFootprint bilinear_footprint(int width, int height, Wrap wrap, Vec2f uv) {
  float x = uv.x * float(width) - 0.5f, y = uv.y * float(height) - 0.5f;
  float fx = std::floor(x), fy = std::floor(y);
  float tx = x - fx, ty = y - fy;
  long ix = long(fx), iy = long(fy);
  BilinearFootprint f;
  f.cols[0] = wrap_index(ix, width, wrap);
  f.cols[1] = wrap_index(ix + 1, width, wrap);
  f.rows[0] = wrap_index(iy, height, wrap);
  f.rows[1] = wrap_index(iy + 1, height, wrap);
  f.weights[0][0] = (1 - ty) * (1 - tx);
  f.weights[0][1] = (1 - ty) * tx;
  f.weights[1][0] = ty * (1 - tx);
  f.weights[1][1] = ty * tx;
  f.tx = tx, f.ty = ty;
  return f;
}

template <class T>
Spectrum<T> bitmap_eval(const Param& p, Wrap wrap, Vec2f uv) {
  const int w = p.width(), h = p.height(), c = p.channels();
  const BilinearFootprint f = bilinear_footprint(w, h, wrap, uv);
  T out[3] = {T(0.f), T(0.f), T(0.f)};
  for (int r = 0; r < 2; ++r)
    for (int q = 0; q < 2; ++q) {
      const size_t base = (size_t(f.rows[r]) * size_t(w) + size_t(f.cols[q])) * size_t(c);
      const float weight = f.weights[r][q];
      if (weight == 0.f) continue;
      for (int k = 0; k < std::min(c, 3); ++k)
        out[k] = out[k] + ParamLoad<T>::load_weighted(p, base + size_t(k), weight);
    }
  if (c == 1) return {out[0], out[0], out[0]};
  return {out[0], out[1], out[2]};
}

// ∂eval/∂u and ∂eval/∂v at uv (RGB; one channel broadcast): the bilinear blend's slope within its
// cell, ∂x/∂u = W and ∂y/∂v = H. Where a clamped lookup repeats the border texel the slope is zero.
// The blend is continuous but its slope jumps at texel centres: derivative of the lookup, not of
// any smoother reconstruction. Used by the geometry gradients (a moving surface slides its uv).
inline void bitmap_uv_gradient(const Param& p, Wrap wrap, Vec2f uv, Vec3f& d_du, Vec3f& d_dv) {
  const int w = p.width(), h = p.height(), c = p.channels();
  const BilinearFootprint f = bilinear_footprint(w, h, wrap, uv);
  const float tx = f.tx, ty = f.ty;
  auto texel = [&](int r, int q) {
    const size_t base = (size_t(f.rows[r]) * size_t(w) + size_t(f.cols[q])) * size_t(c);
    return c == 1 ? Vec3f(p.value[base]) : Vec3f(p.value[base], p.value[base + 1], p.value[base + 2]);
  };
  const Vec3f t00 = texel(0, 0), t01 = texel(0, 1), t10 = texel(1, 0), t11 = texel(1, 1);
  d_du = ((t01 - t00) * (1 - ty) + (t11 - t10) * ty) * float(w);
  d_dv = ((t10 - t00) * (1 - tx) + (t11 - t01) * tx) * float(h);
}

inline void bitmap_backprop(const Param& p, int handle, Wrap wrap, Vec2f uv, const Vec3f& adjoint,
                            GradientAccumulator& grads, bool first_channel_only = false) {
  const int w = p.width(), h = p.height(), c = p.channels();
  const BilinearFootprint f = bilinear_footprint(w, h, wrap, uv);
  for (int r = 0; r < 2; ++r)
    for (int q = 0; q < 2; ++q) {
      const float weight = f.weights[r][q];
      if (weight == 0.f) continue;
      const size_t base = (size_t(f.rows[r]) * size_t(w) + size_t(f.cols[q])) * size_t(c);
      if (c == 1 && !first_channel_only) {
        grads.add(handle, base, weight * (adjoint.x + adjoint.y + adjoint.z));
      } else if (first_channel_only) {
        grads.add(handle, base, weight * adjoint.x);
      } else {
        for (int k = 0; k < std::min(c, 3); ++k) grads.add(handle, base + size_t(k), weight * adjoint[k]);
      }
    }
}

}  // namespace bl
