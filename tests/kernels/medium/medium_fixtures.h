#pragma once
// Media for the tests of kernels/medium/ (test_medium_backprop.cpp, test_tracking.cpp): a Medium
// with the ParamStore holding its parameters, rays through it, and the taped mode's gradient of
// one estimate.
#include <algorithm>
#include <string>
#include <utility>
#include <vector>

#include "engine/core/tape.h"
#include "kernels/medium/medium.h"

namespace bl::test {

struct TestMedium {
  ParamStore store;
  Medium medium;
};

// Completes a medium whose parameter handles (density, scale, ...) are set in t.store, with
// medium.block and medium.headroom as the caller left them: named "fog", a grid when the density
// has shape [Z, Y, X, 1], every parameter wanting gradients, the majorants built. A grid fills a
// box that is not the unit cube, so that to_local scales and translates.
inline void prepare_test_medium(TestMedium& t) {
  Medium& m = t.medium;
  m.name = "fog";
  m.grid = t.store[m.density].shape.size() == 4;
  if (m.grid) m.bbox_min = {-1.f, 0.5f, 2.f}, m.bbox_max = {1.5f, 1.7f, 2.8f};
  t.store.require_grad({});
  m.prepare(t.store);
}

inline Vec3f to_world(const Medium& m, const Vec3f& local) { return m.bbox_min + local * (m.bbox_max - m.bbox_min); }

struct RaySegment {
  std::string label;
  Vec3f origin, direction;  // world space; the direction has unit length
  float length;             // may be infinite
};

// The part of [0, length] inside the medium: all of it for a homogeneous medium; for a grid, the
// part inside its box (a slab test of its own, not traverse_majorants').
inline std::pair<double, double> inside_interval(const Medium& m, const RaySegment& r) {
  double t0 = 0, t1 = r.length;
  if (!m.grid) return {t0, t1};
  for (int a = 0; a < 3; ++a) {
    double near = (double(m.bbox_min[a]) - r.origin[a]) / r.direction[a],
           far = (double(m.bbox_max[a]) - r.origin[a]) / r.direction[a];
    if (near > far) std::swap(near, far);
    t0 = std::max(t0, near), t1 = std::min(t1, far);
  }
  return {t0, std::max(t0, t1)};
}

// The gradient of y with respect to every parameter element (flat numbering), by the taped mode's
// reverse sweep.
inline void taped_gradient(const Tape& tape, const Var& y, std::vector<float>& adjoint, std::vector<double>& out) {
  std::fill(out.begin(), out.end(), 0.0);
  if (!y.active()) return;
  adjoint.assign(tape.size(), 0.f);
  adjoint[y.index] = 1.f;
  reverse_sweep(tape, adjoint, [&](uint32_t flat, float g) { out[flat] += double(g); });
}

}  // namespace bl::test
