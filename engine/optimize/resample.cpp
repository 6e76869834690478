#include "engine/optimize/resample.h"

#include <algorithm>
#include <cmath>
#include <utility>

namespace bl {

namespace {
// Source taps of target index j when an axis of n samples becomes new_n (box-filter overlaps when shrinking,
// linear interpolation between sample centres when growing).
std::vector<std::pair<int, float>> axis_taps(int n, int new_n, int j) {
  std::vector<std::pair<int, float>> taps;
  if (new_n <= n) {
    double lo = double(j) * n / new_n, hi = double(j + 1) * n / new_n;
    int a = int(std::floor(lo)), b = std::max(a + 1, int(std::ceil(hi)));
    for (int i = a; i < std::min(b, n); ++i) {
      double overlap = std::min(hi, double(i + 1)) - std::max(lo, double(i));
      if (overlap > 0) taps.push_back({i, float(overlap / (hi - lo))});
    }
  } else {
    double x = (j + 0.5) * n / new_n - 0.5;
    int i0 = int(std::floor(x));
    float t = float(x - i0);
    taps.push_back({std::clamp(i0, 0, n - 1), 1.f - t});
    taps.push_back({std::clamp(i0 + 1, 0, n - 1), t});
  }
  return taps;
}
}  // namespace

std::vector<float> resample(const std::vector<float>& src, int w, int h, int c, int nw, int nh) {
  auto at = [&](const std::vector<float>& img, int width, int x, int y, int k) {
    return img[(size_t(y) * size_t(width) + size_t(x)) * size_t(c) + size_t(k)];
  };
  // Separable: a horizontal pass (w → nw), then a vertical one (h → nh).
  auto pass = [&](const std::vector<float>& in, int in_w, int in_h, int out_w, int out_h, bool horizontal) {
    std::vector<float> out(size_t(out_w) * size_t(out_h) * size_t(c), 0.f);
    const int n = horizontal ? in_w : in_h, new_n = horizontal ? out_w : out_h;
    for (int j = 0; j < new_n; ++j) {
      const std::vector<std::pair<int, float>> taps = axis_taps(n, new_n, j);
      const int others = horizontal ? in_h : in_w;
      for (int o = 0; o < others; ++o)
        for (int k = 0; k < c; ++k) {
          float v = 0;
          for (auto [i, wgt] : taps) v += wgt * (horizontal ? at(in, in_w, i, o, k) : at(in, in_w, o, i, k));
          size_t idx = horizontal ? (size_t(o) * size_t(out_w) + size_t(j)) : (size_t(j) * size_t(out_w) + size_t(o));
          out[idx * size_t(c) + size_t(k)] = v;
        }
    }
    return out;
  };
  std::vector<float> tmp = pass(src, w, h, nw, h, true);
  return pass(tmp, nw, h, nw, nh, false);
}

std::vector<float> resample_grid(const std::vector<float>& src, int x, int y, int z, int c, int nx, int ny, int nz) {
  std::vector<float> cur = src;
  int dims[3] = {x, y, z};
  const int target[3] = {nx, ny, nz};
  for (int axis = 0; axis < 3; ++axis) {
    if (dims[axis] == target[axis]) continue;
    int out_dims[3] = {dims[0], dims[1], dims[2]};
    out_dims[axis] = target[axis];
    std::vector<float> out(size_t(out_dims[0]) * size_t(out_dims[1]) * size_t(out_dims[2]) * size_t(c), 0.f);
    auto index = [&](const int* d, int ix, int iy, int iz, int k) {
      return ((size_t(iz) * size_t(d[1]) + size_t(iy)) * size_t(d[0]) + size_t(ix)) * size_t(c) + size_t(k);
    };
    std::vector<std::vector<std::pair<int, float>>> taps(static_cast<size_t>(target[axis]));
    for (int j = 0; j < target[axis]; ++j) taps[size_t(j)] = axis_taps(dims[axis], target[axis], j);
    for (int iz = 0; iz < out_dims[2]; ++iz)
      for (int iy = 0; iy < out_dims[1]; ++iy)
        for (int ix = 0; ix < out_dims[0]; ++ix) {
          const int o[3] = {ix, iy, iz};
          for (int k = 0; k < c; ++k) {
            float v = 0.f;
            for (auto [i, w] : taps[size_t(o[axis])]) {
              int s3[3] = {ix, iy, iz};
              s3[axis] = i;
              v += w * cur[index(dims, s3[0], s3[1], s3[2], k)];
            }
            out[index(out_dims, ix, iy, iz, k)] = v;
          }
        }
    cur = std::move(out);
    dims[axis] = target[axis];
  }
  return cur;
}

}  // namespace bl
