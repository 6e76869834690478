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

#include "engine/sampler.h"
#include "engine/scene.h"

namespace bl {

// Where emitted radiance came from: an area emitter (index, uv) or the environment (direction).
struct EmissionRef {
  int area = -1;  // index into Scene::area_emitters; -1 = environment
  Vec2f uv;
  Vec3f direction;  // for the environment: direction towards it
};

// What a derivative shader needs about a scattering vertex.
struct VertexRef {
  const Material* material = nullptr;
  const BsdfValue<float>* value = nullptr;  // the material's textures evaluated at uv (detached)
  Vec2f uv;
  Vec3f wo;  // local shading frame
  int vertex = 0;
};

// Observer that ignores everything (primal and taped modes).
struct NoObserver {
  static constexpr bool kActive = false;
  void emission(const EmissionRef&, const Vec3f&, const Vec3f&) {}
  void nee(const VertexRef&, const Vec3f&, const EmissionRef&, const Vec3f&, const Vec3f&, const Vec3f&) {}
  void scatter(const VertexRef&, const Vec3f&, const Vec3f&, float, float, const Vec3f&, const Vec3f&, int,
               const Ray&) {}
  // The shadow-ray query of next-event estimation at surface vertex `vertex`.
  bool occluded(const Scene& scene, int, const Vec3f& origin, const Vec3f& direction, float tmax) {
    return scene.geometry->occluded(origin, direction, tmax);
  }
};

// Shadow-ray answers of one path, one bit per surface vertex. The adjoint pass records them while
// computing a sample's radiance and hands them to the replay of the same sample: the answers are a
// function of the same random numbers, so the replay need not cast its shadow rays again.
struct VisibilityBits {
  static constexpr int kVertices = 64;  // deeper vertices are queried again
  uint64_t queried = 0, blocked = 0;
};

// First run of a path in the adjoint pass: no events, shadow-ray answers recorded.
struct VisibilityRecorder : NoObserver {
  VisibilityBits bits;
  bool occluded(const Scene& scene, int vertex, const Vec3f& origin, const Vec3f& direction, float tmax) {
    const bool blocked = scene.geometry->occluded(origin, direction, tmax);
    if (vertex < VisibilityBits::kVertices) {
      bits.queried |= uint64_t(1) << vertex;
      if (blocked) bits.blocked |= uint64_t(1) << vertex;
    }
    return blocked;
  }
};

// Replay side: answers from the recorded bits when present.
inline bool replay_occluded(const Scene& scene, const VisibilityBits& bits, int vertex, const Vec3f& origin,
                            const Vec3f& direction, float tmax) {
  if (vertex < VisibilityBits::kVertices && (bits.queried >> vertex & 1u)) return (bits.blocked >> vertex & 1u) != 0;
  return scene.geometry->occluded(origin, direction, tmax);
}

inline float power_heuristic(float a, float b) {
  float a2 = a * a, b2 = b * b;
  return a2 + b2 > 0.f ? a2 / (a2 + b2) : 0.f;
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
};

// Traces one path and returns its radiance estimate. Observer events (float values only):
//  emission(ref, weight, contribution)      contribution = weight · Le, weight = β · w_mis
//  nee(vertex, wi, ref, bsdf_adjoint_w, emitter_adjoint_w, contribution)
//      contribution = β f Le w / p_light; bsdf_adjoint_w = β Le w / p_light; emitter_adjoint_w = β f w / p_light
//  scatter(vertex, wi, f, pdf, q, beta_before, radiance_so_far, vertex_index, next_ray)
//      after the BSDF sample and roulette survived: β ← β f / (pdf q)
template <class T, class Observer>
Spectrum<T> trace_path(const Scene& scene, const PathStart& start, const PathSampler& sampler, Observer& observer) {
  const IntegratorSettings& st = scene.settings;
  const ParamStore& params = scene.params;
  const float select_pdf = scene.emitter_select_probability();
  const int area_count = int(scene.area_emitters.size());
  Spectrum<T> radiance(T(0.f)), beta(T(1.f));
  Ray ray = start.ray;
  float mis_bsdf_pdf = start.bsdf_pdf;

  for (int vertex = start.first_vertex;; ++vertex) {
    const Hit hit = scene.geometry->intersect(ray);
    const bool visible_emitter = !(vertex == 1 && st.hide_emitters);

    // Escaped: environment emission, MIS-weighted against environment sampling.
    if (hit.mesh < 0) {
      if (scene.environment.present && visible_emitter) {
        float w =
            mis_bsdf_pdf > 0.f ? power_heuristic(mis_bsdf_pdf, select_pdf * scene.environment.pdf(ray.direction)) : 1.f;
        Spectrum<T> contribution = beta * scene.environment.eval<T>(params, ray.direction) * w;
        radiance += contribution;
        if constexpr (Observer::kActive)
          observer.emission({-1, {}, ray.direction}, value_of(beta) * w, value_of(contribution));
      }
      break;
    }

    const SurfacePoint sp = scene.surface_point(hit, ray);
    const Mesh& mesh = scene.meshes[size_t(sp.mesh)];
    const Vec3f wo_world = -ray.direction;

    // Hit an area emitter: its emission, MIS-weighted against light sampling.
    if (mesh.emitter >= 0 && visible_emitter) {
      const AreaEmitter& emitter = scene.area_emitters[size_t(mesh.emitter)];
      float cos_shading = dot(sp.shading_normal, wo_world);
      if (cos_shading > 0.f) {
        float w = 1.f;
        if (mis_bsdf_pdf > 0.f)
          w = power_heuristic(mis_bsdf_pdf,
                              select_pdf * emitter.pdf(hit.t, std::abs(dot(sp.geometric_normal, wo_world))));
        Spectrum<T> contribution = beta * emitter.eval<T>(params, sp.uv, cos_shading) * w;
        radiance += contribution;
        if constexpr (Observer::kActive)
          observer.emission({mesh.emitter, sp.uv, {}}, value_of(beta) * w, value_of(contribution));
      }
    }

    // Max depth: a further segment would exceed it.
    if (st.max_depth >= 0 && vertex >= st.max_depth) break;

    const Material& material = scene.materials[size_t(mesh.material)];
    const BsdfValue<T> bsdf = material.at<T>(params, sp.uv);
    const BsdfValue<float> bsdf_detached = bsdf.detached();
    Vec3f normal = sp.shading_normal;
    if (material.two_sided && dot(normal, wo_world) < 0.f) normal = -normal;
    const Frame frame(normal);
    const Vec3f wo = frame.to_local(wo_world);
    const VertexRef vref{&material, &bsdf_detached, sp.uv, wo, vertex};

    // Next-event estimation: one emitter chosen uniformly, one point on it.
    if (area_count > 0 || scene.environment.present) {
      int chosen = std::min(int(sampler.get(Dim::at(vertex, Dim::kLightSelect)) * float(scene.emitter_count())),
                            scene.emitter_count() - 1);
      Vec2f u{sampler.get(Dim::at(vertex, Dim::kLightU)), sampler.get(Dim::at(vertex, Dim::kLightV))};
      EmitterSample es = chosen < area_count ? scene.sample_area_emitter(chosen, sp.p, u) : scene.environment.sample(u);
      if (es.pdf > 0.f) {
        const Vec3f wi = frame.to_local(es.wi);
        Spectrum<T> f = bsdf.eval(wo, wi);
        if (!is_zero(value_of(f))) {
          Vec3f origin = offset_origin(sp.p, sp.geometric_normal, es.wi);
          float tmax = std::isinf(es.distance) ? std::numeric_limits<float>::infinity()
                                               : length(es.point - origin) * (1.f - 1e-3f);
          if (!observer.occluded(scene, vertex, origin, es.wi, tmax)) {
            EmissionRef eref{chosen < area_count ? chosen : -1, es.uv, es.wi};
            Spectrum<T> emitted = chosen < area_count ? scene.area_emitters[size_t(chosen)].eval<T>(params, es.uv, 1.f)
                                                      : scene.environment.eval<T>(params, es.wi);
            float light_pdf = es.pdf * select_pdf;
            float w_over_pdf = power_heuristic(light_pdf, bsdf_detached.pdf(wo, wi)) / light_pdf;
            Spectrum<T> contribution = beta * f * emitted * w_over_pdf;
            radiance += contribution;
            if constexpr (Observer::kActive) {
              Vec3f b = value_of(beta) * w_over_pdf;
              observer.nee(vref, wi, eref, b * value_of(emitted), b * value_of(f), value_of(contribution));
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

    // Russian roulette on the detached throughput (Mitsuba's rule: after the BSDF sample at
    // surface vertex k ≥ rr_depth, continue with q = min(max β, 0.95)).
    float q = 1.f;
    if (st.rr_depth > 0 && vertex >= st.rr_depth) {
      q = std::min(max_component(value_of(beta)), 0.95f);
      if (!(sampler.get(Dim::at(vertex, Dim::kRoulette)) < q)) break;
      beta = beta * (1.f / q);
    }

    const Vec3f wi_world = frame.to_world(bs.wi);
    Ray next;
    next.origin = offset_origin(sp.p, sp.geometric_normal, wi_world);
    next.direction = wi_world;
    if constexpr (Observer::kActive)
      observer.scatter(vref, bs.wi, value_of(f), bs.pdf, q, beta_before, value_of(radiance), vertex, next);
    ray = next;
    mis_bsdf_pdf = bs.pdf;
  }
  return radiance;
}

}  // namespace bl
