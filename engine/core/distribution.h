#pragma once
// Piecewise-constant 1D distribution sampled by inverting its CDF: the triangles of an area
// emitter by area, the rows and columns of an environment map by luminance.
//
// The CDF is kept in double and inverted with a 53-bit uniform (PathSampler::get_double): with
// float CDFs and 24-bit uniforms the probability a bin was drawn with was the CDF's float step, not
// its weight — off by 2.6e-2 rms (11% at worst) for the triangles of a 10⁶-triangle emitter, by
// 1.7e-2 rms over the columns of a 65536-wide sky with a sun, where 2508 columns of positive
// weight were never drawn — while the pdf of every sample assumed the weights: a biased estimate.
// In double a bin of probability p is drawn with probability p ± 4·2⁻⁵³ (a few roundings of the
// running sums; test_sampler checks every bin).
#include <cstddef>
#include <vector>

namespace bl {

struct Distribution1D {
  std::vector<double> cdf;  // size n + 1: cdf[0] = 0, cdf[n] = 1, non-decreasing (an empty bin repeats)
  double total = 0.0;       // the sum of the weights (negative ones and NaN count as 0)

  // Weights ≤ 0 (or NaN) give empty bins; all empty: uniform over the bins. The weights and their
  // sum must be finite (an infinite one would make the CDF NaN): callers' inputs are validated
  // finite (parameters, areas), and build throws std::invalid_argument otherwise.
  void build(const std::vector<double>& weights);
  size_t size() const { return cdf.empty() ? 0 : cdf.size() - 1; }
  // The probability of bin i: the CDF's step, what sample draws it with (to 4·2⁻⁵³), as a float.
  float pmf(size_t i) const { return float(cdf[i + 1] - cdf[i]); }
  // n ≥ 1. The bin with cdf[i] ≤ u < cdf[i + 1] (never an empty one) for u in [0, 1); u's position in it,
  // rescaled to [0, 1), goes to *u_remapped.
  size_t sample(double u, float* u_remapped) const;
};

}  // namespace bl
