#include "engine/optimize/large_steps.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "engine/core/errors.h"
#include "engine/core/weld.h"

namespace bl {

struct LargeSteps::Impl {
  double lambda = 0;
  std::vector<uint32_t> node;     // vertex → welded node
  std::vector<float> copies;      // per node: how many vertices share it
  Eigen::SparseMatrix<double> m;  // I + λ L over nodes
  Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> llt;

  // Node-space [K, 3] from vertex-space [N, 3]: the mean over each node's vertices.
  Eigen::MatrixX3d gather_mean(const std::vector<float>& v) const {
    Eigen::MatrixX3d out = Eigen::MatrixX3d::Zero(Eigen::Index(copies.size()), 3);
    for (size_t i = 0; i < node.size(); ++i)
      for (int k = 0; k < 3; ++k) out(node[i], k) += double(v[3 * i + size_t(k)]);
    for (Eigen::Index r = 0; r < out.rows(); ++r) out.row(r) /= double(copies[size_t(r)]);
    return out;
  }
  Eigen::MatrixX3d gather_sum(const std::vector<float>& v) const {
    Eigen::MatrixX3d out = Eigen::MatrixX3d::Zero(Eigen::Index(copies.size()), 3);
    for (size_t i = 0; i < node.size(); ++i)
      for (int k = 0; k < 3; ++k) out(node[i], k) += double(v[3 * i + size_t(k)]);
    return out;
  }
  std::vector<float> scatter(const Eigen::MatrixX3d& y) const {
    std::vector<float> out(3 * node.size());
    for (size_t i = 0; i < node.size(); ++i)
      for (int k = 0; k < 3; ++k) out[3 * i + size_t(k)] = float(y(node[i], k));
    return out;
  }
};

LargeSteps::LargeSteps(const std::vector<float>& positions, const std::vector<uint32_t>& indices, double lambda,
                       const std::string& where)
    : impl_(std::make_unique<Impl>()) {
  if (!(lambda > 0) || !std::isfinite(lambda))
    throw InputError(where + ": large_steps lambda must be a positive number");
  if (positions.size() % 3 != 0 || indices.size() % 3 != 0)
    throw InputError(where + ": large_steps needs [N, 3] positions and triangles");
  Impl& s = *impl_;
  s.lambda = lambda;
  const size_t n = positions.size() / 3;
  // Weld vertices at one position (engine/core/weld.h; −0 and +0 weld, as the edges do).
  PositionWelder welder;
  welder.reserve(n);
  s.node.resize(n);
  for (size_t i = 0; i < n; ++i) {
    s.node[i] = welder.id(positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]);
    if (s.node[i] == s.copies.size()) s.copies.push_back(0.f);
    s.copies[s.node[i]] += 1.f;
  }
  const size_t nodes = s.copies.size();
  // Unique undirected edges between distinct nodes.
  std::vector<std::pair<uint32_t, uint32_t>> edges;
  edges.reserve(indices.size());
  for (size_t t = 0; t < indices.size(); t += 3)
    for (int e = 0; e < 3; ++e) {
      const uint32_t i = indices[t + size_t(e)], j = indices[t + size_t((e + 1) % 3)];
      if (i >= n || j >= n) throw InputError(where + ": large_steps: triangle index out of range");
      uint32_t a = s.node[i], b = s.node[j];
      if (a == b) continue;
      if (a > b) std::swap(a, b);
      edges.emplace_back(a, b);
    }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  std::vector<double> degree(nodes, 0.0);
  std::vector<Eigen::Triplet<double>> entries;
  entries.reserve(2 * edges.size() + nodes);
  for (const auto& [a, b] : edges) {
    entries.emplace_back(int(a), int(b), -lambda);
    entries.emplace_back(int(b), int(a), -lambda);
    degree[a] += 1, degree[b] += 1;
  }
  for (size_t i = 0; i < nodes; ++i) entries.emplace_back(int(i), int(i), 1.0 + lambda * degree[i]);
  s.m.resize(Eigen::Index(nodes), Eigen::Index(nodes));
  s.m.setFromTriplets(entries.begin(), entries.end());
  s.llt.compute(s.m);
  if (s.llt.info() != Eigen::Success) throw InputError(where + ": large_steps: the factorization of I + λL failed");
}

LargeSteps::~LargeSteps() = default;
LargeSteps::LargeSteps(LargeSteps&&) noexcept = default;
LargeSteps& LargeSteps::operator=(LargeSteps&&) noexcept = default;

std::vector<float> LargeSteps::to_u(const std::vector<float>& x) const {
  return impl_->scatter(impl_->m * impl_->gather_mean(x));
}

std::vector<float> LargeSteps::to_x(const std::vector<float>& u) const {
  Eigen::MatrixX3d y = impl_->llt.solve(impl_->gather_mean(u));
  return impl_->scatter(y);
}

std::vector<float> LargeSteps::gradient_u(const std::vector<float>& g) const {
  Eigen::MatrixX3d y = impl_->llt.solve(impl_->gather_sum(g));
  return impl_->scatter(y);
}

size_t LargeSteps::vertex_count() const { return impl_->node.size(); }
size_t LargeSteps::node_count() const { return impl_->copies.size(); }
double LargeSteps::lambda() const { return impl_->lambda; }

}  // namespace bl

namespace bl {

namespace {

// out = (I + λL) in over z-slabs in parallel; every output element is written once, in order.
void apply_m(const GridDims& d, double lambda, const double* in, double* out) {
  const size_t sx = size_t(d.c), sy = sx * size_t(d.x), sz = sy * size_t(d.y);
  tbb::parallel_for(tbb::blocked_range<int>(0, d.z), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z != r.end(); ++z)
      for (int y = 0; y < d.y; ++y)
        for (int x = 0; x < d.x; ++x)
          for (int c = 0; c < d.c; ++c) {
            const size_t i = size_t(z) * sz + size_t(y) * sy + size_t(x) * sx + size_t(c);
            const double v = in[i];
            double lap = 0;  // Σ over in-grid neighbours of (v − neighbour)
            if (x > 0) lap += v - in[i - sx];
            if (x + 1 < d.x) lap += v - in[i + sx];
            if (y > 0) lap += v - in[i - sy];
            if (y + 1 < d.y) lap += v - in[i + sy];
            if (z > 0) lap += v - in[i - sz];
            if (z + 1 < d.z) lap += v - in[i + sz];
            out[i] = v + lambda * lap;
          }
  });
}

double diagonal(const GridDims& d, double lambda, size_t i) {
  const size_t sx = size_t(d.c), sy = sx * size_t(d.x), sz = sy * size_t(d.y);
  const int x = int(i / sx % size_t(d.x)), y = int(i / sy % size_t(d.y)), z = int(i / sz);
  const int degree = (x > 0) + (x + 1 < d.x) + (y > 0) + (y + 1 < d.y) + (z > 0) + (z + 1 < d.z);
  return 1.0 + lambda * degree;
}

// Σ a·b with a fixed split (the same sum on every run and thread count).
double dot(const std::vector<double>& a, const std::vector<double>& b) {
  return tbb::parallel_deterministic_reduce(
      tbb::blocked_range<size_t>(0, a.size(), 4096), 0.0,
      [&](const tbb::blocked_range<size_t>& r, double acc) {
        for (size_t i = r.begin(); i != r.end(); ++i) acc += a[i] * b[i];
        return acc;
      },
      [](double p, double q) { return p + q; });
}

void check_dims(const GridDims& d, size_t n) {
  if (d.x <= 0 || d.y <= 0 || d.z <= 0 || d.c <= 0 || d.size() != n)
    throw std::invalid_argument("grid large steps: values do not match the grid's dimensions");
}

}  // namespace

std::vector<float> grid_apply_m(const GridDims& d, double lambda, const std::vector<float>& x) {
  check_dims(d, x.size());
  const std::vector<double> in(x.begin(), x.end());
  std::vector<double> out(in.size());
  apply_m(d, lambda, in.data(), out.data());
  return std::vector<float>(out.begin(), out.end());
}

std::vector<float> grid_solve_m(const GridDims& d, double lambda, const std::vector<float>& b,
                                const std::vector<float>& guess) {
  check_dims(d, b.size());
  const size_t n = b.size();
  std::vector<double> x(n, 0.0), r(n), z(n), p(n), q(n), inv_diag(n);
  if (guess.size() == n) std::copy(guess.begin(), guess.end(), x.begin());
  for (size_t i = 0; i < n; ++i) inv_diag[i] = 1.0 / diagonal(d, lambda, i);
  apply_m(d, lambda, x.data(), q.data());
  double b_norm2 = 0;
  for (size_t i = 0; i < n; ++i) {
    r[i] = double(b[i]) - q[i];
    b_norm2 += double(b[i]) * double(b[i]);
  }
  if (b_norm2 == 0) return std::vector<float>(n, 0.f);
  const double stop = 1e-14 * b_norm2;  // relative residual 1e-7: float precision of the result
  for (size_t i = 0; i < n; ++i) z[i] = r[i] * inv_diag[i];
  p = z;
  double rz = dot(r, z);
  // Jacobi-preconditioned CG converges in O(√(1 + 12λ)) iterations; the cap is far above that.
  for (int it = 0; it < 1000 && dot(r, r) > stop; ++it) {
    apply_m(d, lambda, p.data(), q.data());
    const double alpha = rz / dot(p, q);
    for (size_t i = 0; i < n; ++i) {
      x[i] += alpha * p[i];
      r[i] -= alpha * q[i];
      z[i] = r[i] * inv_diag[i];
    }
    const double rz_new = dot(r, z);
    const double beta = rz_new / rz;
    rz = rz_new;
    for (size_t i = 0; i < n; ++i) p[i] = z[i] + beta * p[i];
  }
  return std::vector<float>(x.begin(), x.end());
}

}  // namespace bl
