// The medium's derivative shaders and the tracking functions the renderer calls
// (kernels/medium/medium.h).
//  - backprop_sigma_t, backprop_albedo and backprop_phase against central differences of
//    sigma_t<double>, albedo_at<double> and hg_eval<double> of phase<double>, with respect to every
//    element of the density, albedo, scale and g parameters: homogeneous media (HG and isotropic),
//    8³, 5×6×7 and 1-voxel density grids, RGB and grey albedo grids of their own resolution and a
//    constant albedo, in a box that is not the unit cube, at points inside, near and on its faces
//    and just outside. Every comparison has a negative control: 0.7 × the shader's gradient must
//    fail it.
//  - medium_transmittance<Var> and medium_free_flight<Var> (the taped mode's scalar) in
//    expectation over seeds: the derivatives of E[transmittance] and of E[f(free-flight outcome)]
//    with respect to every parameter element against Beer–Lambert (homogeneous) or quadrature
//    (grid), |z| < 4; the float runs' callbacks give prb's score terms the same gradient sample by
//    sample; negative controls (0.7 × the derivative, the free flight without FreeFlight::real)
//    must give |z| > 4.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "engine/core/tape.h"
#include "kernels/medium/medium.h"
#include "tests/kernels/gradcheck.h"
#include "tests/kernels/medium/medium_fixtures.h"
#include "tests/kernels/test_rng.h"

using namespace bl;
using namespace bl::test;

namespace {

// σ_t and the albedo are linear in every voxel and in the scale, so central differences are exact
// up to double rounding, and the float shaders (products of three floats) are held to 1e-5 of the
// gradient's norm.
constexpr double kLinearRel = 1e-5, kAbsFloor = 1e-7;
// HG in float: the denominator 1 + g² + 2gμ ≥ (1 − |g|)² rounds with an absolute error of a few
// 1e-8, and ∂p/∂g raises it to the power −5/2, so the float shader is good to ~2e-5 relative for
// |g| ≤ 0.8 (denominator ≥ 0.04). 1e-4 keeps a margin of 5; a factor 0.7, 2 or −1 is an error of
// ≥ 0.3. The finite difference step is 1e-5 |g|: its truncation error, (step / denominator)² ≲
// 1e-6 relative, stays well below that.
constexpr double kPhaseRel = 1e-4, kPhaseStep = 1e-5, kMaxG = 0.8;
// A negative control is meaningful only where the gradient is not negligible against the floor.
constexpr double kControllableNorm = 1e-5;

struct MediumCase {
  std::string label;
  std::vector<int> density_shape;  // [1]: a homogeneous medium; [Z, Y, X, 1]: a grid medium
  std::vector<int> albedo_shape;   // [3], [Z, Y, X, 1] (grey) or [Z, Y, X, 3]
  bool hg = true;                  // false: isotropic (no g parameter)
  double density_lo = 0.2, density_hi = 3.0;
  int block = 8;  // voxels per majorant block and axis
};

const std::vector<MediumCase>& shader_cases() {
  static const std::vector<MediumCase> cases{
      {"homogeneous, HG", {1}, {3}, true},
      {"homogeneous, isotropic", {1}, {3}, false},
      {"8^3 grid, RGB albedo grid 8^3", {8, 8, 8, 1}, {8, 8, 8, 3}, true},
      {"5x6x7 grid, RGB albedo grid 2x4x3", {7, 6, 5, 1}, {3, 4, 2, 3}, true},
      {"5x6x7 grid, grey albedo grid 5x6x7", {7, 6, 5, 1}, {7, 6, 5, 1}, true},
      {"8^3 grid, constant albedo, isotropic", {8, 8, 8, 1}, {3}, false},
      {"1-voxel grid, 1-voxel RGB albedo grid", {1, 1, 1, 1}, {1, 1, 1, 3}, true},
  };
  return cases;
}

// A medium "fog" with random values (prepare_test_medium: every parameter wanting gradients, a
// grid in a box that is not the unit cube).
TestMedium make_medium(const MediumCase& c, uint64_t seed) {
  TestRng rng(seed);
  TestMedium t;
  Medium& m = t.medium;
  m.density = t.store.add(random_param("fog.density", c.density_shape, c.density_lo, c.density_hi, rng));
  m.albedo = t.store.add(random_param("fog.albedo", c.albedo_shape, 0.1, 0.95, rng));
  m.scale = t.store.add(random_param("fog.scale", {1}, 1.2, 1.8, rng));
  if (c.hg) m.g = t.store.add(random_param("fog.g", {1}, -kMaxG, kMaxG, rng));
  m.block = c.block;
  prepare_test_medium(t);
  return t;
}

// Lookup points in world space: random in the box; within 0.3 of a face, where the lookups of the
// coarser grids clamp; on faces and at corners; at voxel centres of `n` (weights 1 and 0); and up
// to 2% of the box outside it (a ray's end point may round past a face).
std::vector<Vec3f> lookup_points(const Medium& m, const GridSize& n, TestRng& rng) {
  auto u = [&] { return float(rng.next_double()); };
  std::vector<Vec3f> local;
  for (int i = 0; i < 12; ++i) local.push_back({u(), u(), u()});
  for (int i = 0; i < 12; ++i) {
    Vec3f l(u(), u(), u());
    l[i % 3] = i % 2 ? 0.3f * u() : 1.f - 0.3f * u();
    local.push_back(l);
  }
  for (int i = 0; i < 6; ++i) {
    Vec3f l(u(), u(), u());
    l[i % 3] = float(i / 3);
    local.push_back(l);
  }
  for (int i = 0; i < 8; ++i) local.push_back({float(i & 1), float((i >> 1) & 1), float((i >> 2) & 1)});
  for (int i = 0; i < 4; ++i)
    local.push_back({(float(rng.next_u64() % uint64_t(n.x)) + 0.5f) / float(n.x),
                     (float(rng.next_u64() % uint64_t(n.y)) + 0.5f) / float(n.y),
                     (float(rng.next_u64() % uint64_t(n.z)) + 0.5f) / float(n.z)});
  for (int i = 0; i < 6; ++i) {
    Vec3f l(u(), u(), u());
    l[i % 3] = i < 3 ? -0.02f * u() : 1.f + 0.02f * u();
    local.push_back(l);
  }
  std::vector<Vec3f> world;
  for (const Vec3f& l : local) world.push_back(to_world(m, l));
  return world;
}

Vec3f random_direction(TestRng& rng) {
  const double z = rng.uniform(-1, 1), phi = rng.uniform(0, 2 * M_PI), r = std::sqrt(1 - z * z);
  return {float(r * std::cos(phi)), float(r * std::sin(phi)), float(z)};
}

// An adjoint of either sign, bounded away from zero so that every control has something to see.
float random_adjoint(TestRng& rng) { return float((rng.next_double() < 0.5 ? -1 : 1) * rng.uniform(0.2, 1.0)); }

std::string describe(const Vec3f& v) {
  std::ostringstream o;
  o.precision(9);
  o << "(" << v.x << ", " << v.y << ", " << v.z << ")";
  return o.str();
}

// One derivative shader call against central differences of ⟨adjoint, eval<double>⟩ with
// respect to every element of the parameter `handle`, and the negative control: 0.7 × the
// shader's gradient against the same differences, through the same comparison.
struct ShaderCheck {
  GradientComparison result, control;
  bool controllable = false;  // the gradient is large enough for the control to be able to fail
  // Elements whose difference is exactly 0 (the eval does not read them) but the shader wrote more
  // than 1e-9 of the gradient's norm (less is a tap whose weight is too small for double
  // differences to see, e.g. a rounding-size trilinear weight at a voxel centre).
  size_t stray_writes = 0;
};

ShaderCheck check_shader(ParamStore& store, int handle, const std::function<double()>& eval_dot_adjoint,
                         const std::function<void(GradientAccumulator&)>& backprop, double rel, double step) {
  ShaderCheck c;
  const std::vector<double> analytic = gradient_through_sink(store, handle, backprop);
  Param& p = store[handle];
  std::vector<double> numeric, scaled;
  std::vector<std::string> names;
  double norm = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    numeric.push_back(central_difference_of_param(p, i, eval_dot_adjoint, step));
    scaled.push_back(0.7 * analytic[i]);
    names.push_back(p.name + "[" + std::to_string(i) + "]");
    norm += numeric[i] * numeric[i];
  }
  for (size_t i = 0; i < p.size(); ++i)
    if (numeric[i] == 0.0 && std::abs(analytic[i]) > 1e-9 * std::sqrt(norm)) ++c.stray_writes;
  c.result = compare_gradients(analytic, numeric, names, rel, kAbsFloor);
  c.control = compare_gradients(scaled, numeric, names, rel, kAbsFloor);
  c.controllable = std::sqrt(norm) > kControllableNorm;
  return c;
}

// Worst error ratios over a medium case (≤ 1 passes) and how many controls ran and failed.
struct ShaderSummary {
  double worst_ratio = 0;
  int controls = 0, controls_failed = 0;
  void add(const ShaderCheck& c) {
    worst_ratio = std::max(worst_ratio, c.result.worst_ratio);
    if (!c.controllable) return;
    ++controls;
    controls_failed += !c.control.ok;
  }
  // Every comparison within its tolerance, more than `min_controls` controls, and all of them failed.
  void require(const std::string& label, int min_controls) const {
    INFO(label << ": worst error " << worst_ratio << " of the tolerance; " << controls_failed << " of " << controls
               << " controls failed");
    CHECK(worst_ratio <= 1.0);
    CHECK(controls > min_controls);
    CHECK(controls_failed == controls);
  }
};

void require_shader(const ShaderCheck& c, const std::string& what) {
  INFO(what << "\n" << c.result.report);
  CHECK(c.result.ok);
  CHECK(c.stray_writes == 0);
  if (c.controllable) {
    INFO("negative control (0.7 x the gradient):\n" << c.control.report);
    CHECK_FALSE(c.control.ok);
  }
}

}  // namespace

TEST_CASE("sigma_t backprop matches central differences for every voxel and the scale", "[medium][gradient]") {
  uint64_t seed = 100;
  for (const MediumCase& mc : shader_cases()) {
    TestMedium t = make_medium(mc, seed++);
    const Medium& m = t.medium;
    TestRng rng(seed++);
    ShaderSummary summary;
    for (const Vec3f& x : lookup_points(m, grid_size(t.store[m.density]), rng)) {
      const float adjoint = random_adjoint(rng);
      const auto eval = [&] { return double(adjoint) * m.sigma_t<double>(t.store, x); };
      const auto backprop = [&](GradientAccumulator& grads) { m.backprop_sigma_t(t.store, x, adjoint, grads); };
      for (int handle : {m.density, m.scale}) {
        const ShaderCheck c = check_shader(t.store, handle, eval, backprop, kLinearRel, 1e-4);
        require_shader(
            c, mc.label + ": " + t.store[handle].name + " at " + describe(x) + ", adjoint " + std::to_string(adjoint));
        summary.add(c);
      }
    }
    summary.require(mc.label, 0);
  }
}

TEST_CASE("albedo backprop matches central differences for every voxel and channel", "[medium][gradient]") {
  uint64_t seed = 200;
  for (const MediumCase& mc : shader_cases()) {
    TestMedium t = make_medium(mc, seed++);
    const Medium& m = t.medium;
    TestRng rng(seed++);
    ShaderSummary summary;
    for (const Vec3f& x : lookup_points(m, grid_size(t.store[m.albedo]), rng)) {
      const Vec3f adjoint(random_adjoint(rng), random_adjoint(rng), random_adjoint(rng));
      const ShaderCheck c = check_shader(
          t.store, m.albedo, [&] { return adjoint_dot(adjoint, m.albedo_at<double>(t.store, x)); },
          [&](GradientAccumulator& grads) { m.backprop_albedo(t.store, x, adjoint, grads); }, kLinearRel, 1e-4);
      require_shader(c, mc.label + ": albedo at " + describe(x) + ", adjoint " + describe(adjoint));
      summary.add(c);
    }
    summary.require(mc.label, 0);
  }
}

TEST_CASE("phase backprop matches central differences in g", "[medium][gradient]") {
  uint64_t seed = 300;
  for (const MediumCase& mc : shader_cases()) {
    if (!mc.hg) continue;
    TestMedium t = make_medium(mc, seed++);
    const Medium& m = t.medium;
    TestRng rng(seed++);
    ShaderSummary summary;
    for (int i = 0; i < 400; ++i) {
      // g over (−0.8, 0.8), with g = 0 (isotropic, where the relative step has its floor) and
      // directions either way round.
      t.store[m.g].value[0] = i < 10 ? 0.f : float(rng.uniform(-kMaxG, kMaxG));
      const Vec3f wi = random_direction(rng), wo = i % 4 == 0 ? -wi : random_direction(rng);
      const float adjoint = random_adjoint(rng);
      const ShaderCheck c = check_shader(
          t.store, m.g, [&] { return double(adjoint) * hg_eval<double>(m.phase<double>(t.store), wi, wo); },
          [&](GradientAccumulator& grads) { m.backprop_phase(t.store, wi, wo, adjoint, grads); }, kPhaseRel,
          kPhaseStep);
      require_shader(c, mc.label + ": g " + std::to_string(t.store[m.g].value[0]) + ", wi " + describe(wi) + ", wo " +
                            describe(wo) + ", adjoint " + std::to_string(adjoint));
      summary.add(c);
    }
    summary.require(mc.label, 300);
  }
}

TEST_CASE("medium backprop writes only into the parameters that want gradients", "[medium][gradient]") {
  for (const MediumCase& mc : shader_cases()) {
    TestMedium t = make_medium(mc, 400);
    const Medium& m = t.medium;
    const Vec3f x = to_world(m, {0.3f, 0.6f, 0.45f}), wi = normalize(Vec3f(0.2f, -0.4f, 0.9f)),
                wo = normalize(Vec3f(-0.7f, 0.1f, 0.3f));
    const auto all_grads_after = [&](const std::vector<std::string>& wanted) {
      t.store.require_grad(wanted);
      std::vector<double> grads;
      for (int h = 0; h < int(t.store.count()); ++h) {
        const std::vector<double> g = gradient_through_sink(t.store, h, [&](GradientAccumulator& acc) {
          m.backprop_sigma_t(t.store, x, 0.8f, acc);
          m.backprop_albedo(t.store, x, {0.3f, -0.5f, 0.9f}, acc);
          m.backprop_phase(t.store, wi, wo, 0.6f, acc);
        });
        double sum = 0;
        for (double v : g) sum += std::abs(v);
        grads.push_back(sum);
      }
      return grads;
    };
    INFO(mc.label);
    for (int wanted = 0; wanted < int(t.store.count()); ++wanted) {
      const std::vector<double> g = all_grads_after({t.store[wanted].name});
      INFO("only " << t.store[wanted].name << " wants gradients");
      CHECK(m.wants_sigma_grad(t.store) == (wanted == m.density || wanted == m.scale));
      for (int h = 0; h < int(t.store.count()); ++h) CHECK((g[size_t(h)] != 0.0) == (h == wanted));
    }
    if (!mc.hg) CHECK(m.phase<double>(t.store).g == 0.0);  // isotropic: backprop_phase has nothing to write
  }
}

// Tracking in expectation. The tentative collisions are drawn against detached majorants, so the
// gradient of an estimate is unbiased for the gradient of its expectation only with the score
// terms of delta tracking's real/null choices (FreeFlight::weight and ::real, tracking.h).
namespace {

struct TrackingCase {
  MediumCase medium;
  RaySegment ray;
  int samples;
};

// The outcome whose expectation the free flight is tested on: f(t) at a real collision at t (world
// distance from the ray's origin), kEscaped when the ray leaves unscattered. The escape counts
// against a collision so that the derivatives of both add up (a controlled 0.3 of them is then
// ≥ 10 standard errors at the sample counts below), and f depends on t so that where the
// collision happens matters.
constexpr double kSlope = 0.5, kEscaped = -1.0;
double outcome_collided(double t) { return 1.0 + kSlope * t; }

struct TrackingExpectation {
  double transmittance = 1, outcome = 0;
};

// Homogeneous (σ = scale · density, constant): Beer–Lambert, T = e^{−σL}, and
//   E[f] = ∫₀^L σ e^{−σt} (1 + a t) dt + h E = (1 − E)(1 + a/σ) − a L E + h E,  E = e^{−σL}
// (a = kSlope, h = kEscaped), which is 1 + a/σ for an infinite ray.
TrackingExpectation homogeneous_expectation(const Medium& m, const ParamStore& store, const RaySegment& r) {
  const double sigma = double(store[m.density].value[0]) * double(store[m.scale].value[0]);
  if (std::isinf(r.length)) return {0.0, 1.0 + kSlope / sigma};
  const double length = r.length, e = std::exp(-sigma * length);
  return {e, (1 - e) * (1 + kSlope / sigma) - kSlope * length * e + kEscaped * e};
}

// A grid: the midpoint rule over the part inside the box, with τ(t) = ∫σ_t the optical depth,
//   T = e^{−τ(end)},  E[f] = ∫ σ_t(t) e^{−τ(t)} f(t) dt + h e^{−τ(end)}.
// The integrand is piecewise cubic along the ray; 4000 steps put the error below 1e-7.
constexpr int kQuadratureSteps = 4000;
TrackingExpectation quadrature_expectation(const Medium& m, const ParamStore& store, const RaySegment& r) {
  const auto [t0, t1] = inside_interval(m, r);
  const double h = (t1 - t0) / kQuadratureSteps;
  double depth = 0, collided = 0;
  for (int i = 0; i < kQuadratureSteps; ++i) {
    const double t = t0 + (i + 0.5) * h;
    const double sigma = m.sigma_t<double>(store, r.origin + r.direction * float(t));
    collided += sigma * std::exp(-(depth + 0.5 * sigma * h)) * outcome_collided(t) * h;
    depth += sigma * h;
  }
  return {std::exp(-depth), collided + kEscaped * std::exp(-depth)};
}

TrackingExpectation expectation(const Medium& m, const ParamStore& store, const RaySegment& r) {
  return m.grid ? quadrature_expectation(m, store, r) : homogeneous_expectation(m, store, r);
}

// The elements (Param::tape_offset numbering) whose derivative is not identically zero along the
// ray: the scale, and the density voxels of the lookups' footprints (all of a homogeneous
// medium's one).
std::set<size_t> elements_read(const Medium& m, const ParamStore& store, const RaySegment& r) {
  std::set<size_t> read{store[m.scale].tape_offset};
  if (!m.grid) {
    read.insert(store[m.density].tape_offset);
    return read;
  }
  const auto [t0, t1] = inside_interval(m, r);
  for (int i = 0; i < kQuadratureSteps; ++i) {
    const TrilinearFootprint fp =
        m.footprint(store, r.origin + r.direction * float(t0 + (i + 0.5) * (t1 - t0) / kQuadratureSteps));
    for (int k = 0; k < 8; ++k)
      if (fp.weight[k] != 0.f) read.insert(store[m.density].tape_offset + fp.voxel[k]);
  }
  return read;
}

// Running mean and standard error of every element of a per-sample vector, and the largest value
// any sample put where the expectation is identically zero (it must be exactly 0).
class GradientSamples {
 public:
  GradientSamples(size_t n, const std::set<size_t>& read) : sum_(n, 0.0), sum2_(n, 0.0), read_(n, false) {
    for (size_t k : read) read_[k] = true;
  }
  void add(const std::vector<double>& x, double factor = 1.0) {
    for (size_t k = 0; k < x.size(); ++k) {
      const double v = factor * x[k];
      sum_[k] += v, sum2_[k] += v * v;
      if (!read_[k]) stray_ = std::max(stray_, std::abs(v));
    }
    ++n_;
  }
  double mean(size_t k) const { return sum_[k] / double(n_); }
  double standard_error(size_t k) const {
    const double m = mean(k);
    return std::sqrt(std::max(0.0, sum2_[k] / double(n_) - m * m) / double(n_));
  }
  double z(size_t k, double expected) const {
    const double error = std::abs(mean(k) - expected), se = standard_error(k);
    return se > 0 ? error / se : (error > 1e-12 ? std::numeric_limits<double>::infinity() : 0.0);
  }
  double stray() const { return stray_; }

 private:
  std::vector<double> sum_, sum2_;
  std::vector<bool> read_;
  double stray_ = 0;
  long n_ = 0;
};

// Every element the ray reads: |z| < 4 against the expected derivative.
struct ExpectationComparison {
  bool ok = true;
  double worst_z = 0;
  std::string report;
};

ExpectationComparison compare_in_expectation(const GradientSamples& s, const std::vector<double>& expected,
                                             const std::set<size_t>& read, const std::vector<std::string>& names) {
  ExpectationComparison c;
  std::ostringstream o;
  o.precision(6);
  size_t worst = *read.begin();
  for (size_t k : read) {
    const double z = s.z(k, expected[k]);
    if (z > c.worst_z) c.worst_z = z, worst = k;
    if (z >= 4) {
      c.ok = false;
      o << "  " << names[k] << ": " << s.mean(k) << " ± " << s.standard_error(k) << " expected " << expected[k]
        << " (z " << z << ")\n";
    }
  }
  o << "worst z " << c.worst_z << " at " << names[worst] << " over " << read.size() << " elements\n";
  c.report = o.str();
  return c;
}

// Moves what derivative shaders added into Param::grad to `out` (flat numbering), zeroing it.
void take_gradient(ParamStore& store, std::vector<double>& out) {
  for (Param& p : store.all())
    for (size_t i = 0; i < p.size(); ++i) {
      out[p.tape_offset + i] = double(p.grad[i]);
      p.grad[i] = 0.f;
    }
}

// Largest |a − b| over the elements, relative to the largest |a| (with a floor).
double relative_difference(const std::vector<double>& a, const std::vector<double>& b) {
  double scale = 1e-6, difference = 0;
  for (size_t k = 0; k < a.size(); ++k) {
    scale = std::max(scale, std::abs(a[k]));
    difference = std::max(difference, std::abs(a[k] - b[k]));
  }
  return difference / scale;
}

struct TrackingEvent {
  Vec3f x;
  float sigma, majorant;
  bool real;
};

void run_tracking_case(const TrackingCase& tc, uint64_t seed) {
  TestMedium t = make_medium(tc.medium, seed);
  const Medium& m = t.medium;
  ParamStore& store = t.store;
  const RaySegment& ray = tc.ray;
  INFO(tc.medium.label << ", " << ray.label);

  // The references: expectations and their central differences for every element the ray reads.
  size_t flat_size = 0;
  std::vector<std::string> names;
  for (const Param& p : store.all()) {
    flat_size += p.size();
    for (size_t i = 0; i < p.size(); ++i) names.push_back(p.name + "[" + std::to_string(i) + "]");
  }
  const std::set<size_t> read = elements_read(m, store, ray);
  const TrackingExpectation expected = expectation(m, store, ray);
  std::vector<double> expected_transmittance(flat_size, 0.0), expected_outcome(flat_size, 0.0);
  for (Param& p : store.all())
    for (size_t i = 0; i < p.size(); ++i) {
      if (!read.count(p.tape_offset + i)) continue;
      expected_transmittance[p.tape_offset + i] =
          central_difference_of_param(p, i, [&] { return expectation(m, store, ray).transmittance; });
      expected_outcome[p.tape_offset + i] =
          central_difference_of_param(p, i, [&] { return expectation(m, store, ray).outcome; });
    }
  if (!m.grid && !std::isinf(ray.length)) {
    // The quadrature agrees with Beer–Lambert (it is the reference of the grid cases).
    const TrackingExpectation q = quadrature_expectation(m, store, ray);
    CHECK(q.transmittance == Approx(expected.transmittance).epsilon(1e-6));
    CHECK(q.outcome == Approx(expected.outcome).epsilon(1e-6));
  }

  Tape tape;
  current_tape = &tape;
  GradientAccumulator direct(&store);  // no layout: derivative shaders add straight into Param::grad
  GradientSamples transmittance(flat_size, read), transmittance_control(flat_size, read), outcome(flat_size, read),
      outcome_control(flat_size, read), outcome_without_real(flat_size, read);
  double transmittance_sum = 0, transmittance_sum2 = 0, outcome_sum = 0, outcome_sum2 = 0;
  double prb_difference = 0;
  std::vector<float> adjoint;
  std::vector<double> taped(flat_size), taped_without_real(flat_size), prb(flat_size);
  int decision_mismatches = 0;  // the float and taped runs of one key must make the same choices
  std::vector<TrackingEvent> events;
  const auto record = [&](const Vec3f& x, float sigma, float majorant, bool real) {
    events.push_back({x, sigma, majorant, real});
  };
  for (int i = 0; i < tc.samples; ++i) {
    const uint64_t key = seed * 1000003ull + uint64_t(i);
    // Shadow-ray transmittance by ratio tracking, on the taped mode's scalar.
    {
      tape.clear();
      TrackingSampler rng(key, 1, 1u);
      const Var estimate = medium_transmittance<Var>(m, store, ray.origin, ray.direction, ray.length, rng);
      taped_gradient(tape, estimate, adjoint, taped);
      transmittance.add(taped);
      transmittance_control.add(taped, 0.7);
      transmittance_sum += estimate.v, transmittance_sum2 += double(estimate.v) * estimate.v;
      // prb's form (shadow_transmittance_backprop): the same draws in float, every tentative point
      // x_i adding −T ∂σ_t(x_i) / (σ̄ − σ_t(x_i)).
      events.clear();
      TrackingSampler replay(key, 1, 1u);
      const float value = medium_transmittance<float>(m, store, ray.origin, ray.direction, ray.length, replay, record);
      decision_mismatches += value != estimate.v;
      for (const TrackingEvent& e : events)
        if (e.majorant > e.sigma) m.backprop_sigma_t(store, e.x, -value / (e.majorant - e.sigma), direct);
      take_gradient(store, prb);
      prb_difference = std::max(prb_difference, relative_difference(taped, prb));
    }
    // Free flight by delta tracking: (collided ? f(t) · real : h) · weight, of value f(outcome).
    {
      tape.clear();
      TrackingSampler rng(key, 0, 0x10000u);
      const FreeFlight<Var> ff = medium_free_flight<Var>(m, store, ray.origin, ray.direction, ray.length, rng);
      const float f = ff.collided ? float(outcome_collided(ff.t)) : float(kEscaped);
      const Var estimate = ff.collided ? ff.real * ff.weight * f : ff.weight * f;
      taped_gradient(tape, estimate, adjoint, taped);
      outcome.add(taped);
      outcome_control.add(taped, 0.7);
      outcome_sum += estimate.v, outcome_sum2 += double(estimate.v) * estimate.v;
      // Negative control: the real collision's score term left out.
      taped_gradient(tape, ff.weight * f, adjoint, taped_without_real);
      outcome_without_real.add(taped_without_real);
      // prb's form (ReplayObserver::flight_collision): a real collision adds f ∂σ_t/σ_t, a null
      // one −f ∂σ_t/(σ̄ − σ_t).
      events.clear();
      TrackingSampler replay(key, 0, 0x10000u);
      const FreeFlight<float> flight =
          medium_free_flight<float>(m, store, ray.origin, ray.direction, ray.length, replay, record);
      decision_mismatches += flight.collided != ff.collided || flight.t != ff.t;
      for (const TrackingEvent& e : events) {
        if (e.real)
          m.backprop_sigma_t(store, e.x, f / e.sigma, direct);
        else if (e.majorant > e.sigma)
          m.backprop_sigma_t(store, e.x, -f / (e.majorant - e.sigma), direct);
      }
      take_gradient(store, prb);
      prb_difference = std::max(prb_difference, relative_difference(taped, prb));
    }
  }
  current_tape = nullptr;

  const double n = tc.samples;
  const auto value_z = [&](double sum, double sum2, double exact) {
    const double mean = sum / n, se = std::sqrt(std::max(0.0, sum2 / n - mean * mean) / n);
    return std::abs(mean - exact) / se;
  };
  const size_t scale = store[m.scale].tape_offset;
  const double transmittance_value_z = value_z(transmittance_sum, transmittance_sum2, expected.transmittance);
  const double outcome_value_z = value_z(outcome_sum, outcome_sum2, expected.outcome);
  const ExpectationComparison tr = compare_in_expectation(transmittance, expected_transmittance, read, names);
  const ExpectationComparison tr_control =
      compare_in_expectation(transmittance_control, expected_transmittance, read, names);
  const ExpectationComparison ff = compare_in_expectation(outcome, expected_outcome, read, names);
  const ExpectationComparison ff_control = compare_in_expectation(outcome_control, expected_outcome, read, names);
  const ExpectationComparison ff_without_real =
      compare_in_expectation(outcome_without_real, expected_outcome, read, names);
  INFO("E[T] " << expected.transmittance << " (z of the mean " << transmittance_value_z << "), E[f] "
               << expected.outcome << " (z " << outcome_value_z << ")");
  INFO("dE[T]/dscale " << expected_transmittance[scale] << ": " << transmittance.mean(scale) << " ± "
                       << transmittance.standard_error(scale) << "; dE[f]/dscale " << expected_outcome[scale] << ": "
                       << outcome.mean(scale) << " ± " << outcome.standard_error(scale));
  INFO("transmittance:\n" << tr.report << "free flight:\n" << ff.report);
  INFO("controls: transmittance x 0.7 z "
       << transmittance_control.z(scale, expected_transmittance[scale]) << ", free flight x 0.7 z "
       << outcome_control.z(scale, expected_outcome[scale]) << ", free flight without real z "
       << outcome_without_real.z(scale, expected_outcome[scale]));
  INFO("prb form vs taped, per sample: worst relative difference " << prb_difference);
  CHECK(outcome_value_z < 4);
  CHECK(ff.ok);
  CHECK(transmittance.stray() == 0.0);
  CHECK(outcome.stray() == 0.0);
  CHECK(outcome_without_real.stray() == 0.0);
  CHECK(decision_mismatches == 0);
  CHECK(prb_difference < 1e-4);
  // Negative controls: the same comparisons must fail, at the scale by more than 4σ.
  CHECK_FALSE(ff_control.ok);
  CHECK_FALSE(ff_without_real.ok);
  CHECK(outcome_control.z(scale, expected_outcome[scale]) > 4);
  CHECK(outcome_without_real.z(scale, expected_outcome[scale]) > 4);
  if (std::isinf(ray.length)) {
    // E[T] = 0: ratio tracking stops once its estimate underflows, every estimate and derivative 0.
    CHECK(transmittance_sum2 == 0.0);
    for (size_t k : read) CHECK((transmittance.mean(k) == 0.0 && transmittance.standard_error(k) == 0.0));
  } else {
    CHECK(transmittance_value_z < 4);
    CHECK(tr.ok);
    CHECK_FALSE(tr_control.ok);
    CHECK(transmittance_control.z(scale, expected_transmittance[scale]) > 4);
  }
}

}  // namespace

// [expectation]: not under the sanitizers (see tests/CMakeLists.txt); the shader cases above run
// the same derivative code, and the tracking code runs in kernels_medium_tracking.
TEST_CASE("tracking gradients in a homogeneous medium match Beer-Lambert in expectation",
          "[medium][tracking][expectation]") {
  const MediumCase homogeneous{"homogeneous", {1}, {3}, true, 1.0, 1.4};
  const Vec3f d = normalize(Vec3f(0.3f, -0.8f, 0.5f));
  run_tracking_case({homogeneous, {"segment of length 0.9", {0.2f, 0.1f, -0.4f}, d, 0.9f}, 40000}, 500);
  run_tracking_case(
      {homogeneous, {"infinite ray", {0.2f, 0.1f, -0.4f}, d, std::numeric_limits<float>::infinity()}, 150000}, 501);
}

TEST_CASE("tracking gradients through a density grid match quadrature in expectation",
          "[medium][tracking][expectation]") {
  // Thin enough for a transmittance of order 0.1; blocks of 3 voxels: several majorants per ray,
  // the last block of each axis partial.
  const MediumCase grid{"6x5x7 density grid", {7, 5, 6, 1}, {3}, true, 0.05, 1.0, 3};
  run_tracking_case(
      {grid,
       {"ray across the box, entering and leaving it", {-1.3f, 0.6f, 2.1f}, normalize(Vec3f(2.5f, 0.9f, 0.55f)), 4.f},
       20000},
      600);
  run_tracking_case(
      {grid, {"segment inside the box", {0.2f, 1.5f, 2.7f}, normalize(Vec3f(-0.5f, -0.6f, -0.4f)), 0.9f}, 20000}, 601);
}
