#include "engine/optimize/large_steps.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>
#include <unordered_map>
#include <utility>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "engine/core/errors.h"

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
  // Weld vertices with bitwise equal positions (−0 and +0 differ, which only splits a seam at 0).
  struct Key {
    uint32_t b[3];
    bool operator==(const Key& o) const { return b[0] == o.b[0] && b[1] == o.b[1] && b[2] == o.b[2]; }
  };
  struct KeyHash {
    size_t operator()(const Key& k) const {
      uint64_t h = k.b[0] * 0x9e3779b97f4a7c15ull;
      h = (h ^ k.b[1]) * 0xbf58476d1ce4e5b9ull;
      h = (h ^ k.b[2]) * 0x94d049bb133111ebull;
      return size_t(h ^ (h >> 31));
    }
  };
  std::unordered_map<Key, uint32_t, KeyHash> ids;
  ids.reserve(n);
  s.node.resize(n);
  for (size_t i = 0; i < n; ++i) {
    Key k;
    std::memcpy(k.b, &positions[3 * i], sizeof k.b);
    auto [it, fresh] = ids.try_emplace(k, uint32_t(ids.size()));
    s.node[i] = it->second;
    if (fresh) s.copies.push_back(0.f);
    s.copies[it->second] += 1.f;
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
