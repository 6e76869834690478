#pragma once
// The one chi-square harness for every direction sampler (BSDFs, lights, the environment map).
//
// A sampler is checked against its own pdf (pbrt-v3's bsdfs test, Mitsuba's ChiSquareTest):
//  1. draw N samples with fixed seeds and histogram them over (θ, φ) bins of a spherical domain;
//  2. integrate the pdf over every bin numerically (midpoint rule on nested, refined sub-grids) to
//     get the expected counts; samples the sampler loses (pdf = 0) form one extra "lost" cell whose
//     expectation is N (1 − ∫ pdf);
//  3. pool the cells whose expected count is below 5, compute Pearson's statistic and its p-value
//     from the regularized incomplete gamma function, and reject below the significance level.
// Every sample's reported pdf is also compared with the pdf function (eval/pdf consistency).
// On failure the report names the bins that deviate most and the sampler's inputs (the label).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include <tbb/parallel_for.h>

#include "engine/core/math.h"
#include "tests/kernels/spherical_quadrature.h"
#include "tests/kernels/test_rng.h"

namespace bl::test {

// Upper regularized incomplete gamma function Q(a, x) = Γ(a, x) / Γ(a): a power series for P
// below x = a + 1 and Lentz's continued fraction for Q above it (Numerical Recipes §6.2).
inline double regularized_gamma_q(double a, double x) {
  if (x <= 0.0) return 1.0;
  const double log_prefactor = a * std::log(x) - x - std::lgamma(a);
  const double eps = 1e-15;
  if (x < a + 1.0) {
    double term = 1.0 / a, sum = term;
    for (int n = 1; n < 100000; ++n) {
      term *= x / (a + n);
      sum += term;
      if (std::abs(term) < std::abs(sum) * eps) break;
    }
    return std::clamp(1.0 - sum * std::exp(log_prefactor), 0.0, 1.0);
  }
  const double tiny = 1e-300;
  double b = x + 1.0 - a, c = 1.0 / tiny, d = 1.0 / b, h = d;
  for (int i = 1; i < 100000; ++i) {
    const double an = -i * (i - a);
    b += 2.0;
    d = an * d + b;
    if (std::abs(d) < tiny) d = tiny;
    c = b + an / c;
    if (std::abs(c) < tiny) c = tiny;
    d = 1.0 / d;
    const double delta = d * c;
    h *= delta;
    if (std::abs(delta - 1.0) < eps) break;
  }
  return std::clamp(std::exp(log_prefactor) * h, 0.0, 1.0);
}

// P(X ≥ chi2) for X ~ χ²(dof).
inline double chi2_p_value(double chi2, int dof) { return regularized_gamma_q(0.5 * dof, 0.5 * chi2); }

struct Chi2Options {
  std::string label;  // the sampler's inputs, printed on failure
  int theta_bins = 20, phi_bins = 40;
  double count_tolerance = 0.02;  // quadrature error allowed per bin, in Poisson deviations
  long sample_count = 500'000;
  uint64_t seed = 1;
  double min_expected = 5.0;
  double significance = 1e-3;
  double pdf_tolerance = 1e-3;  // relative, sample's pdf vs pdf(wi)
};

struct DirectionSample {
  Vec3f direction;
  float pdf = 0.f;  // 0: no sample
};

struct Chi2Result {
  double chi2 = 0.0, p_value = 0.0;
  int dof = 0;
  double pdf_integral = 0.0;     // ∫ pdf over the domain
  double accepted_fraction = 0;  // samples the sampler did not lose
  long pdf_mismatches = 0;       // samples whose reported pdf disagrees with pdf(wi)
  long invalid = 0;              // non-finite, non-unit or out-of-domain directions with pdf > 0
  long impossible = 0;           // samples in bins of zero expected count
  std::string report;
  bool passed(double significance) const {
    return p_value > significance && pdf_mismatches == 0 && invalid == 0 && impossible == 0;
  }
};

// Observed counts of one chunk of samples; chunks run in parallel and are combined in order, so
// the result does not depend on the thread count.
struct Chi2Histogram {
  std::vector<double> counts;  // per bin, plus a last cell for lost samples
  long pdf_mismatches = 0, invalid = 0;
  std::string first_problem, first_lost;
};

// Runs the test. `sample(u_lobe, u)` returns a direction and its pdf; `pdf(w)` is the density.
// Both are called concurrently and must be thread-safe (pure functions of their arguments).
inline Chi2Result chi2_test(const SphericalDomain& domain, const std::function<DirectionSample(float, Vec2f)>& sample,
                            const std::function<float(const Vec3f&)>& pdf, const Chi2Options& opt) {
  const int nt = opt.theta_bins, np = opt.phi_bins, bins = nt * np;
  const double dtheta = domain.theta_max / nt, dphi = 2.0 * M_PI / np;
  Chi2Result r;
  std::ostringstream report;
  report << "sampler: " << opt.label << " (seed " << opt.seed << ")\n";

  // Observed counts, in chunks of samples with their own random streams.
  const long chunk_size = 1 << 16, chunks = (opt.sample_count + chunk_size - 1) / chunk_size;
  std::vector<Chi2Histogram> histograms(static_cast<size_t>(chunks));
  tbb::parallel_for(0L, chunks, [&](long chunk) {
    Chi2Histogram& h = histograms[size_t(chunk)];
    h.counts.assign(size_t(bins) + 1, 0.0);
    TestRng rng(opt.seed * 0x100000001b3ull + uint64_t(chunk));
    const long end = std::min(opt.sample_count, (chunk + 1) * chunk_size);
    for (long s = chunk * chunk_size; s < end; ++s) {
      const float u_lobe = rng.next_float();
      const Vec2f u{rng.next_float(), rng.next_float()};
      const DirectionSample ds = sample(u_lobe, u);
      if (!(ds.pdf > 0.f)) {
        if (h.counts[size_t(bins)]++ == 0) {
          std::ostringstream o;
          o << "first lost sample: " << s << ", u_lobe " << u_lobe << " u (" << u.x << ", " << u.y << ")\n";
          h.first_lost = o.str();
        }
        continue;
      }
      const Vec3f& w = ds.direction;
      const auto [theta, phi] = domain.to_angles(w);
      auto describe = [&] {
        std::ostringstream o;
        o << "wi (" << w.x << ", " << w.y << ", " << w.z << ") pdf " << ds.pdf << " from sample " << s << ": u_lobe "
          << u_lobe << " u (" << u.x << ", " << u.y << ")\n";
        return o.str();
      };
      if (!is_finite(w) || std::abs(length(w) - 1.f) > 1e-4f || theta > domain.theta_max) {
        if (h.invalid++ == 0) h.first_problem += "invalid direction: " + describe();
        h.counts[size_t(bins)] += 1;
        continue;
      }
      const float reference_pdf = pdf(w);
      if (!(std::abs(reference_pdf - ds.pdf) <= opt.pdf_tolerance * std::max(reference_pdf, ds.pdf)))
        if (h.pdf_mismatches++ == 0)
          h.first_problem += "pdf(wi) = " + std::to_string(reference_pdf) + " differs: " + describe();
      const int i = std::min(int(theta / dtheta), nt - 1), j = std::min(int(phi / dphi), np - 1);
      h.counts[size_t(i * np + j)] += 1;
    }
  });
  std::vector<double> observed(size_t(bins) + 1, 0.0);
  std::string first_problem, first_lost;
  for (const Chi2Histogram& h : histograms) {
    for (size_t b = 0; b < observed.size(); ++b) observed[b] += h.counts[b];
    r.pdf_mismatches += h.pdf_mismatches;
    r.invalid += h.invalid;
    if (first_problem.empty()) first_problem = h.first_problem;
    if (first_lost.empty()) first_lost = h.first_lost;
  }
  r.accepted_fraction = 1.0 - observed[size_t(bins)] / double(opt.sample_count);

  // Expected counts: the pdf integrated over each bin, refined until the count is accurate to a
  // small fraction of its Poisson deviation (so quadrature error cannot move the statistic).
  std::vector<double> expected(size_t(bins) + 1, 0.0);
  const double n_samples = double(opt.sample_count);
  tbb::parallel_for(0, bins, [&](int b) {
    const int i = b / np, j = b % np;
    expected[size_t(b)] =
        n_samples *
        integrate_cell(domain, pdf, i * dtheta, (i + 1) * dtheta, j * dphi, (j + 1) * dphi, [&](double estimate) {
          const double count = n_samples * std::abs(estimate);
          return (opt.count_tolerance * std::sqrt(count) + 1e-3) / n_samples;
        });
  });
  double total_expected = 0.0;
  for (int b = 0; b < bins; ++b) total_expected += expected[size_t(b)];
  r.pdf_integral = total_expected / n_samples;
  expected[size_t(bins)] = std::max(0.0, n_samples - total_expected);

  // Cells: (observed, expected, bin); samples in a bin where the pdf integrates to zero are
  // impossible. The lost cell is exempt: its expectation N (1 − ∫ pdf) is only known to the
  // quadrature's accuracy, so a handful of lost samples is judged by the statistic instead.
  struct Cell {
    double observed, expected;
    int bin;
  };
  std::vector<Cell> cells;
  for (int b = 0; b <= bins; ++b) {
    if (b < bins && expected[size_t(b)] == 0.0 && observed[size_t(b)] > 0.0) {
      r.impossible += long(observed[size_t(b)]);
      std::ostringstream o;
      o << observed[size_t(b)] << " samples in bin θ∈[" << (b / np) * dtheta << ", " << (b / np + 1) * dtheta << "] φ∈["
        << (b % np) * dphi << ", " << (b % np + 1) * dphi << "] where the pdf is zero\n";
      first_problem += o.str();
    }
    cells.push_back({observed[size_t(b)], expected[size_t(b)], b});
  }

  // Pool cells of low expected count (pbrt-v3's rule) and compute Pearson's statistic.
  std::sort(cells.begin(), cells.end(), [](const Cell& a, const Cell& b) { return a.expected < b.expected; });
  std::vector<Cell> pooled;
  Cell pool{0.0, 0.0, -1};
  for (const Cell& c : cells) {
    if (c.expected >= opt.min_expected) {
      pooled.push_back(c);
      continue;
    }
    pool.observed += c.observed;
    pool.expected += c.expected;
    if (pool.expected >= opt.min_expected) {
      pooled.push_back(pool);
      pool = {0.0, 0.0, -1};
    }
  }
  if (pool.observed > 0.0 || pool.expected > 0.0) {
    // A remainder below the threshold joins the smallest proper cell.
    if (!pooled.empty() && pool.expected < opt.min_expected) {
      auto smallest = std::min_element(pooled.begin(), pooled.end(),
                                       [](const Cell& a, const Cell& b) { return a.expected < b.expected; });
      smallest->observed += pool.observed;
      smallest->expected += pool.expected;
      smallest->bin = -1;
    } else {
      pooled.push_back(pool);
    }
  }
  for (const Cell& c : pooled)
    if (c.expected > 0.0) r.chi2 += (c.observed - c.expected) * (c.observed - c.expected) / c.expected;
  r.dof = int(pooled.size()) - 1;
  r.p_value = r.dof > 0 ? chi2_p_value(r.chi2, r.dof) : 1.0;

  // Report: summary, first problems, and the cells that deviate most.
  report << "chi2 " << r.chi2 << " dof " << r.dof << " p " << r.p_value << " (need > " << opt.significance << ")"
         << ", ∫pdf " << r.pdf_integral << ", accepted " << r.accepted_fraction << ", pdf mismatches "
         << r.pdf_mismatches << ", invalid " << r.invalid << ", impossible " << r.impossible << "\n"
         << first_problem << first_lost;
  std::sort(pooled.begin(), pooled.end(), [](const Cell& a, const Cell& b) {
    auto contribution = [](const Cell& c) {
      return c.expected > 0 ? (c.observed - c.expected) * (c.observed - c.expected) / c.expected : 0.0;
    };
    return contribution(a) > contribution(b);
  });
  report << "largest deviations:\n";
  for (size_t k = 0; k < std::min<size_t>(8, pooled.size()); ++k) {
    const Cell& c = pooled[k];
    report << "  ";
    if (c.bin < 0)
      report << "pooled low-count cells";
    else if (c.bin == bins)
      report << "lost samples";
    else
      report << "θ∈[" << (c.bin / np) * dtheta << ", " << (c.bin / np + 1) * dtheta << "] φ∈[" << (c.bin % np) * dphi
             << ", " << (c.bin % np + 1) * dphi << "]";
    report << ": observed " << c.observed << " expected " << c.expected << "\n";
  }
  r.report = report.str();
  return r;
}

}  // namespace bl::test
