#pragma once
// The parameter store: every differentiable quantity of a scene is a named float buffer.
// Kernels keep integer handles into it; loaders create the buffers; `--set` overrides them;
// the adjoint integrators write gradients of the same shape.
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include <tbb/enumerable_thread_specific.h>

namespace bl {

struct Param {
  std::string name;        // "<owner>.<key>", e.g. "wall.albedo"
  std::vector<int> shape;  // [3], [1] or [H, W, C]
  std::vector<float> value;
  std::vector<float> grad;
  float lower = 0.f, upper = 1e30f;  // valid range, checked on load and projected by the optimizer
  bool requires_grad = false;        // set for the parameters a gradient run asks for
  // A shape's or camera's pose or vertex positions: differentiated only when named (the default
  // "all parameters" of a gradient run means all appearance parameters).
  bool geometry = false;
  // Where gradients accumulate: small buffers (touched by every path) use per-thread double
  // accumulators reduced once; large ones take lock-free atomic float adds.
  bool small = false;
  size_t small_offset = 0;
  size_t tape_offset = 0;  // index of element 0 in the flat numbering used by the taped mode

  size_t size() const { return value.size(); }
  bool is_image() const { return shape.size() == 3; }
  int height() const { return shape.size() == 3 ? shape[0] : 1; }
  int width() const { return shape.size() == 3 ? shape[1] : 1; }
  int channels() const { return shape.back(); }
};

// Buffers of at most this many floats accumulate per thread in double precision. The
// environment variable BACKLIGHT_SMALL_PARAM_LIMIT overrides it, for bench/gradient only (it
// measures both strategies on the same parameter).
inline constexpr size_t kSmallParamLimit = 64;
size_t small_param_limit();

class ParamStore {
 public:
  // Returns the handle; names must be unique. The total of all values is bounded by
  // limits::kParamValues (an InputError naming `where`, the file being loaded).
  int add(Param p, const std::string& where = "parameters");
  int find(const std::string& name) const;  // -1 when absent (a hash lookup: scenes may hold 10^6)
  Param& operator[](int handle) { return params_[size_t(handle)]; }
  const Param& operator[](int handle) const { return params_[size_t(handle)]; }
  size_t count() const { return params_.size(); }
  std::vector<Param>& all() { return params_; }
  const std::vector<Param>& all() const { return params_; }
  std::string shape_string(int handle) const;

  // Gradient bookkeeping: mark which parameters want gradients, lay out per-thread accumulators.
  void require_grad(const std::vector<std::string>& names);  // empty = all but geometry
  bool wants_geometry() const;                               // a geometry parameter requires grad
  void zero_grad();
  size_t small_total() const { return small_total_; }

 private:
  std::vector<Param> params_;
  std::unordered_map<std::string, int> index_;  // name → handle
  uint64_t total_values_ = 0;
  size_t small_total_ = 0;
};

// Per-thread view through which derivative shaders add δ·∂f/∂θ.
class GradientAccumulator {
 public:
  explicit GradientAccumulator(ParamStore* store = nullptr)
      : store_(store), small_(store ? store->small_total() : 0, 0.0) {}
  void add(int handle, size_t index, float v) {
    Param& p = (*store_)[handle];
    if (!p.requires_grad) return;
    if (p.small) {
      small_[p.small_offset + index] += double(v);
    } else {
      std::atomic_ref<float>(p.grad[index]).fetch_add(v, std::memory_order_relaxed);
    }
  }
  bool wants(int handle) const { return handle >= 0 && (*store_)[handle].requires_grad; }
  std::vector<double>& small() { return small_; }

 private:
  ParamStore* store_;
  std::vector<double> small_;
};

// One accumulator per worker thread, reduced once at the end of a pass.
class GradientSink {
 public:
  explicit GradientSink(ParamStore& store)
      : store_(store), per_thread_([&store] { return GradientAccumulator(&store); }) {}
  GradientAccumulator& local() { return per_thread_.local(); }
  // Adds the per-thread double sums into the float gradient buffers.
  void reduce();

 private:
  ParamStore& store_;
  tbb::enumerable_thread_specific<GradientAccumulator> per_thread_;
};

// Loads parameter element `index` as scalar type T. Plain scalars read the value; the taped
// mode specialises this to create a tape leaf (see engine/core/tape.h).
template <class T>
struct ParamLoad {
  static T load(const Param& p, size_t index) { return T(p.value[index]); }
  // weight · element, e.g. one bilinear tap (one tape entry in the taped mode).
  static T load_weighted(const Param& p, size_t index, float weight) { return T(p.value[index]) * weight; }
};

}  // namespace bl
