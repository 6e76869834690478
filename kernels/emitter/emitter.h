#pragma once
// Emitter contract.
// eval<T>: emitted radiance of scalar T leaving the emitter towards the viewer.
// sample: a direction (or point) with its solid-angle pdf, measured from a reference point.
// pdf: the solid-angle density of `sample` for a given direction.
// backprop: adds the adjoint (RGB) times ∂radiance/∂θ into the radiance parameter's gradient.
// The light-selection probability (uniform over emitters) is applied by the integrator.
#include "engine/core/math.h"

namespace bl {

// Where a direction reads an environment map (kernels/emitter/envmap.h): the texel (nearest
// lookup) or the cell between four samples and the position in it (bilinear).
struct EnvLookup {
  int row = 0, col = 0;
  float fx = 0.f, fy = 0.f;  // bilinear only
};

struct EmitterSample {
  Vec3f wi;              // unit direction from the reference point towards the emitter
  float distance = 0.f;  // to the sampled point; infinity for environments
  float pdf = 0.f;       // solid angle, excluding the light-selection probability
  Vec2f uv;              // where the radiance texture is read
  Vec3f point;
  int triangle = -1;         // area emitters: the sampled triangle of the emitter's mesh
  float b1 = 0.f, b2 = 0.f;  // and the point's barycentrics in it
  EnvLookup env;             // environments: where wi reads the map (eval and pdf share it)
};

}  // namespace bl
