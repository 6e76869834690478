#include "engine/core/distribution.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace bl {

void Distribution1D::build(const std::vector<double>& weights) {
  const size_t n = weights.size();
  cdf.assign(n + 1, 0.0);
  double sum = 0.0;
  for (double w : weights) sum += std::max(0.0, w);  // std::max(0.0, NaN) is 0
  if (!std::isfinite(sum)) throw std::invalid_argument("Distribution1D: the weights' sum is not finite");
  total = sum;
  const bool uniform = !(sum > 0.0);
  const double norm = uniform ? double(n) : sum;
  // Normalised running sums: the last non-empty bin ends at sum / sum = 1 exactly (the same
  // additions in the same order), so no probability is moved onto trailing empty bins.
  double running = 0.0;
  for (size_t i = 0; i < n; ++i) {
    running += uniform ? 1.0 : std::max(0.0, weights[i]);
    cdf[i + 1] = running / norm;
  }
  if (n > 0) cdf[n] = 1.0;
}

size_t Distribution1D::sample(double u, float* u_remapped) const {
  const size_t n = size();
  size_t i = size_t(std::upper_bound(cdf.begin() + 1, cdf.end(), u) - cdf.begin()) - 1;
  // Only for u ≥ 1 (not a sampler's value): the last bin that is not empty.
  i = std::min(i, n - 1);
  while (i > 0 && !(cdf[i + 1] > cdf[i])) --i;
  if (u_remapped) {
    const double w = cdf[i + 1] - cdf[i];
    const float r = w > 0.0 ? float((u - cdf[i]) / w) : 0.f;
    *u_remapped = std::clamp(r, 0.f, std::nextafter(1.f, 0.f));
  }
  return i;
}

}  // namespace bl
