#include "engine/optimize/mesh_distance.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <tbb/blocked_range.h>
#include <tbb/parallel_reduce.h>

#include "engine/core/math.h"

namespace bl {

namespace {

Vec3d at(const std::vector<float>& p, uint32_t i) { return {p[3 * i], p[3 * i + 1], p[3 * i + 2]}; }

// Squared distance from p to triangle abc: the closest point by Voronoi regions (Ericson, Real-Time
// Collision Detection, 5.1.5).
double distance2(const Vec3d& p, const Vec3d& a, const Vec3d& b, const Vec3d& c) {
  const Vec3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  auto len2 = [](const Vec3d& v) { return dot(v, v); };
  if (d1 <= 0 && d2 <= 0) return len2(ap);
  const Vec3d bp = p - b;
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return len2(bp);
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return len2(p - (a + ab * (d1 / (d1 - d3))));
  const Vec3d cp = p - c;
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return len2(cp);
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return len2(p - (a + ac * (d2 / (d2 - d6))));
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0)
    return len2(p - (b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))));
  const double denom = 1.0 / (va + vb + vc);
  if (!std::isfinite(denom)) return len2(ap);  // a degenerate triangle: its corner
  return len2(p - (a + ab * (vb * denom) + ac * (vc * denom)));
}

// Mean over the points of `from` of the distance to the surface `to`.
double one_way(const std::vector<float>& from, const std::vector<float>& to, const std::vector<uint32_t>& indices) {
  const size_t n = from.size() / 3, triangles = indices.size() / 3;
  const double sum = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 16), 0.0,
      [&](const tbb::blocked_range<size_t>& r, double acc) {
        for (size_t i = r.begin(); i != r.end(); ++i) {
          const Vec3d p = at(from, uint32_t(i));
          double best = std::numeric_limits<double>::infinity();
          for (size_t t = 0; t < triangles; ++t)
            best = std::min(
                best, distance2(p, at(to, indices[3 * t]), at(to, indices[3 * t + 1]), at(to, indices[3 * t + 2])));
          acc += std::sqrt(best);
        }
        return acc;
      },
      [](double x, double y) { return x + y; });
  return n ? sum / double(n) : 0.0;
}

}  // namespace

double surface_distance(const std::vector<float>& a, const std::vector<float>& b,
                        const std::vector<uint32_t>& indices) {
  if (a.size() != b.size() || a.empty() || indices.empty()) return -1;
  if (double(a.size() / 3) * double(indices.size() / 3) > 5e8) return -1;
  for (uint32_t i : indices)
    if (3 * size_t(i) + 2 >= a.size()) return -1;
  return 0.5 * (one_way(a, b, indices) + one_way(b, a, indices));
}

}  // namespace bl
