#pragma once
// Constant texture.
// | parameter     | shape | differentiable |
// | <owner>.<key> | [1] or [3] | yes        |
// A one-channel constant is broadcast to grey, so its gradient is the sum of the RGB adjoint.
#include "engine/core/math.h"
#include "engine/core/params.h"

namespace bl {

template <class T>
Spectrum<T> constant_eval(const Param& p) {
  if (p.size() == 1) {
    T v = ParamLoad<T>::load(p, 0);
    return {v, v, v};
  }
  return {ParamLoad<T>::load(p, 0), ParamLoad<T>::load(p, 1), ParamLoad<T>::load(p, 2)};
}

inline void constant_backprop(const Param& p, int handle, const Vec3f& adjoint, GradientAccumulator& grads) {
  if (p.size() == 1) {
    grads.add(handle, 0, adjoint.x + adjoint.y + adjoint.z);
    return;
  }
  for (int c = 0; c < 3; ++c) grads.add(handle, size_t(c), adjoint[c]);
}

}  // namespace bl
