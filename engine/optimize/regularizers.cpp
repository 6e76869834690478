#include "engine/optimize/regularizers.h"

#include <algorithm>
#include <cmath>

namespace bl {

double add_total_variation(Param& p, double weight) {
  if (weight <= 0 || (!p.is_image() && p.shape.size() != 4)) return 0;
  const int c = p.shape.back();
  const bool grid = p.shape.size() == 4;  // [Z, Y, X, C], else an image [H, W, C]
  const int nx = grid ? p.shape[2] : p.shape[1], ny = grid ? p.shape[1] : p.shape[0], nz = grid ? p.shape[0] : 1;
  const double eps2 = 1e-6, cells = double(nx) * ny * nz * c;
  auto at = [&](int x, int y, int z, int k) {
    return ((size_t(z) * size_t(ny) + size_t(y)) * size_t(nx) + size_t(x)) * size_t(c) + size_t(k);
  };
  double tv = 0;
  for (int z = 0; z < nz; ++z)
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x)
        for (int k = 0; k < c; ++k) {
          const size_t i = at(x, y, z, k);
          const size_t nbr[3] = {at(std::min(x + 1, nx - 1), y, z, k), at(x, std::min(y + 1, ny - 1), z, k),
                                 at(x, y, std::min(z + 1, nz - 1), k)};
          double d[3], sum = eps2;
          for (int a = 0; a < 3; ++a) {
            d[a] = double(p.value[nbr[a]]) - p.value[i];
            sum += d[a] * d[a];
          }
          const double len = std::sqrt(sum);
          tv += len;
          const double scale = weight / (cells * len);
          for (int a = 0; a < 3; ++a) {
            p.grad[nbr[a]] += float(scale * d[a]);
            p.grad[i] -= float(scale * d[a]);
          }
        }
  return weight * tv / cells;
}

double add_l1(Param& p, double weight) {
  if (weight <= 0 || p.value.empty()) return 0;
  const double per_element = weight / double(p.value.size());
  double sum = 0;
  for (size_t i = 0; i < p.value.size(); ++i) {
    sum += std::abs(double(p.value[i]));
    p.grad[i] += float(p.value[i] > 0.f ? per_element : p.value[i] < 0.f ? -per_element : 0.);
  }
  return per_element * sum;
}

}  // namespace bl
