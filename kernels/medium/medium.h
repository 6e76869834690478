#pragma once
// A participating medium: extinction σ_t = scale · density(x), single-scattering albedo, and a
// Henyey–Greenstein phase function (g = 0: isotropic).
// | parameter        | shape                 | range   | differentiable |
// | <medium>.density | [Z, Y, X, 1] or [1]   | ≥ 0     | yes            |
// | <medium>.albedo  | [Z, Y, X, 3] or [3]   | [0, 1]  | yes            |
// | <medium>.scale   | [1]                   | ≥ 0     | yes            |
// | <medium>.g       | [1]                   | (−1, 1) | yes            |
// A `grid` medium exists only inside its box: the grid fills the unit cube of local coordinates,
// local = (world − bbox_min) / (bbox_max − bbox_min) (conventions of grid.h, Mitsuba 3's
// gridvolume with a scale-and-translate to_world). A `homogeneous` medium has a [1] density and
// fills whatever shapes name it as their interior (no box). σ_s = albedo · σ_t, σ_a = (1 −
// albedo) · σ_t per channel; σ_t is grey (the same in R, G, B).
//
// Tracking uses the detached majorants built by `prepare` (block maxima of the density × scale ×
// headroom): sampling decisions only, never differentiated (tracking.h). The headroom (> 1) keeps
// the null-collision probability positive everywhere, which the null-collision score terms of
// the gradient need (with σ̄ = σ_t on a plateau of maxima, null collisions never happen there and
// the derivative of the transmittance would be lost); `prepare` must run again after parameter
// updates (the optimizer refreshes it after each step).
#include <cmath>
#include <limits>
#include <string>
#include <type_traits>

#include "engine/core/params.h"
#include "kernels/medium/grid.h"
#include "kernels/medium/tracking.h"
#include "kernels/phase/hg.h"

namespace bl {

struct Medium {
  std::string name;
  bool grid = false;                                  // false: homogeneous
  int density = -1, albedo = -1, scale = -1, g = -1;  // parameter handles
  Vec3f bbox_min{0.f, 0.f, 0.f}, bbox_max{1.f, 1.f, 1.f};
  float headroom = 1.25f;
  // Derivative-only light samples at tentative collisions (engine/integrators/path.h,
  // medium_light_derivative), f: where σ_t < f·σ̄, a fraction f of them takes one; 0 = off.
  float light_derivatives = 0.f;
  bool light_derivative_at(float sigma, float majorant) const { return sigma < light_derivatives * majorant; }
  int block = 8;  // voxels per majorant block and axis

  // Derived by prepare().
  Vec3f inv_extent{1.f, 1.f, 1.f};
  MajorantGrid majorants;  // per unit of world distance (σ_t bounds)
  float homogeneous_majorant = 0.f;

  void prepare(const ParamStore& params) {
    const float s = params[scale].value[0];
    if (grid) {
      const Vec3f extent = bbox_max - bbox_min;
      inv_extent = {1.f / extent.x, 1.f / extent.y, 1.f / extent.z};
      majorants = build_majorants(params[density], block, headroom);
      for (float& v : majorants.value) v *= s;
    } else {
      homogeneous_majorant = params[density].value[0] * s * headroom;
    }
  }

  Vec3f to_local(const Vec3f& world) const { return grid ? (world - bbox_min) * inv_extent : Vec3f{0.5f, 0.5f, 0.5f}; }

  // The pieces of o + t·d (world units, d unit length), t in [0, t_max), with their majorants.
  template <class Visit>
  void segments(const Vec3f& o, const Vec3f& d, float t_max, Visit&& visit) const {
    if (grid) {
      traverse_majorants(majorants, to_local(o), d * inv_extent, 0.f, t_max, visit);
    } else if (t_max > 0.f) {
      visit(MajorantSegment{0.f, t_max, homogeneous_majorant});
    }
  }

  TrilinearFootprint footprint(const ParamStore& params, const Vec3f& world) const {
    return trilinear_footprint(grid_size(params[density]), to_local(world));
  }

  template <class T>
  T sigma_t(const ParamStore& params, const Vec3f& world) const {
    const Param& dp = params[density];
    const T rho = grid ? grid_eval<T>(dp, footprint(params, world), 0) : ParamLoad<T>::load(dp, 0);
    return ParamLoad<T>::load(params[scale], 0) * rho;
  }

  // σ_t in float along one ray (tracking): the density grid's reader and the scale, read once.
  // The same value as sigma_t<float>, bitwise.
  class SigmaReader {
   public:
    SigmaReader(const Medium& m, const ParamStore& params)
        : m_(m),
          density_(params[m.density], 0),
          scale_(params[m.scale].value[0]),
          constant_(m.grid ? 0.f : params[m.density].value[0]) {}
    float operator()(const Vec3f& world) const { return scale_ * (m_.grid ? density_(m_.to_local(world)) : constant_); }

   private:
    const Medium& m_;
    GridReader density_;
    float scale_, constant_;
  };

  template <class T>
  Spectrum<T> albedo_at(const ParamStore& params, const Vec3f& world) const {
    const Param& ap = params[albedo];
    if (ap.shape.size() == 4) return grid_eval_rgb<T>(ap, trilinear_footprint(grid_size(ap), to_local(world)));
    return {ParamLoad<T>::load(ap, 0), ParamLoad<T>::load(ap, 1), ParamLoad<T>::load(ap, 2)};
  }

  template <class T>
  HgParams<T> phase(const ParamStore& params) const {
    return {g >= 0 ? ParamLoad<T>::load(params[g], 0) : T(0.f)};
  }

  // Derivative shaders: adjoint · ∂(quantity at x)/∂θ into every parameter the value read.
  // Whether σ_t reads a parameter that wants a gradient (the density or the scale).
  bool wants_sigma_grad(const ParamStore& params) const {
    return (density >= 0 && params[density].requires_grad) || (scale >= 0 && params[scale].requires_grad);
  }
  void backprop_sigma_t(const ParamStore& params, const Vec3f& world, float adjoint, GradientAccumulator& grads) const {
    const Param& dp = params[density];
    if (grid) {
      const TrilinearFootprint fp = footprint(params, world);
      if (grads.wants(scale)) grads.add(scale, 0, adjoint * grid_eval<float>(dp, fp, 0));
      if (grads.wants(density)) grid_backprop(density, dp, fp, 0, adjoint * params[scale].value[0], grads);
    } else {
      if (grads.wants(scale)) grads.add(scale, 0, adjoint * dp.value[0]);
      if (grads.wants(density)) grads.add(density, 0, adjoint * params[scale].value[0]);
    }
  }
  void backprop_albedo(const ParamStore& params, const Vec3f& world, const Vec3f& adjoint,
                       GradientAccumulator& grads) const {
    if (!grads.wants(albedo)) return;
    const Param& ap = params[albedo];
    if (ap.shape.size() == 4) {
      grid_backprop_rgb(albedo, ap, trilinear_footprint(grid_size(ap), to_local(world)), adjoint, grads);
    } else {
      for (int c = 0; c < 3; ++c) grads.add(albedo, size_t(c), adjoint[c]);
    }
  }
  // adjoint_over_p · ∂p(wi, wo)/∂g.
  void backprop_phase(const ParamStore& params, const Vec3f& wi, const Vec3f& wo, float adjoint,
                      GradientAccumulator& grads) const {
    if (grads.wants(g)) grads.add(g, 0, hg_backprop(phase<float>(params), wi, wo, adjoint).g);
  }
};

// σ_t(world) on T for tracking: the float reader, or sigma_t<T> (the taped mode's leaves).
template <class T>
auto sigma_lookup(const Medium& m, const ParamStore& params) {
  if constexpr (std::is_same_v<T, float>)
    return Medium::SigmaReader(m, params);
  else
    return [&m, &params](const Vec3f& world) { return m.sigma_t<T>(params, world); };
}

// Tracking callbacks that do nothing (primal and taped runs).
struct NoTrackingEvents {
  void operator()(const Vec3f&, float, float, bool) const {}
};

// Delta tracking along a ray through medium m (see tracking.h for the weight's score terms).
// on_collision(x, σ_t value, majorant, real) is called at every tentative collision (prb uses it
// for the score terms of the real/null choices).
template <class T, class OnCollision = NoTrackingEvents>
FreeFlight<T> medium_free_flight(const Medium& m, const ParamStore& params, const Vec3f& o, const Vec3f& d, float t_max,
                                 TrackingSampler& rng, OnCollision&& on_collision = {}) {
  FreeFlight<T> out;
  const auto sigma_at = sigma_lookup<T>(m, params);
  m.segments(o, d, t_max, [&](const MajorantSegment& seg) {
    if (!(seg.majorant > 0.f)) return true;
    float t = seg.t0;
    for (;;) {
      t -= std::log(1.f - rng.next()) / seg.majorant;
      if (!(t < seg.t1)) return true;
      const T sigma = sigma_at(o + d * t);
      const float sigma_value = value_of(sigma);
      const bool real = rng.next() * seg.majorant < sigma_value;
      on_collision(o + d * t, sigma_value, seg.majorant, real);
      if (real) {
        out.collided = true;
        out.t = t;
        out.real = sigma / sigma_value;
        return false;
      }
      out.weight = out.weight * ((seg.majorant - sigma) / (seg.majorant - sigma_value));
      ++out.null_collisions;
    }
  });
  return out;
}

// Ratio tracking: an unbiased estimate of the transmittance of [0, t_max) along o + t·d.
// on_point(x, σ_t value, majorant, false) is called at every tentative point.
template <class T, class OnPoint = NoTrackingEvents>
T medium_transmittance(const Medium& m, const ParamStore& params, const Vec3f& o, const Vec3f& d, float t_max,
                       TrackingSampler& rng, OnPoint&& on_point = {}) {
  T transmittance = T(1.f);
  const auto sigma_at = sigma_lookup<T>(m, params);
  m.segments(o, d, t_max, [&](const MajorantSegment& seg) {
    if (!(seg.majorant > 0.f)) return true;
    float t = seg.t0;
    for (;;) {
      t -= std::log(1.f - rng.next()) / seg.majorant;
      if (!(t < seg.t1)) return true;
      const Vec3f x = o + d * t;
      const T sigma = sigma_at(x);
      on_point(x, value_of(sigma), seg.majorant, false);
      transmittance = transmittance * (T(1.f) - sigma / seg.majorant);
      if (value_of(transmittance) == 0.f) return false;  // also ends rays to infinity in unbounded media
    }
  });
  return transmittance;
}

}  // namespace bl
