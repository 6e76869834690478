#pragma once
// Spherical domains and adaptive cubature over them, for the chi-square harness (expected counts)
// and for the tests that integrate pdfs and BSDFs over the hemisphere (∫ pdf, white furnace).
#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include <tbb/parallel_for.h>

#include "engine/core/math.h"

namespace bl::test {

// A set of directions parameterised by θ ∈ [0, θmax] from an axis n and φ ∈ [0, 2π) around it,
// measured from the tangent s towards t: ω = sin θ cos φ s + sin θ sin φ t + cos θ n, and
// dω = sin θ dθ dφ.
struct SphericalDomain {
  double theta_max = 0.5 * M_PI;
  Vec3d s{1, 0, 0}, t{0, 1, 0}, n{0, 0, 1};

  Vec3f to_direction(double theta, double phi) const {
    return direction(std::sin(theta), std::cos(theta), std::cos(phi), std::sin(phi));
  }
  Vec3f direction(double sin_theta, double cos_theta, double cos_phi, double sin_phi) const {
    return Vec3f(s * (sin_theta * cos_phi) + t * (sin_theta * sin_phi) + n * cos_theta);
  }
  // (θ, φ) of a unit direction, φ in [0, 2π).
  std::pair<double, double> to_angles(const Vec3f& w) const {
    const Vec3d v(w);
    const double phi = std::atan2(dot(v, t), dot(v, s));
    return {std::acos(std::clamp(dot(v, n), -1.0, 1.0)), phi < 0.0 ? phi + 2.0 * M_PI : phi};
  }
};

// The upper hemisphere of the local shading frame: θ from +z, φ = atan2(y, x).
inline SphericalDomain upper_hemisphere() { return {}; }

// The whole sphere in the environment map's latitude-longitude layout (+y up, φ = 2π u with
// u = 0.5 + atan2(x, −z) / 2π), so that bins can be aligned with texels.
inline SphericalDomain latlong_sphere() { return {M_PI, {0, 0, 1}, {-1, 0, 0}, {0, 1, 0}}; }

// Midpoint rule for ∫∫ f(ω) sin θ dθ dφ over [θ0, θ1] × [φ0, φ1] with n × n points (n ≤ 16).
template <class F>
double midpoint_rule(const SphericalDomain& domain, const F& f, double theta0, double theta1, double phi0, double phi1,
                     int n) {
  n = std::min(n, 16);
  const double dtheta = (theta1 - theta0) / n, dphi = (phi1 - phi0) / n;
  double cos_phi[16], sin_phi[16];
  for (int b = 0; b < n; ++b) {
    cos_phi[b] = std::cos(phi0 + (b + 0.5) * dphi);
    sin_phi[b] = std::sin(phi0 + (b + 0.5) * dphi);
  }
  double total = 0.0;
  for (int a = 0; a < n; ++a) {
    const double theta = theta0 + (a + 0.5) * dtheta, st = std::sin(theta), ct = std::cos(theta);
    double row = 0.0;
    for (int b = 0; b < n; ++b) row += double(f(domain.direction(st, ct, cos_phi[b], sin_phi[b])));
    total += row * st;
  }
  return total * dtheta * dphi;
}

// A cell split into 3 × 3 sub-cells.
struct CellSplit {
  double theta0, dtheta, phi0, dphi;
  double bounds(int k, int axis, int end) const {
    const int index = (axis == 0 ? k / 3 : k % 3) + end;
    return axis == 0 ? theta0 + index * dtheta : phi0 + index * dphi;
  }
};

// The midpoint estimates of the 3 × 3 sub-cells; their sum is the midpoint rule on a 3× finer
// grid that contains the coarse grid's points.
template <class F>
double sub_cell_estimates(const SphericalDomain& domain, const F& f, const CellSplit& split, int n, double sub[9]) {
  double fine = 0.0;
  for (int k = 0; k < 9; ++k)
    fine += sub[k] = midpoint_rule(domain, f, split.bounds(k, 0, 0), split.bounds(k, 0, 1), split.bounds(k, 1, 0),
                                   split.bounds(k, 1, 1), n);
  return fine;
}

// Adaptive cubature: a cell's estimate is compared with the sum of its sub-cells' estimates;
// cells that disagree by more than their tolerance are split and refined recursively. Refinement
// concentrates where the integrand needs it, e.g. on the thin ridges GGX reflection lobes become
// near grazing incidence (the solid-angle lobe narrows like cos θo across the plane of incidence).
template <class F>
double integrate_adaptive(const SphericalDomain& domain, const F& f, const CellSplit& split, double coarse,
                          double tolerance, int depth, int n) {
  double sub[9];
  const double fine = sub_cell_estimates(domain, f, split, n, sub);
  if (depth == 0 || std::abs(fine - coarse) <= tolerance) return fine;
  double refined = 0.0;
  for (int k = 0; k < 9; ++k)
    refined +=
        integrate_adaptive(domain, f, {split.bounds(k, 0, 0), split.dtheta / 3, split.bounds(k, 1, 0), split.dphi / 3},
                           sub[k], tolerance / 3, depth - 1, n);
  return refined;
}

// ∫∫ f(ω) dω over the cell [θ0, θ1] × [φ0, φ1], to an absolute accuracy of about
// tolerance(estimate); n ≤ 16 points per axis and sub-cell.
template <class F, class Tolerance>
double integrate_cell(const SphericalDomain& domain, const F& f, double theta0, double theta1, double phi0, double phi1,
                      Tolerance tolerance, int n = 4, int max_depth = 6) {
  const double coarse = midpoint_rule(domain, f, theta0, theta1, phi0, phi1, n);
  const CellSplit split{theta0, (theta1 - theta0) / 3, phi0, (phi1 - phi0) / 3};
  double sub[9];
  const double fine = sub_cell_estimates(domain, f, split, n, sub);
  const double tol = tolerance(fine);
  if (std::abs(fine - coarse) <= tol) return fine;
  double refined = 0.0;
  for (int k = 0; k < 9; ++k)
    refined +=
        integrate_adaptive(domain, f, {split.bounds(k, 0, 0), split.dtheta / 3, split.bounds(k, 1, 0), split.dphi / 3},
                           sub[k], tol / 3, max_depth - 1, n);
  return refined;
}

// ∫ f(ω) dω over the whole domain, cell by cell (cells in parallel, summed in order), to a
// relative accuracy of about rel_tol.
template <class F>
double integrate_over_domain(const SphericalDomain& domain, const F& f, double rel_tol = 1e-4, int theta_cells = 24,
                             int phi_cells = 48) {
  const double dtheta = domain.theta_max / theta_cells, dphi = 2.0 * M_PI / phi_cells;
  const double cell_area = 2.0 * M_PI * (1.0 - std::cos(domain.theta_max)) / (theta_cells * phi_cells);
  std::vector<double> cells(size_t(theta_cells * phi_cells));
  tbb::parallel_for(0, theta_cells * phi_cells, [&](int c) {
    const int i = c / phi_cells, j = c % phi_cells;
    cells[size_t(c)] = integrate_cell(domain, f, i * dtheta, (i + 1) * dtheta, j * dphi, (j + 1) * dphi,
                                      [&](double estimate) { return rel_tol * (std::abs(estimate) + cell_area); });
  });
  double total = 0.0;
  for (double c : cells) total += c;
  return total;
}

}  // namespace bl::test
