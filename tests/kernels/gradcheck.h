#pragma once
// Derivative shaders against central finite differences of their own eval (in double precision).
//
// A derivative shader returns ⟨adjoint, ∂eval/∂p⟩ for every scalar input p. The reference is
//   (⟨adjoint, eval<double>(p + h)⟩ − ⟨adjoint, eval<double>(p − h)⟩) / 2h
// with h ≈ 1e-4 |p|: small enough that truncation error (∝ h²) is negligible, large enough that
// double rounding (∝ 1e-16 / h) is too. The shader runs in float, so gradients are compared
// relative to the norm of the whole gradient vector, with a small absolute floor.
#include <algorithm>
#include <cmath>
#include <sstream>
#include <string>
#include <vector>

#include "engine/core/math.h"
#include "engine/core/params.h"

namespace bl::test {

inline double relative_step(double x, double rel = 1e-4, double min_step = 1e-6) {
  return std::max(rel * std::abs(x), min_step);
}

// d f / d x at x by central differences, f: double → double.
template <class F>
double central_difference(const F& f, double x, double rel = 1e-4) {
  const double h = relative_step(x, rel);
  return (f(x + h) - f(x - h)) / (2.0 * h);
}

// Derivative of f() with respect to the float stored at p.value[index]. The perturbed values are
// rounded to float, so the quotient divides by the step that was actually taken.
template <class F>
double central_difference_of_param(Param& p, size_t index, const F& f, double rel = 1e-4) {
  const float original = p.value[index];
  const double h = relative_step(original, rel);
  const float up = float(double(original) + h), down = float(double(original) - h);
  p.value[index] = up;
  const double f_up = f();
  p.value[index] = down;
  const double f_down = f();
  p.value[index] = original;
  return (f_up - f_down) / (double(up) - double(down));
}

// ⟨adjoint, v⟩ for an RGB value of any scalar with a value_of.
template <class T>
double adjoint_dot(const Vec3f& adjoint, const Spectrum<T>& v) {
  return double(adjoint.x) * double(v.x) + double(adjoint.y) * double(v.y) + double(adjoint.z) * double(v.z);
}

struct GradientComparison {
  bool ok = true;
  double worst_ratio = 0.0;  // max |analytic − numeric| / allowed; ≤ 1 passes
  std::string report;
};

// Every component must satisfy |analytic − numeric| ≤ rel · ‖numeric‖₂ + abs_floor.
inline GradientComparison compare_gradients(const std::vector<double>& analytic, const std::vector<double>& numeric,
                                            const std::vector<std::string>& names, double rel, double abs_floor) {
  GradientComparison c;
  double norm = 0.0;
  for (double g : numeric) norm += g * g;
  norm = std::sqrt(norm);
  const double allowed = rel * norm + abs_floor;
  std::ostringstream o;
  o.precision(9);
  o << "gradient norm " << norm << ", allowed error " << allowed << "\n";
  for (size_t k = 0; k < analytic.size(); ++k) {
    const double error = std::abs(analytic[k] - numeric[k]);
    c.worst_ratio = std::max(c.worst_ratio, error / allowed);
    if (error > allowed) {
      c.ok = false;
      o << "  " << (k < names.size() ? names[k] : std::to_string(k)) << ": backprop " << analytic[k]
        << " finite difference " << numeric[k] << " (error " << error << ")\n";
    }
  }
  c.report = o.str();
  return c;
}

// Runs `backprop(GradientAccumulator&)` through a fresh GradientSink — the renderer's path: small
// parameters accumulate per thread in double and are reduced, large ones take atomic adds — and
// returns the parameter's gradient buffer. The store must have had require_grad called.
template <class F>
std::vector<double> gradient_through_sink(ParamStore& store, int handle, const F& backprop) {
  store.zero_grad();
  GradientSink sink(store);
  backprop(sink.local());
  sink.reduce();
  const Param& p = store[handle];
  return std::vector<double>(p.grad.begin(), p.grad.end());
}

}  // namespace bl::test
