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
  // An image parameter's colour space for 8-bit images set into it later (`--set`, an optimizer
  // config's set/init): its texture's color_space ("linear": not sRGB-decoded; glTF
  // metallic-roughness channels and environment maps are linear by default).
  bool srgb = true;
  size_t tape_offset = 0;  // index of element 0 in the flat numbering used by the taped mode

  size_t size() const { return value.size(); }
  bool is_image() const { return shape.size() == 3; }
  int height() const { return shape.size() == 3 ? shape[0] : 1; }
  int width() const { return shape.size() == 3 ? shape[1] : 1; }
  int channels() const { return shape.back(); }
};

// Where a pass's gradients accumulate (GradientLayout): per-thread double sums, reduced once at
// the end of the pass, for buffers of at most kSmallParamLimit floats (touched by every path,
// they would serialise atomics and lose low bits) and for larger buffers as long as their
// per-thread copies fit kLocalGradientBudget bytes over all threads (a 64³ density grid on up to
// 4 threads, 2 MB each: no atomic per trilinear tap, 8% of a volume gradient pass); lock-free
// atomic float adds into Param::grad for the rest (textures, 128³ grids and up), whose memory
// must not multiply with the thread count. The environment variables
// BACKLIGHT_SMALL_PARAM_LIMIT and BACKLIGHT_LOCAL_GRADIENT_BUDGET override the two, for
// bench/gradient and bench/volume only (they measure both strategies on the same parameter).
inline constexpr size_t kSmallParamLimit = 64;
inline constexpr size_t kLocalGradientBudget = size_t(8) << 20;
size_t small_param_limit();
size_t local_gradient_budget();
void set_local_gradient_budget(size_t bytes);  // for tests: 0 sends every large buffer to atomics

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

 private:
  std::vector<Param> params_;
  std::unordered_map<std::string, int> index_;  // name → handle
  uint64_t total_values_ = 0;
};

// Per parameter: its start in each thread's double buffer, or kAtomic (see kSmallParamLimit).
// Made from the current sizes at the start of each pass, so resampled parameters are laid out
// afresh.
struct GradientLayout {
  static constexpr size_t kAtomic = SIZE_MAX;
  std::vector<size_t> offset;  // per handle
  size_t total = 0;            // doubles per thread

  GradientLayout() = default;
  GradientLayout(const ParamStore& store, size_t threads);
  bool local(int handle) const { return offset[size_t(handle)] != kAtomic; }
};

// Per-thread view through which derivative shaders add δ·∂f/∂θ.
class GradientAccumulator {
 public:
  // Without a layout every add is an atomic float add (accumulators made only to ask `wants`).
  explicit GradientAccumulator(ParamStore* store = nullptr, const GradientLayout* layout = nullptr)
      : store_(store), layout_(layout), local_(layout ? layout->total : 0, 0.0) {}
  void add(int handle, size_t index, float v) {
    add_each(handle, [&](auto&& emit) { emit(index, v); });
  }
  // add(handle, index, v) for several elements of one parameter: emit(add) calls add(index, v)
  // for each, with the parameter's checks made once (a grid lookup's 8 taps).
  template <class Emit>
  void add_each(int handle, Emit&& emit) {
    Param& p = (*store_)[handle];
    if (!p.requires_grad) return;
    if (layout_ && layout_->local(handle)) {
      double* local = local_.data() + layout_->offset[size_t(handle)];
      emit([local](size_t index, float v) { local[index] += double(v); });
    } else {
      float* grad = p.grad.data();
      emit([grad](size_t index, float v) {
        std::atomic_ref<float>(grad[index]).fetch_add(v, std::memory_order_relaxed);
      });
    }
  }
  bool wants(int handle) const { return handle >= 0 && (*store_)[handle].requires_grad; }
  const std::vector<double>& local() const { return local_; }

 private:
  ParamStore* store_;
  const GradientLayout* layout_;
  std::vector<double> local_;
};

// One accumulator per worker thread, reduced once at the end of a pass.
class GradientSink {
 public:
  explicit GradientSink(ParamStore& store);
  GradientAccumulator& local() { return per_thread_.local(); }
  const GradientLayout& layout() const { return layout_; }
  // Adds the per-thread double sums into the float gradient buffers.
  void reduce();

 private:
  ParamStore& store_;
  GradientLayout layout_;
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
