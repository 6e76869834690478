#pragma once
// Adam with per-parameter learning rates, optional decay, and box bounds projected after every
// step; plus the `backlight optimize` driver (engine/optimize/optimize_job.cpp).
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

namespace bl {

struct AdamSettings {
  double learning_rate = 0.01;
  double beta1 = 0.9, beta2 = 0.999, epsilon = 1e-8;
  // Decay: "none", "exponential" (lr·rate^t) or "step" (lr·factor^⌊t/every⌋).
  std::string decay = "none";
  double decay_rate = 1.0;
  int decay_every = 0;
  float lower = -1e30f, upper = 1e30f;
  // Warm-up: the first `warmup` steps after every reset take lr · t / warmup (t = 1, 2, …). Right
  // after a reset Adam's bias-corrected step is ±lr for every element whatever its gradient's
  // signal-to-noise ratio (m̂ / √v̂ = ±1 at t = 1); the ramp lets v̂ average some gradients first.
  int warmup = 0;
  // Storage of the two moments: float32, or bfloat16 with stochastic rounding (half the memory;
  // 8 significant bits, unbiased, see float_to_bf16).
  bool bf16_moments = false;
  // Uniform second moment (Nicolet et al. 2021's "uniform Adam"): every element divides by the
  // largest element's √v̂ instead of its own, so the step keeps the gradient's shape. Used with
  // large steps (large_steps.h): per-element normalisation would undo the preconditioner's
  // smoothing, scaling the damped high frequencies back up.
  bool uniform = false;
};

// bfloat16: the upper 16 bits of a float (same exponent range, 8 significant bits).
inline float bf16_to_float(uint16_t h) {
  const uint32_t bits = uint32_t(h) << 16;
  float f;
  std::memcpy(&f, &bits, 4);
  return f;
}
// Stochastic rounding to bfloat16: `random` (uniform 16 bits) is added below the kept bits before
// they are truncated, so the magnitude rounds up with probability equal to the dropped fraction
// and E[result] = x. Round-to-nearest would stall Adam's second moment: with beta2 = 0.999 an
// update changes v by 0.1%, below half a bfloat16 step (0.2–0.4%), so v would never move.
inline uint16_t float_to_bf16(float x, uint16_t random) {
  uint32_t bits;
  std::memcpy(&bits, &x, 4);
  return uint16_t((bits + random) >> 16);
}

class Adam {
 public:
  Adam() = default;
  explicit Adam(AdamSettings s) : s_(std::move(s)) {}
  // One bias-corrected step of θ along −gradient, then projection onto [lower, upper]. With
  // `uniform_allowed` false the step is per element even when the settings ask for uniform Adam
  // (a grid's schedule stage without large steps: plain Adam, as documented).
  void step(std::vector<float>& value, const std::vector<float>& gradient, bool uniform_allowed = true);
  // Resets moments (after a resolution change).
  void reset(size_t size);
  // The learning rate of the next step (decay and warm-up applied).
  double current_learning_rate() const;
  // The undecayed learning rate (a schedule stage may set its own).
  void set_learning_rate(double lr) { s_.learning_rate = lr; }
  int steps() const { return t_; }
  int decay_steps() const { return global_t_; }

  // State for checkpoints: the moments as floats, or (bf16_moments) as bfloat16 bit patterns;
  // the other pair is empty.
  std::vector<float> m, v;
  std::vector<uint16_t> m16, v16;
  size_t state_size() const { return s_.bf16_moments ? m16.size() : m.size(); }
  void set_state(int t, int global_t) { t_ = t, global_t_ = global_t; }
  const AdamSettings& settings() const { return s_; }

 private:
  AdamSettings s_;
  int t_ = 0;         // steps since the last reset (bias correction)
  int global_t_ = 0;  // steps overall (learning-rate decay)
};

// A log parametrization's floor: values below it enter log space as kLogFloor.
inline constexpr float kLogFloor = 1e-6f;
// In place: value x → u = ln max(x, kLogFloor) and gradient df/dx → df/du = df/dx · max(x, kLogFloor).
void to_log_space(std::vector<float>& value, std::vector<float>& grad);

// `backlight optimize CONFIG [--resume DIR]`: returns the process exit code. A non-empty
// `resume_dir` continues the run whose outputs are in that directory; `resume_any_scene` resumes
// a checkpoint made from another scene file with other content, which is refused otherwise.
int run_optimize(const std::string& config_path, const std::string& resume_dir, int threads, bool quiet,
                 bool resume_any_scene = false);
// Reads and validates an optimization config (JSON, keys, values) without loading its scene or
// running anything; throws InputError like run_optimize. Used by tests/fuzz.
void check_optimize_config(const std::string& config_path);

}  // namespace bl
