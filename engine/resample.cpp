#include "engine/resample.h"

#include <algorithm>
#include <cmath>

namespace bl {

std::vector<float> resample(const std::vector<float>& src, int w, int h, int c, int nw, int nh) {
  auto at = [&](const std::vector<float>& img, int width, int x, int y, int k) {
    return img[(size_t(y) * size_t(width) + size_t(x)) * size_t(c) + size_t(k)];
  };
  // Separable: a horizontal pass (w → nw), then a vertical one (h → nh).
  auto pass = [&](const std::vector<float>& in, int in_w, int in_h, int out_w, int out_h, bool horizontal) {
    std::vector<float> out(size_t(out_w) * size_t(out_h) * size_t(c), 0.f);
    const int n = horizontal ? in_w : in_h, new_n = horizontal ? out_w : out_h;
    for (int j = 0; j < new_n; ++j) {
      // Source taps and weights for target index j along the axis.
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

}  // namespace bl
