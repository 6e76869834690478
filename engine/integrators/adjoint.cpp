// Adjoint integrators: path replay backpropagation (prb, Vicini et al. 2021) and radiative
// backpropagation (rb, Nimier-David et al. 2020). Both run the primal path loop of engine/integrators/path.h
// with an observer that receives every contribution the estimator makes and calls the derivative
// shaders; nothing is stored per sample or per vertex.
#include <tbb/enumerable_thread_specific.h>

#include <atomic>
#include <limits>

#include "engine/dist/dist.h"
#include "engine/integrators/path.h"
#include "engine/integrators/render.h"
#include "engine/io/progress.h"

namespace bl {

namespace {

// Path replay. The estimator is a sum of contributions, each a product of the factors met along
// the path. Given δ (the adjoint of this sample's radiance):
//  - emission: contribution = (β w) Le → δ·β·w flows into Le;
//  - NEE: contribution = β f Le w / p → δ·β·Le·w/p into f, δ·β·f·w/p into Le;
//  - BSDF sample at a vertex: every later contribution carries the factor f/pdf, so
//    ∂(rest)/∂f = rest / f with rest = L − (radiance so far) (the "radiance to come").
// Sampling decisions (directions, pdfs, MIS weights, roulette) are constants, matching the
// detached convention of the primal loop. A vertex colour multiplies the colour texture a BSDF
// reads, so that texture receives the BSDF's colour gradient times the colour (the tint the
// vertex record carries to Material::texture_backprop).
// Media (differential delta and ratio tracking, Nimier-David et al. 2022), with rest = L − radiance
// so far:
//  - a tentative collision of delta tracking multiplies everything after it by σ_t/σ_t (real) or
//    (σ̄ − σ_t)/(σ̄ − σ_t) (null), 1 in value: ∂σ_t gets ⟨δ, rest⟩/σ_t or −⟨δ, rest⟩/(σ̄ − σ_t);
//  - a medium vertex multiplies its light sample and everything after by the albedo (δ·rest/albedo
//    per channel) and the continuation by p(wi, wo)/pdf (⟨δ, rest after its light sample⟩ ∂log p);
//  - a light sample through media carries T = Π(1 − σ_t/σ̄): each point of the shadow ray gets
//    −⟨δ, contribution⟩/(σ̄ − σ_t), found by tracking the same ray again with the same numbers.
struct ReplayObserver {
  static constexpr bool kActive = true;
  static constexpr bool kZeroChannels = false;
  void surface(int, const Ray&, const Hit&, const SurfacePoint&) {}
  const Scene& scene;
  GradientAccumulator& grads;
  Vec3f delta;                // ∂loss/∂(this sample's radiance)
  Vec3f total_radiance;       // this sample's primal estimate, from the first run of the same path
  VisibilityBits visibility;  // that run's shadow-ray answers
  // The last vertex at which that run met a derivative site: later iterations add nothing.
  int last_site = std::numeric_limits<int>::max();
  bool media_grads = true;  // whether shadow rays through media carry derivatives
  // The tentative collisions of the shadow ray being tracked (per-thread scratch, reused).
  std::vector<ShadowPoint>* shadow_points = nullptr;
  // That run's ZeroChannels radiance: what the rest of the path carries in a channel from its
  // first zero factor on, that factor taken as 1 (the derivative at that vertex).
  Vec3f zero_channel_radiance{0.f};
  ZeroChannelMask zero_mask;

  void begin_shadow() { shadow_points->clear(); }
  void shadow_point(const ShadowPoint& p) {
    if (media_grads) shadow_points->push_back(p);
  }

  // BSDF gradients of one vertex (from NEE and from the BSDF sample) are summed and pushed into
  // the textures once, when the path moves on: half the texel scatters of doing it per event.
  const VertexRef* pending = nullptr;
  VertexRef pending_ref;
  BsdfGradient pending_gradient;

  void add_bsdf_adjoint(const VertexRef& v, const Vec3f& wi, const Vec3f& adjoint) {
    if (!pending || pending_ref.vertex != v.vertex) {
      flush();
      pending_ref = v;
      pending = &pending_ref;
      pending_gradient = {};
    }
    pending_gradient += v.material->bsdf_backprop(*v.value, v.wo, wi, adjoint);
  }
  // Must be called once the path is done.
  void flush() {
    flush_real();
    if (pending)
      pending_ref.material->texture_backprop(scene.params, pending_ref.uv, pending_gradient, grads, pending_ref.tint);
    pending = nullptr;
  }

  void emission(const EmissionRef& e, const Vec3f& weight, const Vec3f&) {
    emitter_backprop(scene, e, delta * weight, grads);
  }
  template <class Blocked>
  bool occluded(int vertex, Blocked&& query) {
    return replay_occluded(visibility, vertex, query);
  }
  bool nee_may_contribute(int vertex) const { return replay_nee_may_contribute(visibility, vertex); }
  bool follows(int vertex) const { return vertex <= last_site; }
  void reached(int, int) {}
  void tracked(int) {}
  void nee(const VertexRef& v, const Vec3f& wi, const EmissionRef& e, const Vec3f& bsdf_weight,
           const Vec3f& emitter_weight, const Vec3f&) {
    if (v.material->wants_grad(grads)) add_bsdf_adjoint(v, wi, delta * bsdf_weight);
    emitter_backprop(scene, e, delta * emitter_weight, grads);
  }
  // A real collision's score term waits for its vertex's light sample when light derivatives
  // leave that sample out of it (medium_light_derivative in path.h).
  struct PendingReal {
    const Medium* medium = nullptr;
    Vec3f x;
    float sigma = 0.f, rest = 0.f;
  } pending_real;
  void flush_real() {
    if (pending_real.medium && pending_real.rest != 0.f)
      pending_real.medium->backprop_sigma_t(scene.params, pending_real.x, pending_real.rest / pending_real.sigma,
                                            grads);
    pending_real.medium = nullptr;
  }
  bool light_derivatives(const Medium& m, const ParamStore& params) const {
    return m.light_derivatives > 0.f && m.wants_sigma_grad(params);
  }
  void flight_light(const Medium& m, const Vec3f& x, const Vec3f& weighted) {
    const float w = dot(delta, weighted);
    if (w != 0.f) m.backprop_sigma_t(scene.params, x, w, grads);
  }
  void flight_collision(const Medium& m, const Vec3f& x, float sigma, float majorant, bool real,
                        const Vec3f& radiance_so_far) {
    if (!m.wants_sigma_grad(scene.params)) return;
    const float rest = dot(delta, total_radiance - radiance_so_far);
    if (real && light_derivatives(m, scene.params) && m.light_derivative_at(sigma, majorant)) {
      pending_real = {&m, x, sigma, rest};
      return;
    }
    if (rest == 0.f) return;
    if (real)
      m.backprop_sigma_t(scene.params, x, rest / sigma, grads);
    else if (majorant > sigma)
      m.backprop_sigma_t(scene.params, x, -rest / (majorant - sigma), grads);
  }
  void medium_nee(const Medium& m, const Vec3f&, const Vec3f& wi, const Vec3f& wl, float phase_value,
                  const EmissionRef& e, const Vec3f& emitter_weight, const Vec3f& contribution) {
    emitter_backprop(scene, e, delta * emitter_weight, grads);
    const float weight = dot(delta, contribution);
    if (pending_real.medium) pending_real.rest -= weight;
    if (weight == 0.f) return;
    if (phase_value > 0.f) m.backprop_phase(scene.params, wi, wl, weight / phase_value, grads);
    shadow_transmittance_backprop(scene, *shadow_points, weight, grads);
  }
  void medium_vertex(const Medium& m, const Vec3f& x, const Vec3f& wi, const Vec3f& wo, const Vec3f& albedo,
                     const Vec3f& radiance_before, const Vec3f& radiance_after_nee) {
    flush_real();
    const Vec3f rest = total_radiance - radiance_before;
    bool first_zero[3];
    zero_mask.mark(albedo, first_zero);
    Vec3f adjoint;
    for (int c = 0; c < 3; ++c)
      adjoint[c] = albedo[c] != 0.f ? delta[c] * rest[c] / albedo[c]
                   : first_zero[c]  ? delta[c] * zero_channel_radiance[c]
                                    : 0.f;
    m.backprop_albedo(scene.params, x, adjoint, grads);
    const float continuation = dot(delta, total_radiance - radiance_after_nee);
    if (continuation != 0.f) {
      const float p = hg_eval(m.phase<float>(scene.params), wi, wo);
      if (p > 0.f) m.backprop_phase(scene.params, wi, wo, continuation / p, grads);
    }
  }
  void shadow(const Vec3f& contribution) {
    shadow_transmittance_backprop(scene, *shadow_points, dot(delta, contribution), grads);
  }
  void scatter(const VertexRef& v, const Vec3f& wi, const Vec3f& f, float, float, const Vec3f&,
               const Vec3f& radiance_so_far, int, const Ray&) {
    bool first_zero[3];
    zero_mask.mark(f, first_zero);  // at every vertex, whether or not it wants a gradient
    if (!v.material->wants_grad(grads)) return;
    const Vec3f radiance_to_come = total_radiance - radiance_so_far;
    Vec3f adjoint;
    for (int c = 0; c < 3; ++c)
      adjoint[c] = f[c] != 0.f     ? delta[c] * radiance_to_come[c] / f[c]
                   : first_zero[c] ? delta[c] * zero_channel_radiance[c]
                                   : 0.f;
    add_bsdf_adjoint(v, wi, adjoint);
  }
};

// Radiative backpropagation: at each BSDF sample the incident radiance the derivative needs is
// estimated by an independent path (its own random numbers), so the cost is quadratic in depth.
// Emission and NEE terms are local and handled exactly as in replay.
struct RadiativeObserver {
  static constexpr bool kActive = true;
  static constexpr bool kZeroChannels = false;
  void surface(int, const Ray&, const Hit&, const SurfacePoint&) {}
  const Scene& scene;
  GradientAccumulator& grads;
  Vec3f delta;
  uint64_t seed, pixel, sample;
  VisibilityBits visibility;
  int last_site;
  ReplayObserver local{scene, grads, delta, Vec3f(0.f), visibility};

  void emission(const EmissionRef& e, const Vec3f& w, const Vec3f& c) { local.emission(e, w, c); }
  void nee(const VertexRef& v, const Vec3f& wi, const EmissionRef& e, const Vec3f& bw, const Vec3f& ew,
           const Vec3f& c) {
    local.nee(v, wi, e, bw, ew, c);
  }
  void scatter(const VertexRef& v, const Vec3f& wi, const Vec3f&, float pdf, float q, const Vec3f& beta_before,
               const Vec3f&, int vertex, const Ray& next) {
    if (!v.material->wants_grad(grads)) return;
    PathSampler independent(mix64(seed ^ 0x5eed0fadull) + uint64_t(vertex), pixel, sample);
    NoObserver none;
    Vec3f incident = trace_path<float>(scene, PathStart{next, vertex + 1, pdf}, independent, none);
    local.add_bsdf_adjoint(v, wi, delta * beta_before * incident / (pdf * q));
  }
  void flush() { local.flush(); }
  // rb refuses scenes with media (compute_gradient): its independent estimates would start in
  // the wrong medium.
  void flight_collision(const Medium&, const Vec3f&, float, float, bool, const Vec3f&) {}
  void flight_light(const Medium&, const Vec3f&, const Vec3f&) {}
  bool light_derivatives(const Medium&, const ParamStore&) const { return false; }
  void medium_vertex(const Medium&, const Vec3f&, const Vec3f&, const Vec3f&, const Vec3f&, const Vec3f&,
                     const Vec3f&) {}
  void medium_nee(const Medium&, const Vec3f&, const Vec3f&, const Vec3f&, float, const EmissionRef&, const Vec3f&,
                  const Vec3f&) {}
  void begin_shadow() {}
  void shadow_point(const ShadowPoint&) {}
  void shadow(const Vec3f&) {}
  template <class Blocked>
  bool occluded(int vertex, Blocked&& query) {
    return replay_occluded(visibility, vertex, query);
  }
  bool nee_may_contribute(int vertex) const { return replay_nee_may_contribute(visibility, vertex); }
  bool follows(int vertex) const { return vertex <= last_site; }
  void reached(int, int) {}
  void tracked(int) {}
};

}  // namespace

PassStats backward(Scene& scene, const PassOptions& o, AdjointMethod method, const PixelAdjoint& adjoint,
                   Image* image_out) {
  const Camera& cam = scene.cameras.at(size_t(o.camera));
  if (image_out) *image_out = Image(cam.width, cam.height, 3);
  GradientSink sink(scene.params);
  // Per-thread scratch for one pixel's samples: radiance and shadow-ray answers of each (reused
  // from pixel to pixel; nothing is allocated per sample or per vertex).
  struct SampleRecord {
    Vec3f radiance, zero_channel_radiance;  // the latter: ZeroChannels (path.h)
    VisibilityBits visibility;
    int last_site = 0;
  };
  struct Scratch {
    std::vector<SampleRecord> records;
    std::vector<ShadowPoint> shadow_points;  // one shadow ray's tentative collisions
  };
  // Where derivatives can arise; replays stop after a path's last such vertex (and paths that
  // never meet one are not replayed at all). The gradient is the same: what is skipped adds
  // nothing.
  const DerivativeSites sites = derivative_sites(scene, GradientAccumulator(&scene.params));
  const bool media_grads = sites.tracking;
  tbb::enumerable_thread_specific<Scratch> scratch([&] {
    return Scratch{std::vector<SampleRecord>(size_t(o.spp)), {}};
  });
  Progress progress(method == AdjointMethod::Prb ? "prb" : "rb", owned_pixels(cam.width, cam.height) * uint64_t(o.spp),
                    "spp", o.progress);
  progress.set_ranks(dist::size());
  std::atomic<uint64_t> rays{0};
  for_each_tile(
      cam.width, cam.height,
      [&](int x0, int y0, int x1, int y1) {
        const uint64_t rays_before = Geometry::thread_ray_count();
        GradientAccumulator& grads = sink.local();
        Scratch& thread_scratch = scratch.local();
        std::vector<SampleRecord>& records = thread_scratch.records;
        for (int y = y0; y < y1; ++y)
          for (int x = x0; x < x1; ++x) {
            if (cancelled(o.cancel)) continue;
            const uint64_t pixel = uint64_t(y) * uint64_t(cam.width) + uint64_t(x);
            CameraPacket packet;  // camera rays as render() traces them
            // 1. Primal estimates of this pixel's samples.
            Vec3d sum(0.0);  // the same summation as render(), so both give the same image
            for (int s0 = 0; s0 < o.spp; s0 += Geometry::kPacket) {
              const int n = std::min(Geometry::kPacket, o.spp - s0);
              packet.trace(scene, cam, o.seed, x, y, n, [&](int k) { return s0 + k; });
              for (int k = 0; k < n; ++k) {
                const int s = s0 + k;
                const PathSampler sampler(o.seed, pixel, uint64_t(s));
                VisibilityRecorder recorder;
                recorder.sites = o.replay_whole_paths ? nullptr : &sites;
                records[size_t(s)].radiance = trace_path<float>(scene, packet.start(k), sampler, recorder);
                records[size_t(s)].visibility = recorder.bits;
                records[size_t(s)].zero_channel_radiance = recorder.zero_channel_radiance;
                records[size_t(s)].last_site =
                    o.replay_whole_paths ? std::numeric_limits<int>::max() : recorder.last_site;
                sum += Vec3d(records[size_t(s)].radiance);
              }
            }
            const Vec3f value(sum / double(o.spp));
            if (image_out)
              for (int c = 0; c < 3; ++c) image_out->at(x, y, c) = value[c];
            // 2. δ per sample: the film's transpose (box filter, mean over spp).
            const Vec3f delta = adjoint(size_t(pixel), value) / float(o.spp);
            if (is_zero(delta)) continue;
            // 3. Transport δ back through the scene: the samples whose paths can produce a derivative
            // (a vertex at or before their last site), their camera rays a packet at a time.
            int replayed[Geometry::kPacket];
            for (int s_next = 0; s_next < o.spp;) {
              int n = 0;
              for (; s_next < o.spp && n < Geometry::kPacket; ++s_next)
                if (records[size_t(s_next)].last_site >= 1) replayed[n++] = s_next;
              if (n == 0) break;
              packet.trace(scene, cam, o.seed, x, y, n, [&](int k) { return replayed[k]; });
              for (int k = 0; k < n; ++k) {
                const int s = replayed[k];
                const SampleRecord& record = records[size_t(s)];
                const PathSampler sampler(o.seed, pixel, uint64_t(s));
                if (method == AdjointMethod::Prb) {
                  ReplayObserver replay{scene,
                                        grads,
                                        delta,
                                        record.radiance,
                                        record.visibility,
                                        record.last_site,
                                        media_grads,
                                        &thread_scratch.shadow_points,
                                        record.zero_channel_radiance};
                  trace_path<float>(scene, packet.start(k), sampler, replay);
                  replay.flush();
                } else {
                  RadiativeObserver rb{
                      scene, grads, delta, o.seed, pixel, uint64_t(s), record.visibility, record.last_site,
                  };
                  trace_path<float>(scene, packet.start(k), sampler, rb);
                  rb.flush();
                }
              }
            }
          }
        rays += Geometry::thread_ray_count() - rays_before;
        progress.advance(uint64_t(x1 - x0) * uint64_t(y1 - y0) * uint64_t(o.spp));
      },
      o.cancel);
  progress.finish();
  sink.reduce();
  if (image_out) dist::complete_image(*image_out);
  PassStats stats;
  stats.seconds = progress.elapsed();
  stats.samples = uint64_t(cam.width) * uint64_t(cam.height) * uint64_t(o.spp);
  stats.rays = dist::sum(rays.load());
  return stats;
}

}  // namespace bl
