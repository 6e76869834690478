#include "engine/core/params.h"

#include <algorithm>
#include <cstdlib>

#include <tbb/global_control.h>

#include "engine/core/errors.h"
#include "engine/core/limits.h"

namespace bl {

int ParamStore::add(Param p, const std::string& where) {
  // Parameter names become file names (<name>.grad.exr, params --dump): a '/' or a backslash in an
  // owner's name wrote outside the output folder (an absolute name replaced the folder).
  const bool control = std::any_of(p.name.begin(), p.name.end(),
                                   [](char c) { return static_cast<unsigned char>(c) < 0x20 || c == 0x7f; });
  if (p.name.empty() || p.name.front() == '.' || p.name.find_first_of("/\\") != std::string::npos || control)
    throw InputError(where + ": parameter name '" + (control ? std::string("(with a control character)") : p.name) +
                     "': names must not be empty or contain '/', '\\' or control characters (they become file names)");
  if (find(p.name) >= 0) throw InputError(where + ": duplicate parameter name '" + p.name + "'");
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

namespace {
size_t env_size(const char* name, size_t fallback) {
  const char* v = std::getenv(name);
  return v ? size_t(std::strtoull(v, nullptr, 10)) : fallback;
}
}  // namespace

size_t small_param_limit() {
  static const size_t limit = env_size("BACKLIGHT_SMALL_PARAM_LIMIT", kSmallParamLimit);
  return limit;
}

namespace {
std::atomic<size_t>& budget_setting() {
  static std::atomic<size_t> budget{env_size("BACKLIGHT_LOCAL_GRADIENT_BUDGET", kLocalGradientBudget)};
  return budget;
}
}  // namespace

size_t local_gradient_budget() { return budget_setting().load(); }
void set_local_gradient_budget(size_t bytes) { budget_setting().store(bytes); }

void ParamStore::require_grad(const std::vector<std::string>& names) {
  for (auto& p : params_) p.requires_grad = names.empty() && !p.geometry;
  for (const auto& n : names) {
    int h = find(n);
    if (h < 0) throw InputError("unknown parameter '" + n + "' (see `backlight params`)");
    params_[size_t(h)].requires_grad = true;
  }
  size_t flat = 0;
  for (auto& p : params_) {
    p.tape_offset = flat;
    flat += p.size();
  }
  zero_grad();
}

GradientLayout::GradientLayout(const ParamStore& store, size_t threads) {
  offset.assign(store.count(), kAtomic);
  size_t budget_left = local_gradient_budget();
  const size_t per_value = sizeof(double) * std::max<size_t>(threads, 1);
  for (size_t h = 0; h < store.count(); ++h) {
    const Param& p = store[int(h)];
    if (!p.requires_grad) continue;
    bool local = p.size() <= small_param_limit();
    if (!local && p.size() <= budget_left / per_value) {
      local = true;
      budget_left -= p.size() * per_value;
    }
    if (local) {
      offset[h] = total;
      total += p.size();
    }
  }
}

bool ParamStore::wants_geometry() const {
  for (const auto& p : params_)
    if (p.geometry && p.requires_grad) return true;
  return false;
}

void ParamStore::zero_grad() {
  for (auto& p : params_) p.grad.assign(p.value.size(), 0.f);
}

GradientSink::GradientSink(ParamStore& store)
    : store_(store),
      layout_(store, size_t(tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism))),
      per_thread_([this] { return GradientAccumulator(&store_, &layout_); }) {}

void GradientSink::reduce() {
  std::vector<double> total(layout_.total, 0.0);
  for (auto& acc : per_thread_)
    for (size_t i = 0; i < total.size(); ++i) total[i] += acc.local()[i];
  auto& params = store_.all();
  for (size_t h = 0; h < params.size(); ++h) {
    if (!layout_.local(int(h))) continue;
    Param& p = params[h];
    const double* sum = total.data() + layout_.offset[h];
    for (size_t i = 0; i < p.size(); ++i) p.grad[i] += float(sum[i]);
  }
  per_thread_.clear();
}

}  // namespace bl
