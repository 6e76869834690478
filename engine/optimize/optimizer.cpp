#include "engine/optimize/optimizer.h"

#include <algorithm>
#include <cmath>

namespace bl {

void Adam::reset(size_t size) {
  m.assign(size, 0.f);
  v.assign(size, 0.f);
  t_ = 0;
}

double Adam::current_learning_rate() const {
  if (s_.decay == "exponential") return s_.learning_rate * std::pow(s_.decay_rate, double(global_t_));
  if (s_.decay == "step" && s_.decay_every > 0)
    return s_.learning_rate * std::pow(s_.decay_rate, double(global_t_ / s_.decay_every));
  return s_.learning_rate;
}

void Adam::step(std::vector<float>& value, const std::vector<float>& gradient) {
  if (m.size() != value.size()) reset(value.size());
  const double lr = current_learning_rate();
  ++t_;
  ++global_t_;
  const double correction1 = 1.0 - std::pow(s_.beta1, double(t_));
  const double correction2 = 1.0 - std::pow(s_.beta2, double(t_));
  for (size_t i = 0; i < value.size(); ++i) {
    const double g = gradient[i];
    const double mi = s_.beta1 * m[i] + (1.0 - s_.beta1) * g;
    const double vi = s_.beta2 * v[i] + (1.0 - s_.beta2) * g * g;
    m[i] = float(mi);
    v[i] = float(vi);
    const double update = lr * (mi / correction1) / (std::sqrt(vi / correction2) + s_.epsilon);
    value[i] = std::clamp(float(double(value[i]) - update), s_.lower, s_.upper);
  }
}

}  // namespace bl
