#pragma once
// Interior (continuous) term of geometry gradients: how shading changes when vertices and the
// camera move, with every visibility decision held fixed (the boundary terms, boundary.h, carry
// the rest).
//
// Parameterization (Li et al. 2018, redner's): every sampled direction is a constant of
// differentiation in world space, and so is each pdf, the Russian roulette and the pixel
// position. A path vertex x_k is where the ray from x_{k−1} along its fixed direction meets the
// moving triangle it hit, so x_k slides along that ray and its barycentrics (and shading normal)
// change. A light sample keeps its barycentrics on the moving emitter triangle: its point moves
// with the emitter, and the estimate carries the area-measure factor |n_y·ω| / r² and the
// triangle's area relative to their detached values. MIS weights are differentiated (a light
// sample's point and a BSDF-sampled hit on the same emitter move differently, so detached weights
// would no longer sum to one along both motions).
//
// The derivative of one path's radiance is then a sum over its vertices of d log(factor) times
// the radiance that factor carries: the BSDF continuation from x_k carries the radiance gathered
// after it (L − L_so_far, as path replay), a light sample its own contribution, an emitter hit
// through BSDF sampling its own. Each factor depends on at most two consecutive vertices, the
// emitter triangle and the vertex normals; x_k depends on x_{k−1} through its ray's origin, so the
// derivatives are pulled back along the path once, from its end, over a per-path record of its
// vertices (O(max depth) per thread; no per-image transcript, memory flat in spp).
//
// Supported for now: diffuse surfaces (constant or bitmap albedo: a sliding point reads its
// texture at moving uvs, the bilinear lookup's slope), constant-radiance area emitters, any
// environment (a rotating camera seeing the sky: a bilinear map's direction gradient; the nearest
// lookup's jumps are refused by check_geometry_view), no media, no
// null surfaces, no vertex colours. Anything else is refused with an InputError naming what.
#include <cstdint>
#include <vector>

#include "engine/integrators/boundary.h"

namespace bl {

struct PathGeometryOptions {
  int camera = 0;
  int spp = 4;  // camera paths per pixel
  uint64_t seed = 0;
  std::vector<int> meshes;     // meshes whose vertices get gradients (empty: all)
  bool interior = true;        // the interior term
  bool boundary = true;        // the secondary-visibility boundary term (one edge sample per vertex)
  bool camera_moves = false;   // the camera's pose is differentiated: every edge moves relative to x
  float side_angle = 1e-5f;    // radians, the offset of the boundary term's side paths
  int edge_samples = 1;        // edge samples per vertex (each costs a shadow ray, and two paths if visible)
  bool edge_hierarchy = true;  // sample edges through edges::EdgeTree (false: a scan of every edge per vertex)
  // The oracle: each path's derivative from a tape of the whole path (reverse-mode AD of the same
  // log-factor templates and of the hits as functions of the previous hit) instead of the
  // closed-form pull-back; the same paths and edge samples, so the same gradient to float precision.
  bool taped = false;
  bool progress = false;  // a progress bar on stderr ("geometry", camera paths)
  // Stops the pass early when set (PassOptions::cancel); the result is then partial: discard it.
  const std::atomic<bool>* cancel = nullptr;
};

// Interior and secondary-visibility terms of dF/d(vertex positions, vertex normals, camera origin
// and rotation) for F = Σ_p ⟨adjoint_p, I_p⟩ (`adjoint` has the camera's size and 3 channels),
// from `spp` camera paths per pixel; with the primary-visibility term (boundary.h) it is the
// whole derivative. The camera fields are direct derivatives (the camera's rays move with it, the
// environment stays, so a bilinear map seen directly turns across the film: its radiance's
// direction gradient, Environment::direction_gradient); they are complete only with camera_moves.
//
// Secondary visibility: at each surface vertex x below the maximum depth, `edge_samples` points p
// on the edges that are discontinuities seen from x (edges of the meshes that get gradients, or of
// every mesh once x itself moves or an emitter does), chosen through a hierarchy over the edges
// (edges.h: subtrees whose faces all face x, or all face away, are skipped; near, long edges are
// preferred) and uniformly along the edge, ω = (p − x)/r, and one path on each side of the plane
// through x and the edge. The BSDF-sampled share of the incident radiance jumps across ω
// with directions fixed: flux [h⁻ − h⁺] n·(ṗ − ẋ)/r; the light-sampled share of an area emitter
// a side sees directly moves with the emitter: flux ±h_N (n·(ṗ − ẋ)/r − n·(ẏ − ẋ)/r_y); h = β f L
// over the arc length per unit edge length |ê × ω|/r and the edge pdf. ẋ is pulled back along the
// path like the interior term's derivatives.
GeometryGradient path_geometry_gradient(const Scene& scene, const Image& adjoint, const PathGeometryOptions& options);

// Throws the InputError path_geometry_gradient throws for a scene it does not support.
void check_interior_support(const Scene& scene);

namespace interior_detail {
// Exposed for the unit tests (central differences against these templates' own values).
// Ray o + t·d against the triangle p0 p1 p2: the hit and its (unnormalised) shading normal,
// interpolated vertex normals n[0..2] when `n` is given, else the face normal (p1−p0)×(p2−p0).
template <class S>
struct MovingHit {
  Vec3<S> x, m;
  S b1, b2;  // barycentrics of corners 1 and 2 (the uv follows them)
};
template <class S>
MovingHit<S> moving_hit(const Vec3<S>& o, const Vec3<S>& d, const Vec3<S>& p0, const Vec3<S>& p1, const Vec3<S>& p2,
                        const Vec3<S>* n) {
  const Vec3<S> e1 = p1 - p0, e2 = p2 - p0;
  const Vec3<S> pvec = cross(d, e2);
  const S inv_det = S(1.0) / dot(e1, pvec);
  const Vec3<S> tvec = o - p0;
  const S b1 = dot(tvec, pvec) * inv_det;
  const Vec3<S> qvec = cross(tvec, e1);
  const S b2 = dot(d, qvec) * inv_det;
  const S t = dot(e2, qvec) * inv_det;
  MovingHit<S> h;
  h.x = o + d * t;
  h.m = n ? n[0] * (S(1.0) - b1 - b2) + n[1] * b1 + n[2] * b2 : cross(e1, e2);
  h.b1 = b1;
  h.b2 = b2;
  return h;
}

inline constexpr double kInvPiD = 0.31830988618379067;

// Reverse-mode derivative of moving_hit: given ∂F/∂x, ∂F/∂m and (`gb`, optional) ∂F/∂(b1, b2)
// beyond what flows through m, ∂F with respect to the ray's
// origin and direction, the corners and the vertex normals (`n` as in moving_hit; `grad_n` is left
// untouched without it). With n = e1 × e2, t = n·(p0 − o)/(n·d), x − p0 = b1 e1 + b2 e2 and the dual
// basis g1 = e2 × n / |n|², g2 = n × e1 / |n|²: γ = β1 g1 + β2 g2 (β the barycentrics' adjoints),
// A = ∂F/∂x + γ, s = A·d / n·d; ∂o = A − s n, ∂d = t ∂o, ∂n = −s (x − p0), and the corners
// through e1, e2 and p0. Checked against the dual-number evaluation of moving_hit.
struct HitAdjoint {
  Vec3d origin, direction, p[3], n[3];
};
inline HitAdjoint moving_hit_adjoint(const Vec3d& o, const Vec3d& d, const Vec3d* p, const Vec3d* n, const Vec3d& gx,
                                     const Vec3d& gm, const double* gb = nullptr) {
  const Vec3d e1 = p[1] - p[0], e2 = p[2] - p[0];
  const Vec3d normal = cross(e1, e2);
  const double nn = dot(normal, normal), nd = dot(normal, d);
  const double t = dot(normal, p[0] - o) / nd;
  const Vec3d x = o + d * t;
  const Vec3d g1 = cross(e2, normal) / nn, g2 = cross(normal, e1) / nn;
  const double b1 = dot(g1, x - p[0]), b2 = dot(g2, x - p[0]);
  HitAdjoint r;
  Vec3d gn(0.0);  // ∂F/∂(e1 × e2)
  Vec3d gamma(0.0);
  if (n) {
    const double beta1 = dot(gm, n[1] - n[0]), beta2 = dot(gm, n[2] - n[0]);
    gamma = g1 * beta1 + g2 * beta2;
    r.n[0] = gm * (1.0 - b1 - b2);
    r.n[1] = gm * b1;
    r.n[2] = gm * b2;
  } else {
    gn = gm;  // flat: m = e1 × e2
  }
  if (gb) gamma += g1 * gb[0] + g2 * gb[1];
  const Vec3d A = gx + gamma;
  const double s = dot(A, d) / nd;
  r.origin = A - normal * s;
  r.direction = r.origin * t;
  gn += (x - p[0]) * (-s);
  const Vec3d ge1 = gamma * (-b1) + cross(e2, gn), ge2 = gamma * (-b2) + cross(gn, e1);
  r.p[1] = ge1;
  r.p[2] = ge2;
  r.p[0] = normal * s - gamma - ge1 - ge2;
  return r;
}

template <class S>
S power_heuristic_of(const S& a, const S& b) {
  return a * a / (a * a + b * b);
}

template <class S>
Vec3<S> unit_normal(const Vec3<S>& m, double sign) {
  return m * (S(sign) / length(m));
}

// log of the geometry in a diffuse BSDF sample's continuation: log(s·n̂·d), d fixed (s = −1 where
// a two-sided surface is seen from its back).
template <class S>
S log_continuation(const Vec3<S>& m, double sign, const Vec3d& d) {
  return log(dot(unit_normal(m, sign), Vec3<S>(d)));
}

// log of a light sample's geometry and MIS weight at x (shading normal m, sign s) towards the
// point with barycentrics (b1, b2) of the emitter triangle q[0..2]: cosine at x, |n_y·ω| / r²,
// the triangle's area, and the power heuristic against the diffuse pdf, the light pdf being
// `select` · r² / (|n_y·ω| · A) with A = exp(log_area) the emitter's total area.
template <class S>
S log_light_sample(const Vec3<S>& x, const Vec3<S>& m, double sign, const Vec3<S>* q, double b1, double b2,
                   const S& log_area, double select) {
  const Vec3<S> y = q[0] * S(1.0 - b1 - b2) + q[1] * S(b1) + q[2] * S(b2);
  const Vec3<S> v = y - x;
  const S r = length(v);
  const Vec3<S> w = v / r;
  const Vec3<S> c = cross(q[1] - q[0], q[2] - q[0]);
  const S c_len = length(c);
  const S cos_x = dot(unit_normal(m, sign), w);
  const S cos_y = abs(dot(c, w)) / c_len;
  const S p_light = S(select) * r * r / (cos_y * exp(log_area));
  const S p_bsdf = cos_x * S(kInvPiD);
  return log(cos_x) + log(cos_y) - S(2.0) * log(r) + log(c_len) + log(power_heuristic_of(p_light, p_bsdf));
}

// The same for a sample of the environment in the fixed direction w, of light pdf `p_light`.
template <class S>
S log_environment_sample(const Vec3<S>& m, double sign, const Vec3d& w, double p_light) {
  const S cos_x = dot(unit_normal(m, sign), Vec3<S>(w));
  return log(cos_x) + log(power_heuristic_of(S(p_light), cos_x * S(kInvPiD)));
}

// log of the MIS weight of an emitter hit by BSDF sampling: the ray left origin o (shading normal
// m_prev, sign s) along d and hit x on triangle p[0..2] of an emitter of total area exp(log_area).
template <class S>
S log_emitter_hit_weight(const Vec3<S>& m_prev, double sign, const Vec3d& d, const Vec3<S>& o, const Vec3<S>& x,
                         const Vec3<S>* p, const S& log_area, double select) {
  const S p_bsdf = dot(unit_normal(m_prev, sign), Vec3<S>(d)) * S(kInvPiD);
  const S r = length(x - o);
  const Vec3<S> c = cross(p[1] - p[0], p[2] - p[0]);
  const S cos_y = abs(dot(c, Vec3<S>(d))) / length(c);
  const S p_light = S(select) * r * r / (cos_y * exp(log_area));
  return log(power_heuristic_of(p_bsdf, p_light));
}

// The same for a BSDF-sampled ray that escaped to the environment (light pdf `p_light`).
template <class S>
S log_environment_hit_weight(const Vec3<S>& m_prev, double sign, const Vec3d& d, double p_light) {
  const S p_bsdf = dot(unit_normal(m_prev, sign), Vec3<S>(d)) * S(kInvPiD);
  return log(power_heuristic_of(p_bsdf, S(p_light)));
}
}  // namespace interior_detail

}  // namespace bl
