#pragma once
// Adam with per-parameter learning rates, optional decay, and box bounds projected after every
// step; plus the `backlight optimize` driver (engine/optimize/optimize_job.cpp).
#include <cstdint>
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
};

class Adam {
 public:
  Adam() = default;
  explicit Adam(AdamSettings s) : s_(std::move(s)) {}
  // One bias-corrected step of θ along −gradient, then projection onto [lower, upper].
  void step(std::vector<float>& value, const std::vector<float>& gradient);
  // Resets moments (after a resolution change).
  void reset(size_t size);
  double current_learning_rate() const;
  // The undecayed learning rate (a schedule stage may set its own).
  void set_learning_rate(double lr) { s_.learning_rate = lr; }
  int steps() const { return t_; }
  int decay_steps() const { return global_t_; }

  // State for checkpoints.
  std::vector<float> m, v;
  void set_state(int t, int global_t) { t_ = t, global_t_ = global_t; }
  const AdamSettings& settings() const { return s_; }

 private:
  AdamSettings s_;
  int t_ = 0;         // steps since the last reset (bias correction)
  int global_t_ = 0;  // steps overall (learning-rate decay)
};

// `backlight optimize CONFIG [--resume DIR]`: returns the process exit code. A non-empty
// `resume_dir` continues the run whose outputs are in that directory.
int run_optimize(const std::string& config_path, const std::string& resume_dir, int threads, bool quiet);
// Reads and validates an optimization config (JSON, keys, values) without loading its scene or
// running anything; throws InputError like run_optimize. Used by tests/fuzz.
void check_optimize_config(const std::string& config_path);

}  // namespace bl
