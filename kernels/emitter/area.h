#pragma once
// Area emitter on a triangle mesh: constant-in-angle radiance on the side its normals point to.
// | parameter        | type                | differentiable |
// | <shape>.radiance | RGB or RGB texture  | yes            |
// Points are sampled uniformly by area (triangle chosen with probability ∝ area), so the
// solid-angle pdf is d² / (A cos θ_emitter).
#include <vector>

#include "engine/core/distribution.h"
#include "kernels/emitter/emitter.h"
#include "kernels/texture/texture.h"

namespace bl {

struct AreaEmitter {
  int mesh = -1;
  TextureSlot radiance;
  Distribution1D triangles;  // by area
  float total_area = 0.f;

  // Radiance towards a viewer at cosine `cos_normal_to_viewer` with the shading normal.
  template <class T>
  Spectrum<T> eval(const ParamStore& s, Vec2f uv, float cos_normal_to_viewer) const {
    if (cos_normal_to_viewer <= 0.f) return Spectrum<T>(T(0.f));
    return radiance.eval<T>(s, uv);
  }
  // Mirrors eval: no gradient where nothing is emitted (the back side).
  void backprop(const ParamStore& s, Vec2f uv, float cos_normal_to_viewer, const Vec3f& adjoint,
                GradientAccumulator& grads) const {
    if (cos_normal_to_viewer <= 0.f) return;
    radiance.backprop(s, uv, adjoint, grads);
  }
  // pdf in solid angle of hitting this emitter at distance d with cosine cos_emitter.
  float pdf(float distance, float cos_emitter) const {
    if (cos_emitter <= 0.f || total_area <= 0.f) return 0.f;
    return distance * distance / (cos_emitter * total_area);
  }
};

}  // namespace bl
