#include "engine/core/params.h"

#include <cstdlib>

#include "engine/core/errors.h"
#include "engine/core/limits.h"

namespace bl {

int ParamStore::add(Param p, const std::string& where) {
  if (find(p.name) >= 0) throw InputError("duplicate parameter name '" + p.name + "'");
  uint64_t total = total_values_;
  limits::add_to_total(where, "total parameter size (values of all parameters)", total, p.value.size(),
                       limits::kParamValues);
  total_values_ = total;
  p.grad.assign(p.value.size(), 0.f);
  index_.emplace(p.name, int(params_.size()));
  params_.push_back(std::move(p));
  return int(params_.size() - 1);
}

int ParamStore::find(const std::string& name) const {
  const auto it = index_.find(name);
  return it == index_.end() ? -1 : it->second;
}

std::string ParamStore::shape_string(int handle) const {
  std::string s = "[";
  const auto& shape = params_[size_t(handle)].shape;
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? "," : "") + std::to_string(shape[i]);
  return s + "]";
}

size_t small_param_limit() {
  static const size_t limit = [] {
    const char* v = std::getenv("BACKLIGHT_SMALL_PARAM_LIMIT");
    return v ? size_t(std::strtoull(v, nullptr, 10)) : kSmallParamLimit;
  }();
  return limit;
}

void ParamStore::require_grad(const std::vector<std::string>& names) {
  for (auto& p : params_) p.requires_grad = names.empty() && !p.geometry;
  for (const auto& n : names) {
    int h = find(n);
    if (h < 0) throw InputError("unknown parameter '" + n + "' (see `backlight params`)");
    params_[size_t(h)].requires_grad = true;
  }
  small_total_ = 0;
  size_t flat = 0;
  for (auto& p : params_) {
    p.small = p.size() <= small_param_limit();
    p.small_offset = p.small ? small_total_ : 0;
    if (p.small) small_total_ += p.size();
    p.tape_offset = flat;
    flat += p.size();
  }
  zero_grad();
}

bool ParamStore::wants_geometry() const {
  for (const auto& p : params_)
    if (p.geometry && p.requires_grad) return true;
  return false;
}

void ParamStore::zero_grad() {
  for (auto& p : params_) p.grad.assign(p.value.size(), 0.f);
}

void GradientSink::reduce() {
  std::vector<double> total(store_.small_total(), 0.0);
  for (auto& acc : per_thread_)
    for (size_t i = 0; i < total.size(); ++i) total[i] += acc.small()[i];
  for (auto& p : store_.all())
    if (p.small && p.requires_grad)
      for (size_t i = 0; i < p.size(); ++i) p.grad[i] += float(total[p.small_offset + i]);
  per_thread_.clear();
}

}  // namespace bl
