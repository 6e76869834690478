#pragma once
// Phase function contract (the medium analogue of kernels/bsdf/bsdf.h).
//
// Directions follow Mitsuba 3 (../shared/reference/mitsuba3-volume/README.md): at a medium vertex
// `wi = −d_in` points back along the path (d_in: the direction the path was travelling) and `wo`
// points away from the vertex (towards the light in next-event estimation, or the sampled next
// direction). Both are unit world-space vectors; there is no shading frame.
//  - eval(params, wi, wo): the phase function value p(wi, wo), a density over wo that integrates
//    to 1 over the sphere (no cosine: media have no surface). Reciprocal: p(wi, wo) = p(wo, wi).
//  - sample(params, wi, u): wo and its pdf; phase sampling here is exact (pdf = eval), so the
//    path weight p/pdf is 1 and only MIS needs the pdf.
//  - pdf(params, wi, wo) = eval for exact samplers.
//  - backprop(params, wi, wo, adjoint): adjoint · ∂eval/∂θ for each differentiable input θ,
//    computed by running eval on forward duals (one source of truth, DESIGN.md property 2).
#include "engine/core/math.h"

namespace bl {

struct PhaseSample {
  Vec3f wo;
  float pdf = 0.f;  // 0: no sample
};

}  // namespace bl
