// PathSampler: random numbers are a pure function of (seed, pixel, sample, dimension) — path
// replay depends on it — and they must look independent and uniform across every one of those
// coordinates (pbrt-v4's samplers_test idea). Distribution1D: each bin is drawn with its weight's
// probability, however small, for the 53-bit numbers light sampling gives it.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <set>
#include <stdexcept>
#include <vector>

#include "engine/core/distribution.h"
#include "engine/core/sampler.h"
#include "tests/kernels/chi2.h"

using namespace bl;

namespace {

// Pearson's chi-square of n values against 100 equal bins on [0, 1).
double uniformity_p_value(const std::vector<float>& values) {
  const int bins = 100;
  std::vector<double> counts(bins, 0.0);
  for (float v : values) counts[size_t(std::min(int(v * bins), bins - 1))] += 1;
  const double expected = double(values.size()) / bins;
  double chi2 = 0.0;
  for (double c : counts) chi2 += (c - expected) * (c - expected) / expected;
  return test::chi2_p_value(chi2, bins - 1);
}

// Independence of two streams: chi-square over a 10 × 10 grid of value pairs.
double pair_independence_p_value(const std::vector<float>& a, const std::vector<float>& b) {
  const int n = 10;
  std::vector<double> counts(n * n, 0.0);
  for (size_t i = 0; i < a.size(); ++i)
    counts[size_t(std::min(int(a[i] * n), n - 1) * n + std::min(int(b[i] * n), n - 1))] += 1;
  const double expected = double(a.size()) / (n * n);
  double chi2 = 0.0;
  for (double c : counts) chi2 += (c - expected) * (c - expected) / expected;
  return test::chi2_p_value(chi2, n * n - 1);
}

double correlation(const std::vector<float>& a, const std::vector<float>& b) {
  double ma = 0, mb = 0;
  for (size_t i = 0; i < a.size(); ++i) ma += a[i], mb += b[i];
  ma /= double(a.size());
  mb /= double(b.size());
  double sab = 0, saa = 0, sbb = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    sab += (a[i] - ma) * (b[i] - mb);
    saa += (a[i] - ma) * (a[i] - ma);
    sbb += (b[i] - mb) * (b[i] - mb);
  }
  return sab / std::sqrt(saa * sbb);
}

constexpr size_t kCount = 200'000;
// |r| of independent streams is ≈ N(0, 1/N); 5 standard deviations.
const double kMaxCorrelation = 5.0 / std::sqrt(double(kCount));

template <class F>
std::vector<float> generate(F value_at) {
  std::vector<float> v(kCount);
  for (size_t i = 0; i < kCount; ++i) v[i] = value_at(uint64_t(i));
  return v;
}

void check_independent(const char* what, const std::vector<float>& a, const std::vector<float>& b) {
  INFO(what);
  CHECK(std::abs(correlation(a, b)) < kMaxCorrelation);
  CHECK(pair_independence_p_value(a, b) > 1e-3);
}

}  // namespace

TEST_CASE("path sampler replays: equal coordinates give equal numbers", "[sampler]") {
  for (uint64_t seed : {0ull, 1ull, 12345ull})
    for (uint64_t pixel : {0ull, 7ull, 1919ull * 1080ull})
      for (uint64_t sample : {0ull, 1ull, 4095ull}) {
        const PathSampler first(seed, pixel, sample), again(seed, pixel, sample);
        CHECK(first.key() == again.key());
        // Any order of access, any number of times: a pure function of the dimension.
        std::vector<float> forward, backward(64);
        for (uint32_t d = 0; d < 64; ++d) forward.push_back(first.get(d));
        for (uint32_t d = 64; d-- > 0;) backward[d] = again.get(d);
        CHECK(forward == backward);
        CHECK(first.get(17) == forward[17]);
      }
}

TEST_CASE("path sampler values lie in [0, 1)", "[sampler]") {
  CHECK(bits_to_unit_float(0) == 0.f);
  CHECK(bits_to_unit_float(~0ull) < 1.f);
  float lo = 1.f, hi = 0.f;
  for (uint64_t pixel = 0; pixel < 2000; ++pixel) {
    const PathSampler s(3, pixel, pixel % 7);
    for (uint32_t d = 0; d < 200; ++d) {
      const float v = s.get(d);
      lo = std::min(lo, v);
      hi = std::max(hi, v);
    }
  }
  CHECK(lo >= 0.f);
  CHECK(hi < 1.f);
  CHECK(lo < 1e-4f);  // the range is actually covered
  CHECK(hi > 1.f - 1e-4f);
}

TEST_CASE("path sampler values are uniform along every coordinate", "[sampler]") {
  for (uint32_t dim : {0u, 1u, Dim::at(1, Dim::kBsdfU), Dim::at(7, Dim::kRoulette), 1000u}) {
    INFO("dimension " << dim);
    CHECK(uniformity_p_value(generate([&](uint64_t i) { return PathSampler(1, i, 0).get(dim); })) > 1e-3);
    CHECK(uniformity_p_value(generate([&](uint64_t i) { return PathSampler(1, 42, i).get(dim); })) > 1e-3);
    CHECK(uniformity_p_value(generate([&](uint64_t i) { return PathSampler(i, 42, 3).get(dim); })) > 1e-3);
  }
  CHECK(uniformity_p_value(generate([](uint64_t i) { return PathSampler(9, 5, 2).get(uint32_t(i)); })) > 1e-3);
}

TEST_CASE("neighbouring dimensions, pixels, samples and seeds are uncorrelated", "[sampler]") {
  for (uint32_t dim : {0u, Dim::at(1, Dim::kLightU), Dim::at(3, Dim::kBsdfU)}) {
    INFO("dimension " << dim);
    check_independent("dimension d vs d + 1", generate([&](uint64_t i) { return PathSampler(1, i, 0).get(dim); }),
                      generate([&](uint64_t i) { return PathSampler(1, i, 0).get(dim + 1); }));
    check_independent("pixel p vs p + 1", generate([&](uint64_t i) { return PathSampler(1, i, 0).get(dim); }),
                      generate([&](uint64_t i) { return PathSampler(1, i + 1, 0).get(dim); }));
    check_independent("sample s vs s + 1", generate([&](uint64_t i) { return PathSampler(1, 99, i).get(dim); }),
                      generate([&](uint64_t i) { return PathSampler(1, 99, i + 1).get(dim); }));
    check_independent("seed vs seed + 1", generate([&](uint64_t i) { return PathSampler(5, i, 0).get(dim); }),
                      generate([&](uint64_t i) { return PathSampler(6, i, 0).get(dim); }));
    check_independent("pixel p sample s vs pixel p + 1 sample s − 1",
                      generate([&](uint64_t i) { return PathSampler(1, i + 1, 1).get(dim); }),
                      generate([&](uint64_t i) { return PathSampler(1, i + 2, 0).get(dim); }));
  }
}

TEST_CASE("different seeds, pixels and samples give different streams", "[sampler]") {
  std::set<uint64_t> keys;
  size_t count = 0;
  for (uint64_t seed = 0; seed < 4; ++seed)
    for (uint64_t pixel = 0; pixel < 256; ++pixel)
      for (uint64_t sample = 0; sample < 64; ++sample, ++count) keys.insert(PathSampler(seed, pixel, sample).key());
  CHECK(keys.size() == count);

  auto equal_values = [](const PathSampler& a, const PathSampler& b) {
    int equal = 0;
    for (uint32_t d = 0; d < 1000; ++d) equal += a.get(d) == b.get(d);
    return equal;
  };
  // With 24 random bits a coincidence has probability 6e-8 per value.
  CHECK(equal_values(PathSampler(1, 10, 0), PathSampler(2, 10, 0)) <= 1);
  CHECK(equal_values(PathSampler(1, 10, 0), PathSampler(1, 11, 0)) <= 1);
  CHECK(equal_values(PathSampler(1, 10, 0), PathSampler(1, 10, 1)) <= 1);
}

TEST_CASE("dimension layout gives every vertex its own slots", "[sampler]") {
  std::set<uint32_t> used{Dim::kPixelX, Dim::kPixelY};
  for (uint32_t slot :
       {Dim::kLightSelect, Dim::kLightU, Dim::kLightV, Dim::kLobe, Dim::kBsdfU, Dim::kBsdfV, Dim::kRoulette})
    CHECK(slot < Dim::kPerVertex);
  size_t count = 2;
  for (int vertex = 1; vertex <= 64; ++vertex)
    for (uint32_t slot = 0; slot < Dim::kPerVertex; ++slot, ++count) used.insert(Dim::at(vertex, slot));
  CHECK(used.size() == count);
}

TEST_CASE("get_double extends get to 53 bits, in [0, 1)", "[sampler]") {
  CHECK(bits_to_unit_double(0) == 0.0);
  CHECK(bits_to_unit_double(~0ull) < 1.0);
  CHECK(bits_to_unit_double(~0ull) == 1.0 - std::ldexp(1.0, -53));
  for (uint64_t pixel = 0; pixel < 500; ++pixel) {
    const PathSampler s(3, pixel, pixel % 7);
    for (uint32_t d = 0; d < 50; ++d) {
      const double v = s.get_double(d);
      REQUIRE(v >= 0.0);
      REQUIRE(v < 1.0);
      // The same leading 24 bits as the float of the same dimension.
      REQUIRE(std::floor(v * 16777216.0) / 16777216.0 == double(s.get(d)));
    }
  }
  // The bits below a float's are uniform too (they are what tells tiny bins apart).
  CHECK(uniformity_p_value(generate([](uint64_t i) {
          return float(std::fmod(PathSampler(1, i, 0).get_double(Dim::at(1, Dim::kLightU)) * 16777216.0, 1.0));
        })) > 1e-3);
}

namespace {

// What Distribution1D::sample draws each bin with, for u on the 53-bit grid k / 2⁵³ (get_double):
// the number of grid points it maps to the bin. sample is monotone in u, so bin i's points start at
// the first k with k / 2⁵³ ≥ cdf[i]; checked by drawing at that k and the one before it.
std::vector<double> realized_probabilities(const Distribution1D& d) {
  const double grid = 9007199254740992.0;  // 2⁵³
  const size_t n = d.size();
  std::vector<double> first(n + 1, grid);
  for (size_t i = 0; i < n; ++i) first[i] = std::ceil(d.cdf[i] * grid);  // exact: a power-of-two scale
  std::vector<double> p(n, 0.0);
  size_t wrong = 0, first_wrong = n;
  for (size_t i = 0; i < n; ++i) {
    if (!(first[i + 1] > first[i])) continue;  // no grid point in bin i
    float at_start = -1.f, at_end = -1.f;
    const bool ok = d.sample(first[i] / grid, &at_start) == i && d.sample((first[i + 1] - 1.0) / grid, &at_end) == i &&
                    (i == 0 || d.sample((first[i] - 1.0) / grid, nullptr) < i) && at_start >= 0.f && at_start < 1.f &&
                    at_end >= at_start && at_end < 1.f;
    if (!ok && wrong++ == 0) first_wrong = i;
    p[i] = (first[i + 1] - first[i]) / grid;
  }
  INFO(wrong << " bins whose grid points sample does not map to them, the first " << first_wrong);
  CHECK(wrong == 0);
  return p;
}

void check_distribution(const std::string& label, const std::vector<double>& weights) {
  Distribution1D d;
  d.build(weights);
  REQUIRE(d.size() == weights.size());
  long double sum = 0;
  for (double w : weights) sum += std::max(0.0, w);
  const std::vector<double> realized = realized_probabilities(d);
  double worst_abs = 0.0, worst_rel = 0.0, worst_pmf = 0.0;
  size_t missing = 0, spurious = 0;
  for (size_t i = 0; i < weights.size(); ++i) {
    const double q = sum > 0 ? double(std::max(0.0, weights[i]) / sum) : 1.0 / double(weights.size());
    worst_abs = std::max(worst_abs, std::abs(realized[i] - q));
    if (q > 1e-9) worst_rel = std::max(worst_rel, std::abs(realized[i] / q - 1.0));
    if (q > 0) worst_pmf = std::max(worst_pmf, std::abs(double(d.pmf(i)) / q - 1.0));
    missing += q > 0 && realized[i] == 0.0;
    spurious += q == 0 && realized[i] > 0.0;
  }
  INFO(label << ": " << weights.size() << " bins, worst |realized − weight| " << worst_abs << ", worst relative "
             << worst_rel << " (bins above 1e-9), worst pmf relative " << worst_pmf << ", " << missing
             << " bins of positive weight never drawn, " << spurious << " empty bins drawn");
  // A few roundings of the running sums in double, each 2⁻⁵³ at most.
  CHECK(worst_abs <= 4 * std::ldexp(1.0, -53));
  CHECK(worst_rel < 1e-6);
  CHECK(worst_pmf < 2e-7);  // the reported pmf is its float
  CHECK(missing == 0);
  CHECK(spurious == 0);
}

}  // namespace

TEST_CASE("Distribution1D draws every bin with its weight's probability", "[sampler][distribution]") {
  // The triangles of a 10⁶-triangle emitter (areas in [0.5, 1.5)): with float CDFs and 24-bit
  // numbers their realized probabilities were off by 2.6% rms, 11% at worst.
  std::vector<double> triangles(1'000'000);
  for (size_t t = 0; t < triangles.size(); ++t) triangles[t] = 0.5 + bits_to_unit_double(mix64(t));
  check_distribution("10^6 triangles", triangles);
  // The columns of a 65536-wide sky with a sun 10⁴ brighter: 2508 sky columns were never drawn.
  std::vector<double> columns(65536);
  for (size_t c = 0; c < columns.size(); ++c)
    columns[c] = (1.0 + 0.9 * std::sin(double(c) * 6.28 / 65536.0)) * (c >= 21763 && c <= 21928 ? 1e4 : 1.0);
  check_distribution("65536 columns with a sun", columns);
  // Rows of an 8192-row map whose polar rows weigh ~1e-9 (sin θ at the poles, a sun elsewhere).
  std::vector<double> rows(8192);
  for (size_t r = 0; r < rows.size(); ++r)
    rows[r] = std::sin((double(r) + 0.5) / 8192.0 * M_PI) * (r >= 2028 && r <= 2068 ? 1e4 : 1.0);
  check_distribution("8192 rows with a sun", rows);
  // Empty bins first, last, in runs and alone, and negative or NaN weights (empty too).
  std::vector<double> gappy(5000, 0.0);
  for (size_t i = 3; i + 7 < gappy.size(); ++i)
    gappy[i] = i % 5 == 0 ? 0.0 : (i % 11 == 0 ? -1.0 : (i % 13 == 0 ? std::nan("") : 1e-3 * double(i % 17 + 1)));
  check_distribution("empty bins", gappy);
  check_distribution("all empty (uniform)", std::vector<double>(1000, 0.0));
  check_distribution("one bin", {2.5});
  // Infinite weights (or a sum beyond double's range) would make the CDF NaN: refused.
  Distribution1D refused;
  CHECK_THROWS_AS(refused.build({1.0, std::numeric_limits<double>::infinity(), 1.0}), std::invalid_argument);
  CHECK_THROWS_AS(refused.build({1e308, 1e308}), std::invalid_argument);
}
