#include "engine/optimize/optimizer.h"

#include <algorithm>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

namespace bl {

void to_log_space(std::vector<float>& value, std::vector<float>& grad) {
  for (size_t i = 0; i < value.size(); ++i) {
    const float x = std::max(value[i], kLogFloor);
    grad[i] *= x;
    value[i] = std::log(x);
  }
}

void Adam::reset(size_t size) {
  if (s_.bf16_moments) {
    m16.assign(size, 0);
    v16.assign(size, 0);
  } else {
    m.assign(size, 0.f);
    v.assign(size, 0.f);
  }
  t_ = 0;
}

double Adam::current_learning_rate() const {
  double lr = s_.learning_rate;
  if (s_.decay == "exponential") lr *= std::pow(s_.decay_rate, double(global_t_));
  if (s_.decay == "step" && s_.decay_every > 0) lr *= std::pow(s_.decay_rate, double(global_t_ / s_.decay_every));
  if (s_.warmup > 0 && t_ < s_.warmup) lr *= double(t_ + 1) / double(s_.warmup);
  return lr;
}

namespace {
// 32 well-mixed bits of a 64-bit key (splitmix64's finaliser): the stochastic-rounding bits of
// one element at one step, the same for every thread count and after a resume.
uint32_t mix32(uint64_t x) {
  x ^= x >> 33;
  x *= 0xff51afd7ed558ccdull;
  x ^= x >> 33;
  x *= 0xc4ceb9fe1a85ec53ull;
  x ^= x >> 33;
  return uint32_t(x);
}
}  // namespace

void Adam::step(std::vector<float>& value, const std::vector<float>& gradient, bool uniform_allowed) {
  if (state_size() != value.size()) reset(value.size());
  const double lr = current_learning_rate();
  ++t_;
  ++global_t_;
  const double correction1 = 1.0 - std::pow(s_.beta1, double(t_));
  const double correction2 = 1.0 - std::pow(s_.beta2, double(t_));
  const bool half = s_.bf16_moments;
  const uint64_t step_key = uint64_t(uint32_t(global_t_)) << 32;
  // New moments of element i, stored, and returned as the step uses them.
  auto moments = [&](size_t i, double& mi, double& vi) {
    const double g = gradient[i];
    const double m_old = half ? bf16_to_float(m16[i]) : m[i];
    const double v_old = half ? bf16_to_float(v16[i]) : v[i];
    mi = s_.beta1 * m_old + (1.0 - s_.beta1) * g;
    vi = s_.beta2 * v_old + (1.0 - s_.beta2) * g * g;
    if (half) {
      const uint32_t r = mix32(step_key ^ uint64_t(i));
      m16[i] = float_to_bf16(float(mi), uint16_t(r));
      v16[i] = float_to_bf16(float(vi), uint16_t(r >> 16));
      // The step uses the stored moments, so a resumed run continues bit for bit.
      mi = bf16_to_float(m16[i]);
      vi = bf16_to_float(v16[i]);
    } else {
      m[i] = float(mi);
      v[i] = float(vi);
    }
  };
  const size_t grain = size_t(1) << 14;
  if (!s_.uniform || !uniform_allowed) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, value.size(), grain), [&](const auto& range) {
      for (size_t i = range.begin(); i != range.end(); ++i) {
        double mi, vi;
        moments(i, mi, vi);
        const double update = lr * (mi / correction1) / (std::sqrt(vi / correction2) + s_.epsilon);
        value[i] = std::clamp(float(double(value[i]) - update), s_.lower, s_.upper);
      }
    });
    return;
  }
  // Uniform: one second moment for the whole parameter, the largest element's, so every element
  // steps by the same scale and a preconditioned gradient keeps its shape (see AdamSettings).
  std::vector<double> first(value.size());
  const double vmax = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, value.size(), grain), 0.0,
      [&](const auto& range, double acc) {
        for (size_t i = range.begin(); i != range.end(); ++i) {
          double vi;
          moments(i, first[i], vi);
          acc = std::max(acc, vi);
        }
        return acc;
      },
      [](double a, double b) { return std::max(a, b); });
  const double denominator = std::sqrt(vmax / correction2) + s_.epsilon;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, value.size(), grain), [&](const auto& range) {
    for (size_t i = range.begin(); i != range.end(); ++i) {
      const double update = lr * (first[i] / correction1) / denominator;
      value[i] = std::clamp(float(double(value[i]) - update), s_.lower, s_.upper);
    }
  });
}

}  // namespace bl
