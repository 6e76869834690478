#pragma once
// Laplacian-preconditioned vertex positions for the optimizer ("large steps", Nicolet et al.
// 2021, "Large Steps in Inverse Rendering of Geometry").
//
// The optimizer works on u = M x instead of the positions x, with M = I + λ L and L the mesh's
// combinatorial Laplacian (L_ii = number of neighbours of vertex i, L_ij = −1 when i and j share
// an edge). A gradient g with respect to x becomes M⁻¹ g with respect to u (M is symmetric), and
// a step on u maps back to x = M⁻¹ u: high-frequency components of the gradient, which a plain
// step on x turns into tangled or folded triangles, are damped by 1/(1 + λ μ) for a Laplacian
// eigenvalue μ, so a mesh can move far per step and stay smooth. M is symmetric positive definite;
// it is factorized once per topology (sparse Cholesky, Eigen's SimplicialLLT) and every transform
// is two triangular solves per coordinate.
//
// Vertices at exactly the same position (seams of uv or normal splits in a loaded mesh) are welded
// into one node of L: a seam then moves as one, instead of opening into a crack.
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace bl {

class LargeSteps {
 public:
  // `positions`: [N, 3] row-major (the parameter's value); `indices`: triangles into them.
  // Throws InputError (`where` names the parameter) for λ ≤ 0, an index out of range or a
  // factorization that fails.
  LargeSteps(const std::vector<float>& positions, const std::vector<uint32_t>& indices, double lambda,
             const std::string& where);
  ~LargeSteps();
  LargeSteps(LargeSteps&&) noexcept;
  LargeSteps& operator=(LargeSteps&&) noexcept;

  // u = M x for positions x ([N, 3]).
  std::vector<float> to_u(const std::vector<float>& x) const;
  // x = M⁻¹ u.
  std::vector<float> to_x(const std::vector<float>& u) const;
  // The gradient with respect to u of a loss whose gradient with respect to x is g: M⁻¹ g
  // (duplicates of a welded vertex get the sum of their gradients, each).
  std::vector<float> gradient_u(const std::vector<float>& g) const;

  size_t vertex_count() const;
  size_t node_count() const;  // after welding
  double lambda() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace bl

namespace bl {

// Large steps for a grid parameter ([Z, Y, X, C], e.g. a medium's density): the same
// reparametrisation u = M x with M = I + λ L, L the 6-neighbour Laplacian of the voxel lattice
// (a voxel's degree counts its neighbours inside the grid: no flux through the faces), each
// channel on its own. M is applied without a matrix; M⁻¹ comes from conjugate gradients with a
// Jacobi preconditioner, stopped at a relative residual of 1e-7 (M's condition number is at most
// 1 + 12λ). λ is in units of the grid's own voxels: after a coarse-to-fine resampling the same λ
// smooths over the same number of (smaller) voxels.
struct GridDims {
  int x = 0, y = 0, z = 0, c = 0;
  size_t size() const { return size_t(x) * size_t(y) * size_t(z) * size_t(c); }
};
// (I + λL) x.
std::vector<float> grid_apply_m(const GridDims& d, double lambda, const std::vector<float>& x);
// The x with (I + λL) x = b; `guess` (same size, or empty) starts the iteration.
std::vector<float> grid_solve_m(const GridDims& d, double lambda, const std::vector<float>& b,
                                const std::vector<float>& guess = {});

}  // namespace bl
