#pragma once
// The path loop: unidirectional path tracing with next-event estimation and MIS (power
// heuristic), Russian roulette and Mitsuba 3's max-depth convention (max_depth counts path
// segments, the camera ray included).
//
// One loop serves every integrator (DESIGN.md, property 6):
//  - `path` (primal) runs it on float with no observer;
//  - the taped mode runs it on a tape scalar, recording every parameter-dependent operation;
//  - `prb` runs it on float with an observer that receives each contribution as it is made and
//    calls the derivative shaders (path replay), and `rb` with one that estimates incident
//    radiance independently.
// Sampling is detached: directions, pdfs, MIS weights and roulette decisions are computed from
// plain float values and are constants of differentiation, so all modes make the same decisions
// for the same random numbers.
#include <cmath>
#include <limits>
#include <vector>

#include "engine/core/sampler.h"
#include "engine/scene/scene.h"
#include "kernels/medium/medium.h"

namespace bl {

// Where emitted radiance came from: an area emitter (index, uv) or the environment (direction).
struct EmissionRef {
  int area = -1;  // index into Scene::area_emitters; -1 = environment
  Vec2f uv;
  Vec3f direction;  // for the environment: direction towards it
  // For a light sample on an area emitter: the sampled triangle and barycentrics (geometry
  // gradients move the point with its triangle).
  int triangle = -1;
  float b1 = 0.f, b2 = 0.f;
};

// What a derivative shader needs about a scattering vertex.
struct VertexRef {
  const Material* material = nullptr;
  const BsdfValue<float>* value = nullptr;  // the material's textures evaluated at uv (detached)
  Vec2f uv;
  Vec3f tint;  // the vertex colour the material's colour was multiplied by (white: none)
  Vec3f wo;    // local shading frame
  int vertex = 0;
};

// A tentative collision of ratio tracking on a shadow ray: the transmittance estimate carries the
// factor 1 − σ_t(x)/σ̄ for it.
struct ShadowPoint {
  const Medium* medium;
  Vec3f x;
  float sigma, majorant;
};

// Observer that ignores everything (primal and taped modes).
struct NoObserver {
  static constexpr bool kActive = false;
  // Whether the loop tracks zero channels (ZeroChannels below; prb's first run) and hands their
  // radiance to zero_channels(radiance_after_first_zero) at the end of the path.
  static constexpr bool kZeroChannels = false;
  void zero_channels(const Vec3f&) {}
  // Media (see trace_path): a tentative collision of delta tracking; a medium vertex after its
  // light sample and phase sample; the light sample of a medium vertex; the transmittance of a
  // surface vertex's shadow ray.
  void flight_collision(const Medium&, const Vec3f&, float, float, bool, const Vec3f&) {}
  void medium_vertex(const Medium&, const Vec3f&, const Vec3f&, const Vec3f&, const Vec3f&, const Vec3f&,
                     const Vec3f&) {}
  void begin_shadow() {}
  void shadow_point(const ShadowPoint&) {}
  void medium_nee(const Medium&, const Vec3f&, const Vec3f&, const Vec3f&, float, const EmissionRef&, const Vec3f&,
                  const Vec3f&) {}
  void shadow(const Vec3f&) {}
  // A derivative-only light sample at a tentative collision (medium_light_derivative): ∂σ_t(x)
  // gets ⟨δ, weighted⟩. Whether the loop should take them for medium m at all (the taped mode:
  // when σ_t reads a parameter that wants a gradient; otherwise their terms are zero):
  void flight_light(const Medium&, const Vec3f&, const Vec3f&) {}
  bool light_derivatives(const Medium& m, const ParamStore& params) const {
    return m.light_derivatives > 0.f && m.wants_sigma_grad(params);
  }
  void emission(const EmissionRef&, const Vec3f&, const Vec3f&) {}
  void nee(const VertexRef&, const Vec3f&, const EmissionRef&, const Vec3f&, const Vec3f&, const Vec3f&) {}
  void scatter(const VertexRef&, const Vec3f&, const Vec3f&, float, float, const Vec3f&, const Vec3f&, int,
               const Ray&) {}
  // The shadow-ray query of next-event estimation at `vertex`: `blocked()` answers it by casting
  // rays (and, through media, tracking them); a replay may answer from its first run's record.
  template <class Blocked>
  bool occluded(int, Blocked&& blocked) {
    return blocked();
  }
  // Whether next-event estimation at `vertex` can contribute at all. Only a replay knows better
  // (from the first run's shadow-ray answers); it then skips the emitter sample and both evals.
  bool nee_may_contribute(int) const { return true; }
  // Iteration `vertex` of the loop reached `site`: a mesh index, kSiteEscape or kSiteMedium.
  void reached(int, int) {}
  // Iteration `vertex` hit a surface (active observers only): the ray, its hit and the point.
  void surface(int, const Ray&, const Hit&, const SurfacePoint&) {}
  // Whether the path is worth following into iteration `vertex` (a replay stops after the last
  // vertex that can produce a derivative).
  bool follows(int) const { return true; }
  // Iteration `vertex` tracked a medium: a free-flight segment inside one, or a shadow ray through
  // one (every observer hears it; the first run of prb notes it as a derivative site).
  void tracked(int) {}
};

inline constexpr int kSiteEscape = -1;  // the ray left the scene (environment emission)
inline constexpr int kSiteMedium = -2;  // a real collision in a medium

// Where a derivative event of an adjoint pass can be non-zero, decided once per pass from which
// parameters want gradients. A surface counts if its material reads such a parameter, if it is
// an emitter whose radiance does, or, when any emitter's radiance does, if it is a scattering
// surface at all (its light sample reaches that emitter). Escaped rays count when the
// environment's radiance wants a gradient, medium vertices when any emitter does. With a
// gradient on any medium parameter, every iteration that tracks a medium counts as well (its
// tentative collisions, medium vertex and shadow-ray tracking carry derivatives): `tracking`.
struct DerivativeSites {
  std::vector<uint8_t> mesh;
  bool escape = false, medium = false, tracking = false;

  bool at(int site) const {
    if (site == kSiteEscape) return escape;
    if (site == kSiteMedium) return medium;
    return mesh[size_t(site)] != 0;
  }
};

inline DerivativeSites derivative_sites(const Scene& scene, const GradientAccumulator& grads) {
  DerivativeSites d;
  bool emitters = grads.wants(scene.environment.present ? scene.environment.param : -1);
  for (const AreaEmitter& e : scene.area_emitters) emitters = emitters || grads.wants(e.radiance.param);
  for (const Medium& m : scene.media)
    d.tracking =
        d.tracking || grads.wants(m.density) || grads.wants(m.scale) || grads.wants(m.albedo) || grads.wants(m.g);
  d.escape = scene.environment.present && grads.wants(scene.environment.param);
  d.medium = emitters;
  d.mesh.resize(scene.meshes.size());
  for (size_t i = 0; i < scene.meshes.size(); ++i) {
    const Mesh& mesh = scene.meshes[i];
    const Material& material = scene.materials[size_t(mesh.material)];
    if (material.is_null) continue;  // crossed, never a vertex
    const bool own_emission =
        mesh.emitter >= 0 && grads.wants(scene.area_emitters[size_t(mesh.emitter)].radiance.param);
    d.mesh[i] = material.wants_grad(grads) || own_emission || emitters;
  }
  return d;
}

// The radiance a path would carry in a colour channel had its first zero factor in that channel
// been 1. prb's replay takes a vertex's derivative as δ · (radiance still to come) / f per
// channel, which says nothing where f (a BSDF sample's value, a medium's albedo) is 0 in a
// channel: an albedo channel at exactly 0 (an 8-bit texture, a bound the optimizer projected
// onto) lost its whole bounce term (25% of a Cornell wall's gradient). The derivative there is
// δ · (what the rest of the path carries with that factor replaced by 1); only the first zero per
// channel matters (after a second one the true throughput before it is already 0). The first run
// tracks that throughput β̃ and radiance L̃ per channel from each channel's first zero on (the
// same factors as β, the zero replaced by 1) and the replay uses L̃ at that vertex. Paths with no
// zero channel pay three compares per vertex and an untaken branch per event (no change within
// the noise of Cornell timings). Exact at 0 only: a factor tiny but not 0 (below ~1e-7 of the
// channel's radiance so far) still goes through rest / f, whose float difference loses the
// bounce term (2.7% of a gradient at 1e-30, 0.27% at 1e-7).
struct ZeroChannels {
  bool active = false;  // some channel has met its first zero
  bool zeroed[3] = {false, false, false};
  Vec3f beta{0.f}, radiance{0.f};  // β̃, L̃ (0 in channels not zeroed yet)

  // A factor `value` about to multiply β at a vertex whose throughput so far is `beta_now`:
  // channels at their first zero start β̃ from `beta_now`, and the factor for β̃ is returned
  // (the zeros replaced by 1 in those channels).
  Vec3f first_zeros(const Vec3f& value, const Vec3f& beta_now) {
    Vec3f factor = value;
    for (int c = 0; c < 3; ++c)
      if (value[c] == 0.f && !zeroed[c]) {
        zeroed[c] = true;
        active = true;
        beta[c] = beta_now[c];
        factor[c] = 1.f;
      }
    return factor;
  }
};

// Replay side of ZeroChannels: whether channel c of `value` is that channel's first zero on the
// path (the same vertices the first run found, met in the same order).
struct ZeroChannelMask {
  bool zeroed[3] = {false, false, false};
  // Marks the first zeros of `value`; first[c] says which channels they were.
  void mark(const Vec3f& value, bool first[3]) {
    for (int c = 0; c < 3; ++c) {
      first[c] = value[c] == 0.f && !zeroed[c];
      zeroed[c] = zeroed[c] || value[c] == 0.f;
    }
  }
};

// Shadow-ray answers of one path, one bit per surface vertex. The adjoint pass records them while
// computing a sample's radiance and hands them to the replay of the same sample: the answers are a
// function of the same random numbers, so the replay need not cast its shadow rays again.
struct VisibilityBits {
  static constexpr int kVertices = 64;  // deeper vertices are queried again
  uint64_t queried = 0, blocked = 0;
};

// First run of a path in the adjoint pass: no events; shadow-ray answers recorded, and the last
// vertex at which a derivative event can be non-zero (0: none), where the replay may stop.
struct VisibilityRecorder : NoObserver {
  static constexpr bool kZeroChannels = true;
  const DerivativeSites* sites = nullptr;  // null: every vertex counts
  VisibilityBits bits;
  int last_site = 0;
  Vec3f zero_channel_radiance{0.f};  // ZeroChannels::radiance at the end of the path
  void zero_channels(const Vec3f& radiance) { zero_channel_radiance = radiance; }
  void reached(int vertex, int site) {
    if (!sites || sites->at(site)) last_site = vertex;
  }
  void tracked(int vertex) {
    if (!sites || sites->tracking) last_site = vertex;
  }
  template <class Blocked>
  bool occluded(int vertex, Blocked&& query) {
    const bool blocked = query();
    if (vertex < VisibilityBits::kVertices) {
      bits.queried |= uint64_t(1) << vertex;
      if (blocked) bits.blocked |= uint64_t(1) << vertex;
    }
    return blocked;
  }
};

// Replay side: whether NEE at `vertex` contributed in the recorded run. A vertex whose shadow ray
// was never cast (emitter sample with pdf 0, or a zero BSDF value towards it) or was blocked
// contributed nothing, and the replay of the same random numbers would compute the same nothing.
inline bool replay_nee_may_contribute(const VisibilityBits& bits, int vertex) {
  if (vertex >= VisibilityBits::kVertices) return true;
  return (bits.queried >> vertex & 1u) && !(bits.blocked >> vertex & 1u);
}

// Replay side: answers from the recorded bits when present, else by the query.
template <class Blocked>
bool replay_occluded(const VisibilityBits& bits, int vertex, Blocked&& query) {
  if (vertex < VisibilityBits::kVertices && (bits.queried >> vertex & 1u)) return (bits.blocked >> vertex & 1u) != 0;
  return query();
}

inline float power_heuristic(float a, float b) {
  float a2 = a * a, b2 = b * b;
  if (a2 + b2 <= std::numeric_limits<float>::max()) return a2 + b2 > 0.f ? a2 / (a2 + b2) : 0.f;
  // A square overflowed (the light pdf of a triangle of area 1e-20 is ~1e20): inf / inf was NaN.
  // The same weight from the ratio of the smaller to the larger pdf.
  if (a >= b) {
    const float r = b / a;
    return 1.f / (1.f + r * r);
  }
  const float r = a / b;
  return r * r / (1.f + r * r);
}

inline void emitter_backprop(const Scene& scene, const EmissionRef& e, const Vec3f& adjoint, GradientAccumulator& g) {
  if (e.area >= 0)
    scene.area_emitters[size_t(e.area)].backprop(scene.params, e.uv, 1.f, adjoint, g);  // front side by construction
  else
    scene.environment.backprop(scene.params, e.direction, adjoint, g);
}

// Where a path starts: the camera ray (vertex 1 is its first hit) or, for rb's independent
// estimates, a ray leaving a surface vertex after a BSDF sample of solid-angle pdf `bsdf_pdf`.
struct PathStart {
  Ray ray;
  int first_vertex = 1;
  float bsdf_pdf = 0.f;  // 0: the ray was not BSDF-sampled (no MIS on what it hits)
  int medium = -1;       // the medium the ray starts in (the camera's), -1 = vacuum
  // What `ray` hits, when the caller has traced it already (a pixel's camera rays go through
  // Embree as one packet: Geometry::intersect_packet, the same hits as one by one).
  const Hit* first_hit = nullptr;
};

// Up to Geometry::kPacket camera rays of one pixel and their first hits, traced as one Embree
// packet: a pixel's samples start from nearly the same ray, so the packet traversal visits the
// BVH about once for all of them (Geometry::intersect_packet: the single-ray hits, but for ties
// on shared edges, which it may give to the other triangle). The primal, prb (first run and
// replay), rb and the taped mode all start their paths this way, so they follow the same paths.
// (The geometry-gradient passes, engine/integrators/interior.cpp and boundary.cpp, trace their
// own camera rays.)
struct CameraPacket {
  Ray rays[Geometry::kPacket];
  Hit hits[Geometry::kPacket];
  int medium = -1;
  // Traces the camera rays of samples sample_of(0 .. count-1) of pixel (x, y), count ≤ kPacket.
  template <class SampleOf>
  void trace(const Scene& scene, const Camera& cam, uint64_t seed, int x, int y, int count, SampleOf sample_of) {
    const uint64_t pixel = uint64_t(y) * uint64_t(cam.width) + uint64_t(x);
    for (int k = 0; k < count; ++k) {
      const PathSampler sampler(seed, pixel, uint64_t(sample_of(k)));
      rays[k] = cam.generate(float(x) + sampler.get(Dim::kPixelX), float(y) + sampler.get(Dim::kPixelY));
    }
    medium = cam.medium;
    scene.geometry->intersect_packet(rays, count, hits);
  }
  // The k-th path's start (valid while this packet lives).
  PathStart start(int k) const { return PathStart{rays[k], 1, 0.f, medium, &hits[k]}; }
};

// The transmittance of the shadow segment o + t·d, t < tmax, starting in `medium`: ratio tracking
// through every medium the walk (walk_shadow_segment, engine/scene/scene.h) crosses, 0 when a
// surface that is not null blocks it. One tracking stream per (path, vertex): the replay
// regenerates it.
struct NoShadowEvents {
  void operator()(const Medium&, const Vec3f&, float, float) const {}
};

template <class T>
struct ShadowWalk {
  T transmittance = T(1.f);
  bool blocked = false;
  bool tracked = false;  // the walk crossed a medium (tracked it, or stopped at a blocker in it)
};

template <class T, class OnPoint = NoShadowEvents>
ShadowWalk<T> shadow_transmittance(const Scene& scene, const Vec3f& o, const Vec3f& d, float tmax, int medium,
                                   TrackingSampler& rng, bool find_blockers, OnPoint&& on_point = {}) {
  ShadowWalk<T> walk;
  walk.blocked =
      walk_shadow_segment(scene, o, d, tmax, medium, find_blockers, [&](int m, const Vec3f& origin, float length) {
        const Medium& med = scene.media[size_t(m)];
        walk.tracked = true;
        walk.transmittance =
            walk.transmittance * medium_transmittance<T>(med, scene.params, origin, d, length, rng,
                                                         [&](const Vec3f& x, float sigma, float majorant, bool) {
                                                           on_point(med, x, sigma, majorant);
                                                         });
        return value_of(walk.transmittance) != 0.f;
      });
  if (walk.blocked) walk.transmittance = T(0.f);  // nothing before the blocker needs tracking
  return walk;
}

inline TrackingSampler shadow_sampler(uint64_t path_key, int vertex) { return {path_key, vertex, 1u}; }

// shadow_transmittance for the path loop: an active observer hears of every tentative collision
// (a replay keeps them to differentiate the estimate without tracking the ray a second time).
template <class T, class Observer>
ShadowWalk<T> observed_shadow_transmittance(const Scene& scene, const Vec3f& o, const Vec3f& d, float tmax, int medium,
                                            TrackingSampler& rng, bool find_blockers, Observer& observer) {
  if constexpr (Observer::kActive) {
    observer.begin_shadow();
    return shadow_transmittance<T>(scene, o, d, tmax, medium, rng, find_blockers,
                                   [&](const Medium& m, const Vec3f& x, float sigma, float majorant) {
                                     observer.shadow_point(ShadowPoint{&m, x, sigma, majorant});
                                   });
  } else {
    return shadow_transmittance<T>(scene, o, d, tmax, medium, rng, find_blockers);
  }
}

// The shadow ray of next-event estimation at `vertex`, from o towards the light (tmax short of
// it), starting in `medium`: whether the light is visible and, through media, the transmittance.
// Without media it is the observer's visibility query. With media one walk along the ray finds a
// blocker and tracks the media together — a separate visibility query first would cast every ray
// of the walk twice. A replay that recalls the first run's answer tracks only when the light was
// visible, regenerating the same draws from the (path, vertex) stream.
template <class T, class Observer>
bool trace_shadow_ray(const Scene& scene, Observer& observer, uint64_t path_key, int vertex, const Vec3f& o,
                      const Vec3f& d, float tmax, int medium, T& transmittance) {
  transmittance = T(1.f);
  if (scene.media.empty()) return !observer.occluded(vertex, [&] { return scene.occluded(o, d, tmax); });
  TrackingSampler rng = shadow_sampler(path_key, vertex);
  bool walked = false;
  auto walk = [&](bool find_blockers) {  // tracks the ray, tells the observer when a medium was met
    walked = true;
    const ShadowWalk<T> w = observed_shadow_transmittance<T>(scene, o, d, tmax, medium, rng, find_blockers, observer);
    if (w.tracked) observer.tracked(vertex);
    transmittance = w.transmittance;
    return w.blocked;
  };
  if (observer.occluded(vertex, [&] { return walk(true); })) return false;
  if (!walked) walk(false);
  return true;
}

// The derivative of a ratio-tracked transmittance Π (1 − σ_t(x_i)/σ̄_i): each point contributes
// −∂σ_t(x_i) / (σ̄_i − σ_t(x_i)) to ∂ log T; adds weight · that into the media's parameters
// (weight = ⟨δ, contribution the ray carried⟩).
inline void shadow_transmittance_backprop(const Scene& scene, const std::vector<ShadowPoint>& points, float weight,
                                          GradientAccumulator& grads) {
  if (weight == 0.f) return;
  for (const ShadowPoint& p : points)
    if (p.medium->wants_sigma_grad(scene.params) && p.majorant > p.sigma)
      p.medium->backprop_sigma_t(scene.params, p.x, -weight / (p.majorant - p.sigma), grads);
}

// The light sample of a medium vertex at x (Mitsuba volpath: one emitter chosen uniformly by
// u_select, a point on it by u, MIS against phase sampling): the emitter sample, the shadow ray's
// length and the MIS weight over the light pdf. Shared by the path loop and the light derivatives.
struct MediumLightSample {
  int chosen = 0;  // index into the area emitters; area count = the environment
  EmitterSample es;
  float tmax = 0.f, w_over_pdf = 0.f;
  // The chosen emitter's radiance towards x.
  template <class T>
  Spectrum<T> emitted(const Scene& scene, const ParamStore& params) const {
    return chosen < int(scene.area_emitters.size()) ? scene.area_emitters[size_t(chosen)].eval<T>(params, es.uv, 1.f)
                                                    : scene.environment.eval<T>(params, es.env);
  }
};
inline MediumLightSample medium_light_sample(const Scene& scene, const Vec3f& x, const Vec3f& wi,
                                             const HgParams<float>& phase, double u_select, double u0, double u1) {
  MediumLightSample s;
  const int area_count = int(scene.area_emitters.size());
  s.chosen = scene.choose_emitter(u_select);
  s.es = s.chosen < area_count ? scene.sample_area_emitter(s.chosen, x, u0, u1) : scene.environment.sample(u0, u1);
  if (!(s.es.pdf > 0.f)) return s;
  s.tmax = std::isinf(s.es.distance) ? std::numeric_limits<float>::infinity() : length(s.es.point - x) * (1.f - 1e-3f);
  const float light_pdf = s.es.pdf * scene.emitter_select_probability();
  s.w_over_pdf = power_heuristic(light_pdf, hg_pdf(phase, wi, s.es.wi)) / light_pdf;
  return s;
}

// Density derivatives from light samples at tentative collisions (Medium::light_derivatives = f >
// 0). A real collision of delta tracking at x (probability σ_t/σ̄) gives ∂σ_t(x) the score term
// ⟨δ, rest⟩/σ_t; rest includes the vertex's own light sample, whose share of that term has the
// expectation ∂σ_t(x)·E[light sample at x]/σ̄ and a variance of order 1/σ_t — large where the
// medium is thin against its majorant (the holes of a density being recovered). At the points
// where σ_t < f·σ̄ (a detached decision that depends on x alone), the real collision's score term
// leaves its light sample out, and every tentative collision there, real or null, instead takes
// with probability f one light sample of the same estimator (the β before the collision, albedo,
// phase function, shadow-ray transmittance and MIS weight of a medium vertex) from its own
// stream, contributing ∂σ_t(x)·sample/(f σ̄): the same expectation, with a variance of order
// 1/(f σ̄) < 1/σ_t. Elsewhere nothing changes. Only derivative passes (prb's replay and the taped
// mode) take these samples; images are unchanged. Returns sample/(f σ̄), zero when not taken,
// occluded or not possible.
inline Vec3f medium_light_derivative(const Scene& scene, const Medium& med, int medium, const Vec3f& x, const Vec3f& wi,
                                     float sigma, float majorant, const Vec3f& beta, uint64_t path_key, uint32_t flight,
                                     uint32_t collision) {
  if (!med.light_derivative_at(sigma, majorant)) return {};
  const float q = med.light_derivatives;
  TrackingSampler rng(path_key, int(flight), 0x20000u + collision);
  if (!(rng.next() < q)) return {};
  const HgParams<float> phase = med.phase<float>(scene.params);
  const double u_select = rng.next_double();
  const double u0 = rng.next_double(), u1 = rng.next_double();
  const MediumLightSample ls = medium_light_sample(scene, x, wi, phase, u_select, u0, u1);
  if (!(ls.es.pdf > 0.f)) return {};
  const ShadowWalk<float> walk = shadow_transmittance<float>(scene, x, ls.es.wi, ls.tmax, medium, rng, true);
  if (walk.blocked || walk.transmittance == 0.f) return {};
  return beta * med.albedo_at<float>(scene.params, x) * ls.emitted<float>(scene, scene.params) *
         (hg_eval(phase, wi, ls.es.wi) * walk.transmittance * ls.w_over_pdf / (q * majorant));
}

// Traces one path and returns its radiance estimate. Observer events (float values only):
//  emission(ref, weight, contribution)      contribution = weight · Le, weight = β · w_mis
//  nee(vertex, wi, ref, bsdf_adjoint_w, emitter_adjoint_w, contribution)
//      contribution = β f Le w / p_light; bsdf_adjoint_w = β Le w / p_light; emitter_adjoint_w = β f w / p_light
//  scatter(vertex, wi, f, pdf, q, beta_before, radiance_so_far, vertex_index, next_ray)
//      after the BSDF sample and roulette survived: β ← β f / (pdf q)
//
// Media (Mitsuba 3 volpath conventions, ../shared/reference/mitsuba3-volume/README.md): inside a
// medium, each segment is tracked (delta tracking against the medium's majorants); a real
// collision is a path vertex like a surface hit (it counts towards max_depth, takes one light
// sample with MIS against phase sampling, then samples the phase function), a null collision is
// not. Null surfaces only switch the medium: no vertex, no light sample, and the MIS reference
// point stays at the last real vertex. Shadow rays cross null surfaces, their transmittance
// estimated by ratio tracking. Medium events for the adjoint (float values):
//  flight_collision(medium, x, σ_t, σ̄, real, radiance_so_far)   every tentative collision
//  medium_nee(medium, x, wi, wl, p(wi, wl), ref, emitter_weight, contribution)
//  medium_vertex(medium, x, wi, wo, albedo, radiance_before_vertex, radiance_after_its_nee)
//  shadow(contribution)   the transmittance of a surface vertex's light sample
//  begin_shadow(), shadow_point(point)   the tracking of the shadow ray the next medium_nee or
//                                        shadow event is about
template <class T, class Observer>
Spectrum<T> trace_path(const Scene& scene, const PathStart& start, const PathSampler& sampler, Observer& observer) {
  const IntegratorSettings& st = scene.settings;
  const ParamStore& params = scene.params;
  const float select_pdf = scene.emitter_select_probability();
  const int area_count = int(scene.area_emitters.size());
  const bool has_emitters = area_count > 0 || scene.environment.present;
  Spectrum<T> radiance(T(0.f)), beta(T(1.f));
  [[maybe_unused]] ZeroChannels zc;  // Observer::kZeroChannels only
  constexpr bool kZero = Observer::kZeroChannels;
  static_assert(!kZero || std::is_same_v<T, float>, "zero channels are tracked by the float first run only");
  Ray ray = start.ray;
  float mis_bsdf_pdf = start.bsdf_pdf;
  int medium = start.medium;
  float travelled = 0.f;  // distance from the last real vertex along `ray`'s direction (null crossings)
  uint32_t flight = 0;    // free-flight tracking streams used so far
  int null_crossings = 0;

  const Hit* traced = start.first_hit;  // the first segment's hit, when given
  for (int vertex = start.first_vertex;;) {
    if (!observer.follows(vertex)) break;
    const Hit hit = traced ? *traced : scene.geometry->intersect(ray);
    traced = nullptr;
    const bool visible_emitter = !(vertex == 1 && st.hide_emitters);

    // Inside a medium: free flight up to the surface (or to infinity).
    if (medium >= 0) {
      observer.tracked(vertex);
      const Medium& med = scene.media[size_t(medium)];
      const uint32_t flight_index = flight++;
      TrackingSampler rng(sampler.key(), int(flight_index), 0x10000u);
      const float t_max = hit.mesh < 0 ? std::numeric_limits<float>::infinity() : hit.t;
      const Vec3f radiance_so_far = value_of(radiance);
      // Light derivatives (medium_light_derivative): derivative passes only, where a real
      // collision here would take a light sample.
      constexpr bool kDerivativePass = Observer::kActive || !std::is_same_v<T, float>;
      const bool light_derivatives = kDerivativePass && has_emitters &&
                                     !(st.max_depth >= 0 && vertex >= st.max_depth) &&
                                     observer.light_derivatives(med, params);
      uint32_t collisions = 0;
      bool real_light = false;  // the real collision leaves its light sample out of its score term
      const FreeFlight<T> ff = medium_free_flight<T>(
          med, params, ray.origin, ray.direction, t_max, rng,
          [&](const Vec3f& x, float sigma, float majorant, bool real) {
            if constexpr (Observer::kActive) observer.flight_collision(med, x, sigma, majorant, real, radiance_so_far);
            if constexpr (kDerivativePass) {
              if (!light_derivatives) return;
              if (real) real_light = med.light_derivative_at(sigma, majorant);
              const Vec3f c = medium_light_derivative(scene, med, medium, x, -ray.direction, sigma, majorant,
                                                      value_of(beta), sampler.key(), flight_index, collisions++);
              if (is_zero(c)) return;
              if constexpr (Observer::kActive) {
                observer.flight_light(med, x, c);
              } else {  // zero in value, ∂σ_t(x)·c in derivative
                const T d = med.sigma_t<T>(params, x) - sigma;
                radiance += Spectrum<T>(d * c.x, d * c.y, d * c.z);
              }
            }
          });
      beta = beta * ff.weight;
      if constexpr (kZero)
        if (zc.active) zc.beta = zc.beta * value_of(ff.weight);
      if (ff.collided) {
        observer.reached(vertex, kSiteMedium);
        if (st.max_depth >= 0 && vertex >= st.max_depth) break;
        const Vec3f p = ray.origin + ray.direction * ff.t;
        const Vec3f wi_phase = -ray.direction;  // Mitsuba's wi: back along the path
        const Spectrum<T> albedo = med.albedo_at<T>(params, p);
        const HgParams<T> phase = med.phase<T>(params);
        const HgParams<float> phase_detached{value_of(phase.g)};
        [[maybe_unused]] Vec3f zc_albedo;  // the albedo for β̃ (ZeroChannels)
        if constexpr (kZero) zc_albedo = zc.first_zeros(value_of(albedo), value_of(beta));

        if (has_emitters && observer.nee_may_contribute(vertex)) {
          const MediumLightSample ls = medium_light_sample(
              scene, p, wi_phase, phase_detached, sampler.get_double(Dim::at(vertex, Dim::kLightSelect)),
              sampler.get_double(Dim::at(vertex, Dim::kLightU)), sampler.get_double(Dim::at(vertex, Dim::kLightV)));
          const EmitterSample& es = ls.es;
          if (es.pdf > 0.f) {
            const T f = hg_eval(phase, wi_phase, es.wi);
            T tr = T(1.f);
            if (trace_shadow_ray<T>(scene, observer, sampler.key(), vertex, p, es.wi, ls.tmax, medium, tr)) {
              const Spectrum<T> emitted = ls.emitted<T>(scene, params);
              // With light derivatives the real choice's score term leaves this sample out.
              const Spectrum<T> contribution =
                  (real_light ? beta : beta * ff.real) * albedo * emitted * (f * tr * ls.w_over_pdf);
              radiance += contribution;
              if constexpr (kZero)
                if (zc.active)
                  zc.radiance +=
                      (real_light ? zc.beta : zc.beta * ff.real) * zc_albedo * emitted * (f * tr * ls.w_over_pdf);
              if constexpr (Observer::kActive) {
                const EmissionRef eref{ls.chosen < area_count ? ls.chosen : -1, es.uv, es.wi};
                const Vec3f emitter_weight =
                    value_of(beta) * value_of(albedo) * (value_of(f) * value_of(tr) * ls.w_over_pdf);
                observer.medium_nee(med, p, wi_phase, es.wi, value_of(f), eref, emitter_weight, value_of(contribution));
              }
            }
          }
        }

        Vec2f u{sampler.get(Dim::at(vertex, Dim::kBsdfU)), sampler.get(Dim::at(vertex, Dim::kBsdfV))};
        const PhaseSample ps = hg_sample(phase_detached, wi_phase, u);
        if (!(ps.pdf > 0.f)) break;
        // p / pdf is 1 in value; on T it carries the derivative of the phase function.
        beta = beta * ff.real * albedo * (hg_eval(phase, wi_phase, ps.wo) / ps.pdf);
        if constexpr (kZero)
          if (zc.active) zc.beta = zc.beta * ff.real * zc_albedo * (hg_eval(phase, wi_phase, ps.wo) / ps.pdf);
        if constexpr (Observer::kActive)
          observer.medium_vertex(med, p, wi_phase, ps.wo, value_of(albedo), radiance_so_far, value_of(radiance));
        float q = 1.f;
        if (st.rr_depth > 0 && vertex >= st.rr_depth) {
          q = std::min(max_component(value_of(beta)), 0.95f);
          if (!(sampler.get(Dim::at(vertex, Dim::kRoulette)) < q)) break;
          beta = beta * (1.f / q);
          if constexpr (kZero) zc.beta = zc.beta * (1.f / q);
        }
        if (is_zero(value_of(beta))) break;  // nothing more can reach the film (see the surface vertex)
        ray.origin = p;                      // in place, member by member (see the surface vertex below)
        ray.direction = ps.wo;
        ray.tmin = 0.f;
        ray.tmax = Ray{}.tmax;
        mis_bsdf_pdf = ps.pdf;
        travelled = 0.f;
        ++vertex;
        continue;
      }
    }

    // Escaped: environment emission, MIS-weighted against environment sampling.
    if (hit.mesh < 0) {
      observer.reached(vertex, kSiteEscape);
      if (scene.environment.present && visible_emitter) {
        const EnvLookup look = scene.environment.lookup(ray.direction);  // one atan2/acos for pdf and eval
        const float w = mis_bsdf_pdf > 0.f
                            ? power_heuristic(mis_bsdf_pdf, select_pdf * scene.environment.pdf(ray.direction, look))
                            : 1.f;
        const Spectrum<T> emitted = scene.environment.eval<T>(params, look);
        Spectrum<T> contribution = beta * emitted * w;
        radiance += contribution;
        if constexpr (kZero)
          if (zc.active) zc.radiance += zc.beta * emitted * w;
        if constexpr (Observer::kActive)
          observer.emission({-1, {}, ray.direction}, value_of(beta) * w, value_of(contribution));
      }
      break;
    }

    observer.reached(vertex, hit.mesh);
    const Mesh& mesh = scene.meshes[size_t(hit.mesh)];
    const Material& material = scene.materials[size_t(mesh.material)];

    // A null surface: the ray continues unchanged, possibly into another medium. Crossing needs
    // the point and the face normal only (the same values surface_point gives), not its shading
    // attributes.
    if (material.is_null) {
      if constexpr (Observer::kActive) observer.surface(vertex, ray, hit, scene.surface_point(hit, ray));
      if (++null_crossings > kMaxNullCrossings) break;
      const Vec3f ng = mesh.face_normals[size_t(hit.triangle)];
      medium = scene.medium_after(mesh, ray.direction, ng, medium);
      const Vec3f origin = offset_origin(ray.origin + ray.direction * hit.t, ng, ray.direction);
      travelled += length(origin - ray.origin);
      ray.origin = origin;  // the same direction, the whole ray again (in place: see below)
      ray.tmin = 0.f;
      ray.tmax = Ray{}.tmax;
      continue;
    }

    const SurfacePoint sp = scene.surface_point(hit, ray);
    if constexpr (Observer::kActive) observer.surface(vertex, ray, hit, sp);
    const Vec3f wo_world = -ray.direction;

    // Hit an area emitter: its emission, MIS-weighted against light sampling.
    if (mesh.emitter >= 0 && visible_emitter) {
      const AreaEmitter& emitter = scene.area_emitters[size_t(mesh.emitter)];
      float cos_shading = dot(sp.shading_normal, wo_world);
      if (cos_shading > 0.f) {
        float w = 1.f;
        if (mis_bsdf_pdf > 0.f)
          w = power_heuristic(
              mis_bsdf_pdf, select_pdf * emitter.pdf(travelled + hit.t, std::abs(dot(sp.geometric_normal, wo_world))));
        const Spectrum<T> emitted = emitter.eval<T>(params, sp.uv, cos_shading);
        Spectrum<T> contribution = beta * emitted * w;
        radiance += contribution;
        if constexpr (kZero)
          if (zc.active) zc.radiance += zc.beta * emitted * w;
        if constexpr (Observer::kActive)
          observer.emission({mesh.emitter, sp.uv, {}}, value_of(beta) * w, value_of(contribution));
      }
    }

    // Max depth: a further segment would exceed it.
    if (st.max_depth >= 0 && vertex >= st.max_depth) break;

    const BsdfValue<T> bsdf = material.at<T>(params, sp.uv, sp.color);
    const BsdfValue<float> bsdf_detached = bsdf.detached();
    Vec3f normal = sp.shading_normal;
    if (material.two_sided && dot(normal, wo_world) < 0.f) normal = -normal;
    const Frame frame(normal);
    const Vec3f wo = frame.to_local(wo_world);
    const VertexRef vref{&material, &bsdf_detached, sp.uv, sp.color, wo, vertex};

    // Next-event estimation: one emitter chosen uniformly, one point on it.
    if (has_emitters && observer.nee_may_contribute(vertex)) {
      const int chosen = scene.choose_emitter(sampler.get_double(Dim::at(vertex, Dim::kLightSelect)));
      const double u0 = sampler.get_double(Dim::at(vertex, Dim::kLightU)),
                   u1 = sampler.get_double(Dim::at(vertex, Dim::kLightV));
      EmitterSample es =
          chosen < area_count ? scene.sample_area_emitter(chosen, sp.p, u0, u1) : scene.environment.sample(u0, u1);
      if (es.pdf > 0.f) {
        const Vec3f wi = frame.to_local(es.wi);
        Spectrum<T> f = bsdf.eval(wo, wi);
        if (!is_zero(value_of(f))) {
          Vec3f origin = offset_origin(sp.p, sp.geometric_normal, es.wi);
          float tmax = std::isinf(es.distance) ? std::numeric_limits<float>::infinity()
                                               : length(es.point - origin) * (1.f - 1e-3f);
          const int shadow_medium =
              scene.media.empty() ? -1 : scene.medium_after(mesh, es.wi, sp.geometric_normal, medium);
          T tr = T(1.f);  // transmittance of the shadow ray through media
          if (trace_shadow_ray<T>(scene, observer, sampler.key(), vertex, origin, es.wi, tmax, shadow_medium, tr)) {
            EmissionRef eref{chosen < area_count ? chosen : -1, es.uv, es.wi, es.triangle, es.b1, es.b2};
            Spectrum<T> emitted = chosen < area_count ? scene.area_emitters[size_t(chosen)].eval<T>(params, es.uv, 1.f)
                                                      : scene.environment.eval<T>(params, es.env);
            float light_pdf = es.pdf * select_pdf;
            float w_over_pdf = power_heuristic(light_pdf, bsdf_detached.pdf(wo, wi)) / light_pdf;
            Spectrum<T> contribution = beta * f * emitted * (tr * w_over_pdf);
            radiance += contribution;
            if constexpr (kZero)
              if (zc.active) zc.radiance += zc.beta * f * emitted * (tr * w_over_pdf);
            if constexpr (Observer::kActive) {
              Vec3f b = value_of(beta) * (value_of(tr) * w_over_pdf);
              observer.nee(vref, wi, eref, b * value_of(emitted), b * value_of(f), value_of(contribution));
              if (!scene.media.empty()) observer.shadow(value_of(contribution));
            }
          }
        }
      }
    }

    // BSDF sampling continues the path.
    Vec2f u{sampler.get(Dim::at(vertex, Dim::kBsdfU)), sampler.get(Dim::at(vertex, Dim::kBsdfV))};
    BsdfSample bs = bsdf_detached.sample(wo, sampler.get(Dim::at(vertex, Dim::kLobe)), u);
    if (bs.pdf <= 0.f) break;
    Spectrum<T> f = bsdf.eval(wo, bs.wi);
    if (is_zero(value_of(f))) break;
    const Vec3f beta_before = value_of(beta);
    beta = beta * f * (1.f / bs.pdf);
    if constexpr (kZero) {
      const Vec3f zc_f = zc.first_zeros(f, beta_before);
      if (zc.active) zc.beta = zc.beta * zc_f * (1.f / bs.pdf);
    }

    // Russian roulette on the detached throughput (Mitsuba's rule: after the BSDF sample at
    // surface vertex k ≥ rr_depth, continue with q = min(max β, 0.95)).
    float q = 1.f;
    if (st.rr_depth > 0 && vertex >= st.rr_depth) {
      q = std::min(max_component(value_of(beta)), 0.95f);
      if (!(sampler.get(Dim::at(vertex, Dim::kRoulette)) < q)) break;
      beta = beta * (1.f / q);
      if constexpr (kZero) zc.beta = zc.beta * (1.f / q);
    }
    // Nothing more can reach the film: the throughput underflowed to 0 (an albedo of 0.01 after
    // ~25 bounces; with max_depth -1 and roulette off a closed scene then looped for ever), or
    // zero factors in different channels at two vertices left none (the second's own derivative
    // is then lost, as in the taped mode: see ZeroChannels).
    if (is_zero(value_of(beta))) break;

    const Vec3f wi_world = frame.to_world(bs.wi);
    // The next ray is written in place, member by member: assembling it aside and copying it
    // whole made the copy's wide loads wait for the narrower stores still in flight (a store-
    // forwarding stall measured at ~2.5% of a Cornell render).
    ray.origin = offset_origin(sp.p, sp.geometric_normal, wi_world);
    ray.direction = wi_world;
    ray.tmin = 0.f;
    ray.tmax = Ray{}.tmax;
    if constexpr (Observer::kActive)
      observer.scatter(vref, bs.wi, value_of(f), bs.pdf, q, beta_before, value_of(radiance), vertex, ray);
    medium = scene.medium_after(mesh, wi_world, sp.geometric_normal, medium);
    mis_bsdf_pdf = bs.pdf;
    travelled = 0.f;
    ++vertex;
  }
  if constexpr (kZero) observer.zero_channels(zc.radiance);
  return radiance;
}

}  // namespace bl
