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
// The interior and secondary-visibility terms are in interior.h. This is exact for what it covers:
// e.g. a shape emitting constant radiance seen directly.
#include <atomic>
#include <cstdint>
#include <vector>

#include "engine/io/image_io.h"
#include "engine/scene/scene.h"

namespace bl {

// The derivative of F with respect to every vertex position of every mesh (world space):
// gradients[mesh][vertex]. Meshes whose gradient is not wanted may be left out with `meshes`
// (indices; empty = all). The interior term (interior.h) also differentiates with respect to the
// meshes' stored vertex normals (a rigid pose rotates them) and the camera ray's origin and
// direction; the boundary terms leave those zero.
struct GeometryGradient {
  std::vector<int> meshes;  // which mesh each entry of `vertices` is
  std::vector<std::vector<Vec3d>> vertices;
  std::vector<std::vector<Vec3d>> normals;       // like `vertices` for meshes with vertex normals, else empty
  Vec3d camera_origin{0.0}, camera_rotate{0.0};  // interior term only (axis-angle about the origin)
  uint64_t samples = 0;
  double edge_length = 0;  // total projected length of the candidate edges on the film (pixels)
  int edges = 0;           // candidate edges
};

// Checks the adjoint image against the camera (an InputError naming `what` and both sizes) and
// sets up zero gradients for `meshes` (all when empty), with vertex-normal buffers when `normals`.
GeometryGradient empty_geometry_gradient(const Scene& scene, const Camera& cam, const Image& adjoint,
                                         std::vector<int> meshes, const char* what, bool normals = false);

struct BoundaryOptions {
  int camera = 0;
  uint64_t samples = 0;  // edge samples (0: one per pixel)
  uint64_t seed = 0;
  std::vector<int> meshes;    // meshes whose vertices get gradients (empty: all)
  float side_offset = 1e-3f;  // ε in pixels
  bool progress = false;      // a progress bar on stderr ("boundary", edge samples)
  // Stops the pass early when set (PassOptions::cancel); the result is then partial: discard it.
  const std::atomic<bool>* cancel = nullptr;
};

// Liang–Barsky: the parameter range [t0, t1] of a + t·(b − a), t ∈ [0, 1], inside [0, w]×[0, h];
// false when the segment misses the rectangle.
bool clip_to_film(double ax, double ay, double bx, double by, double w, double h, double* t0, double* t1);

// Primary-visibility boundary term of dF/d(vertex positions) for F = Σ_p ⟨adjoint_p, I_p⟩
// (`adjoint` has the camera's size and 3 channels).
GeometryGradient primary_boundary_gradient(const Scene& scene, const Image& adjoint, const BoundaryOptions& options);

// The secondary-visibility term is computed with the interior term, on the same camera paths:
// path_geometry_gradient (interior.h).

// Chain rule from vertex gradients into a rigid pose about `pivot`: positions p = pivot + t +
// R(r) · (s ⊙ (p₀ − pivot)) at t = 0, r = 0 (axis-angle), s = 1.
struct PoseGradient {
  Vec3d translate, rotate, scale;
};
PoseGradient pose_gradient(const Mesh& mesh, const std::vector<Vec3d>& vertex_gradient, const Vec3f& pivot);
// The same with the gradient of the mesh's vertex normals (`normal_gradient`, empty for none),
// which turn with the rotation and follow the inverse transpose of the scale (renormalised).
PoseGradient pose_gradient(const Mesh& mesh, const std::vector<Vec3d>& vertex_gradient,
                           const std::vector<Vec3d>& normal_gradient, const Vec3f& pivot);
// Element-wise sum of two gradients over the same meshes (e.g. interior + boundary terms).
GeometryGradient& operator+=(GeometryGradient& a, const GeometryGradient& b);

// Chain rule into a rigid motion of the camera (its frame moves with it): translating it by δ or
// rotating it by ω (axis-angle, world axes, about its origin) moves every point relative to it by
// −δ or −ω × (p − origin). `g` must hold every mesh (BoundaryOptions::meshes empty).
struct CameraPoseGradient {
  Vec3d origin, rotate;
};
CameraPoseGradient camera_pose_gradient(const Scene& scene, const GeometryGradient& g, const Camera& cam);

}  // namespace bl
