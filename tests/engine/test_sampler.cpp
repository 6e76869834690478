// PathSampler: random numbers are a pure function of (seed, pixel, sample, dimension) — path
// replay depends on it — and they must look independent and uniform across every one of those
// coordinates (pbrt-v4's samplers_test idea).
#include <catch2/catch.hpp>

#include <cmath>
#include <set>
#include <vector>

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
