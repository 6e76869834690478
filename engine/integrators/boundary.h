#pragma once
// Boundary (visibility) terms of geometry gradients, by edge sampling (Li et al. 2018).
//
// When a mesh vertex moves, the image changes in two ways: the shading of the points it covers
// changes (the interior term) and its silhouettes move across the film, where the integrand
// jumps (the boundary term). For a functional F = Σ_p a_p · I_p of a box-filtered image
// (I_p = the mean of L over pixel p, unit pixel area), the boundary term of primary visibility is
//
//   dF/dθ |_boundary = ∫_edges a(x) · ⟨L(x⁻) − L(x⁺)⟩ · (∂x/∂θ · n) dl,
//
// an integral over the edges' projections on the film: n is either unit normal of the projected
// edge, x^± = x ± ε·n its two sides, a(x) the adjoint of the pixel holding x, and ⟨·,·⟩ the dot
// product over RGB. (Moving the edge by δ along n makes a strip of width δ that showed L(x⁺)
// show L(x⁻).) Where something in front hides the edge, both sides see it and the term is 0.
//
// Candidate edges, per mesh, after welding vertices at equal positions (a cube's split vertices
// share its edges): boundary edges (one face), silhouettes seen from the camera (one face front-,
// the other back-facing) and shading creases (two faces whose normals differ and whose shading
// is discontinuous across the edge: flat shading or split vertex normals). Null surfaces have no
// edges. An edge crossing the camera's near plane is clipped to it (the clipped end slides along
// the edge as either vertex moves); one wholly behind it is not seen.
//
// Sampling: an edge in proportion to the length of its projection clipped to the film, then a
// point uniformly along it; L(x^±) is one primal path each (the same random numbers on both sides).
// A sample's contribution goes to the edge's two endpoints, (1 − s) and s of it at the point's
// parameter s, through the projection's Jacobian; a welded edge splits it evenly between the
// faces' copies of its vertices (right for motions that keep the copies together).
//
// Discontinuities inside faces are not edges and are missed: a one-sided emitter or BSDF decides
// its side with the interpolated shading normal, which near a smooth mesh's silhouette turns away
// from the camera in a band; the band's inner border moves with the mesh (a smooth-shaded
// emitting sphere of 48 segments: a fifth of the derivative; flat shading has no such band).
//
// Not here yet (issue 9): the interior term, an edge hierarchy for the secondary term, and
// parameters in grad/optimize. This is exact for what it covers: e.g. a shape emitting constant
// radiance seen directly.
#include <cstdint>
#include <vector>

#include "engine/io/image_io.h"
#include "engine/scene/scene.h"

namespace bl {

// The derivative of F with respect to every vertex position of every mesh (world space):
// gradients[mesh][vertex]. Meshes whose gradient is not wanted may be left out with `meshes`
// (indices; empty = all).
struct BoundaryGradient {
  std::vector<int> meshes;  // which mesh each entry of `vertices` is
  std::vector<std::vector<Vec3d>> vertices;
  uint64_t samples = 0;
  double edge_length = 0;  // total projected length of the candidate edges on the film (pixels)
  int edges = 0;           // candidate edges
};

struct BoundaryOptions {
  int camera = 0;
  uint64_t samples = 0;  // edge samples (0: one per pixel)
  uint64_t seed = 0;
  std::vector<int> meshes;    // meshes whose vertices get gradients (empty: all)
  float side_offset = 1e-3f;  // ε in pixels
};

// Primary-visibility boundary term of dF/d(vertex positions) for F = Σ_p ⟨adjoint_p, I_p⟩
// (`adjoint` has the camera's size and 3 channels).
BoundaryGradient primary_boundary_gradient(const Scene& scene, const Image& adjoint, const BoundaryOptions& options);

// Secondary-visibility boundary term: the derivative of what surface points see. Camera paths
// (`spp` per pixel, BSDF-sampled, max depth as the scene's, no roulette) stop at each surface
// vertex x; one point p on the candidate edges seen from x (uniform in 3D edge length over the
// edges of `meshes`: a linear scan per vertex, no hierarchy yet) gives the direction ω = (p − x)/r
// across which the incident radiance jumps; one path on each side (offset by ±`side_angle` along
// the normal n of the plane through x and the edge) estimates L(ω⁻) − L(ω⁺), and
//   dF += ⟨a, β f(ω) (L(ω⁻) − L(ω⁺))⟩ · (n·ṗ / r) · (|ê × ω| / r) / pdf(p),
// with β the path throughput to x, f the BSDF (cosine included), |ê × ω| / r the arc length on
// the sphere of directions per unit edge length. Covers shadows and anything else seen from a
// surface point (occluders, moving lights' outlines); exact where visibility is the whole
// derivative (black occluders and constant emitters moving, scattering surfaces still). Scenes
// with media or null surfaces are refused (InputError).
struct SecondaryOptions {
  int camera = 0;
  int spp = 4;  // camera paths per pixel
  uint64_t seed = 0;
  std::vector<int> meshes;   // as BoundaryOptions::meshes
  float side_angle = 1e-5f;  // radians
};
BoundaryGradient secondary_boundary_gradient(const Scene& scene, const Image& adjoint, const SecondaryOptions& options);

// Chain rule from vertex gradients into a rigid pose about `pivot`: positions p = pivot + t +
// R(r) · (s ⊙ (p₀ − pivot)) at t = 0, r = 0 (axis-angle), s = 1.
struct PoseGradient {
  Vec3d translate, rotate, scale;
};
PoseGradient pose_gradient(const Mesh& mesh, const std::vector<Vec3d>& vertex_gradient, const Vec3f& pivot);

// Chain rule into a rigid motion of the camera (its frame moves with it): translating it by δ or
// rotating it by ω (axis-angle, world axes, about its origin) moves every point relative to it by
// −δ or −ω × (p − origin). `g` must hold every mesh (BoundaryOptions::meshes empty).
struct CameraPoseGradient {
  Vec3d origin, rotate;
};
CameraPoseGradient camera_pose_gradient(const Scene& scene, const BoundaryGradient& g, const Camera& cam);

}  // namespace bl
