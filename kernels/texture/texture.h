#pragma once
// Texture contract.
// A texture slot is a handle into the ParamStore plus how to read it: a constant (shape [C]) or a
// bitmap (shape [H, W, C]). `eval<T>(store, uv)` returns an RGB value of scalar type T (a
// one-channel texture is broadcast to grey). `backprop(store, uv, adjoint, grads)` adds
// ⟨adjoint, ∂eval/∂texel⟩ into the texel gradients — the transpose of eval's linear map, which
// makes it exact for every texel (eval is linear in the texels).
#include "engine/core/math.h"
#include "engine/core/params.h"
#include "kernels/texture/bitmap.h"
#include "kernels/texture/constant.h"

namespace bl {

struct TextureSlot {
  int param = -1;
  bool bitmap = false;
  Wrap wrap = Wrap::Repeat;

  template <class T>
  Spectrum<T> eval(const ParamStore& store, Vec2f uv) const {
    const Param& p = store[param];
    return bitmap ? bitmap_eval<T>(p, wrap, uv) : constant_eval<T>(p);
  }
  // First channel only, for scalar quantities such as roughness.
  template <class T>
  T eval_scalar(const ParamStore& store, Vec2f uv) const {
    const Param& p = store[param];
    if (!bitmap) return ParamLoad<T>::load(p, 0);
    return bitmap_eval<T>(p, wrap, uv).x;
  }
  // ∂eval/∂u, ∂eval/∂v (zero for a constant).
  void uv_gradient(const ParamStore& store, Vec2f uv, Vec3f& d_du, Vec3f& d_dv) const {
    d_du = d_dv = Vec3f(0.f);
    if (bitmap) bitmap_uv_gradient(store[param], wrap, uv, d_du, d_dv);
  }
  void backprop(const ParamStore& store, Vec2f uv, const Vec3f& adjoint, GradientAccumulator& grads) const {
    if (!grads.wants(param)) return;
    const Param& p = store[param];
    if (bitmap)
      bitmap_backprop(p, param, wrap, uv, adjoint, grads);
    else
      constant_backprop(p, param, adjoint, grads);
  }
  void backprop_scalar(const ParamStore& store, Vec2f uv, float adjoint, GradientAccumulator& grads) const {
    if (!grads.wants(param)) return;
    const Param& p = store[param];
    if (p.channels() == 1) {
      backprop(store, uv, Vec3f(adjoint, 0, 0), grads);
      return;
    }
    // Scalar reads take channel 0 of a multi-channel parameter.
    if (bitmap)
      bitmap_backprop(p, param, wrap, uv, Vec3f(adjoint, 0, 0), grads, /*first_channel_only=*/true);
    else
      grads.add(param, 0, adjoint);
  }
};

}  // namespace bl
