#pragma once
// Voxel grids of a heterogeneous medium: trilinear lookup, its exact transpose, block majorants
// and a 3D DDA over the blocks.
// | parameter          | shape         | range  | differentiable |
// | <medium>.density   | [Z, Y, X, 1]  | ≥ 0    | yes (every voxel) |
// | <medium>.albedo    | [Z, Y, X, 3]  | [0, 1] | yes (every voxel) |
// Conventions (Mitsuba 3's gridvolume, ../shared/reference/mitsuba3-volume/README.md): the grid
// fills the unit cube of local coordinates; voxel (ix, iy, iz) is element (iz·Y + iy)·X + ix (x
// fastest, the order of Mitsuba's .vol and of a NumPy array rho[iz, iy, ix]) and is a point
// sample at local ((ix + ½)/X, (iy + ½)/Y, (iz + ½)/Z). A lookup blends the 8 voxel centres around
// q = local·N − ½ per axis, with integer indices clamped to the grid: within half a voxel of a
// face the value is constant along that axis (no fall-off to zero inside the grid).
#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "engine/core/math.h"
#include "engine/core/params.h"

namespace bl {

struct GridSize {
  int x = 1, y = 1, z = 1, channels = 1;
  size_t voxels() const { return size_t(x) * size_t(y) * size_t(z); }
  size_t index(int ix, int iy, int iz) const { return (size_t(iz) * size_t(y) + size_t(iy)) * size_t(x) + size_t(ix); }
};

inline GridSize grid_size(const Param& p) {
  // Shape [Z, Y, X, C]; a constant [C] is a 1×1×1 grid.
  if (p.shape.size() == 4) return {p.shape[2], p.shape[1], p.shape[0], p.shape[3]};
  return {1, 1, 1, p.shape.back()};
}

// The 8 voxels a lookup reads and their weights; eval and backprop share it, so the derivative
// shader is the exact transpose of the lookup.
struct TrilinearFootprint {
  size_t voxel[8];
  float weight[8];
};

inline TrilinearFootprint trilinear_footprint(const GridSize& n, const Vec3f& local) {
  const int dims[3] = {n.x, n.y, n.z};
  int i0[3], i1[3];
  float f[3];
  for (int a = 0; a < 3; ++a) {
    const float q = local[a] * float(dims[a]) - 0.5f;
    const float fl = std::floor(q);
    f[a] = q - fl;
    const long base = long(fl);
    i0[a] = int(std::clamp(base, 0L, long(dims[a] - 1)));
    i1[a] = int(std::clamp(base + 1, 0L, long(dims[a] - 1)));
  }
  TrilinearFootprint fp;
  for (int k = 0; k < 8; ++k) {
    const int bx = k & 1, by = (k >> 1) & 1, bz = (k >> 2) & 1;
    fp.voxel[k] = n.index(bx ? i1[0] : i0[0], by ? i1[1] : i0[1], bz ? i1[2] : i0[2]);
    fp.weight[k] = (bx ? f[0] : 1.f - f[0]) * (by ? f[1] : 1.f - f[1]) * (bz ? f[2] : 1.f - f[2]);
  }
  return fp;
}

// Channel c of the grid at `local`, on scalar type T (a tape leaf per tap in the taped mode).
template <class T>
T grid_eval(const Param& p, const TrilinearFootprint& fp, int channel) {
  const size_t channels = size_t(grid_size(p).channels);
  T out = T(0.f);
  for (int k = 0; k < 8; ++k)
    if (fp.weight[k] != 0.f)
      out = out + ParamLoad<T>::load_weighted(p, fp.voxel[k] * channels + size_t(channel), fp.weight[k]);
  return out;
}

// One channel of a grid read in float, for the lookups of tracking (every tentative collision
// reads the density): the arithmetic of trilinear_footprint followed by grid_eval<float>, tap
// for tap, so the value is bitwise the same, but the shape is read once per ray instead of once
// per lookup and no footprint is built. (A zero-weight tap adds +0 here where grid_eval skips
// it: the same value.)
class GridReader {
 public:
  GridReader(const Param& p, int channel)
      : data_(p.value.data() + channel), n_(grid_size(p)), channels_(size_t(n_.channels)) {}

  float operator()(const Vec3f& local) const {
    const int dims[3] = {n_.x, n_.y, n_.z};
    long i0[3], i1[3];
    float w[3][2];
    for (int a = 0; a < 3; ++a) {
      const float q = local[a] * float(dims[a]) - 0.5f;
      const float fl = std::floor(q);
      const float f = q - fl;
      const long base = long(fl);
      i0[a] = std::clamp(base, 0L, long(dims[a] - 1));
      i1[a] = std::clamp(base + 1, 0L, long(dims[a] - 1));
      w[a][0] = 1.f - f;
      w[a][1] = f;
    }
    const size_t x[2] = {size_t(i0[0]) * channels_, size_t(i1[0]) * channels_};
    const size_t row = n_.x * channels_, slab = size_t(n_.y) * row;
    const size_t y[2] = {size_t(i0[1]) * row, size_t(i1[1]) * row};
    const size_t z[2] = {size_t(i0[2]) * slab, size_t(i1[2]) * slab};
    float out = 0.f;
    for (int k = 0; k < 8; ++k) {
      const int bx = k & 1, by = (k >> 1) & 1, bz = (k >> 2) & 1;
      out = out + data_[z[bz] + y[by] + x[bx]] * (w[0][bx] * w[1][by] * w[2][bz]);
    }
    return out;
  }

 private:
  const float* data_;
  GridSize n_;
  size_t channels_;
};

template <class T>
Spectrum<T> grid_eval_rgb(const Param& p, const TrilinearFootprint& fp) {
  if (grid_size(p).channels == 1) {
    const T v = grid_eval<T>(p, fp, 0);
    return {v, v, v};
  }
  return {grid_eval<T>(p, fp, 0), grid_eval<T>(p, fp, 1), grid_eval<T>(p, fp, 2)};
}

// Adds adjoint · ∂(channel c at the footprint)/∂voxel into the gradient (the transpose of eval).
inline void grid_backprop(int handle, const Param& p, const TrilinearFootprint& fp, int channel, float adjoint,
                          GradientAccumulator& grads) {
  const size_t channels = size_t(grid_size(p).channels);
  grads.add_each(handle, [&](auto&& add) {
    for (int k = 0; k < 8; ++k)
      if (fp.weight[k] != 0.f) add(fp.voxel[k] * channels + size_t(channel), fp.weight[k] * adjoint);
  });
}

inline void grid_backprop_rgb(int handle, const Param& p, const TrilinearFootprint& fp, const Vec3f& adjoint,
                              GradientAccumulator& grads) {
  if (grid_size(p).channels == 1) {
    grid_backprop(handle, p, fp, 0, adjoint.x + adjoint.y + adjoint.z, grads);
    return;
  }
  for (int c = 0; c < 3; ++c) grid_backprop(handle, p, fp, c, adjoint[c], grads);
}

// Block majorants: the grid cut into blocks of `block` voxels per axis, each holding an upper
// bound of the interpolated channel 0 inside it. The interpolant inside a block blends voxel
// centres up to one voxel beyond the block's faces, so each bound is the maximum over the
// block's voxels widened by one on every side (clamped). Trilinear weights are a convex
// combination, so the bound is exact, not a guess; `headroom` (≥ 1) scales it so small parameter
// updates between rebuilds stay under it. Along an axis of more than kMaxBlocksPerAxis · block
// voxels the blocks are longer, so that no axis has more than kMaxBlocksPerAxis of them: a ray's
// DDA steps through every block it crosses, and a 1×1×2²¹ grid (2¹⁸ blocks along z) rendered at
// 1,050 samples/s against 205,000 for a 1×1×4096 one (32², 4 spp, one thread).
inline constexpr int kMaxBlocksPerAxis = 256;

struct MajorantGrid {
  int block = 8;               // voxels per block asked for
  int size[3] = {8, 8, 8};     // voxels per block along x, y, z: `block`, more along a long axis
  int bx = 1, by = 1, bz = 1;  // block counts
  GridSize voxels;
  std::vector<float> value;  // per block, (z·by + y)·bx + x

  float at(int x, int y, int z) const { return value[(size_t(z) * size_t(by) + size_t(y)) * size_t(bx) + size_t(x)]; }
  float max() const { return value.empty() ? 0.f : *std::max_element(value.begin(), value.end()); }
};

inline MajorantGrid build_majorants(const Param& p, int block, float headroom) {
  MajorantGrid m;
  m.block = std::max(1, block);
  m.voxels = grid_size(p);
  const GridSize& n = m.voxels;
  const int dims[3] = {n.x, n.y, n.z};
  for (int a = 0; a < 3; ++a)
    m.size[a] = std::max(m.block, int((int64_t(dims[a]) + kMaxBlocksPerAxis - 1) / kMaxBlocksPerAxis));
  const int sx = m.size[0], sy = m.size[1], sz = m.size[2];
  m.bx = int((int64_t(n.x) + sx - 1) / sx);
  m.by = int((int64_t(n.y) + sy - 1) / sy);
  m.bz = int((int64_t(n.z) + sz - 1) / sz);
  m.value.assign(size_t(m.bx) * size_t(m.by) * size_t(m.bz), 0.f);
  const size_t channels = size_t(n.channels);
  // 64-bit block bounds: a block of 2^30 voxels (a 1×1×2^30 grid's single one) times its index.
  auto lo = [](int b, int s) { return int(std::max<int64_t>(0, int64_t(b) * s - 1)); };
  auto hi_end = [](int b, int s, int n) { return int(std::min<int64_t>(n - 1, (int64_t(b) + 1) * s)); };
  for (int z = 0; z < m.bz; ++z)
    for (int y = 0; y < m.by; ++y)
      for (int x = 0; x < m.bx; ++x) {
        float hi = 0.f;
        for (int iz = lo(z, sz); iz <= hi_end(z, sz, n.z); ++iz)
          for (int iy = lo(y, sy); iy <= hi_end(y, sy, n.y); ++iy)
            for (int ix = lo(x, sx); ix <= hi_end(x, sx, n.x); ++ix)
              hi = std::max(hi, p.value[n.index(ix, iy, iz) * channels]);
        m.value[(size_t(z) * size_t(m.by) + size_t(y)) * size_t(m.bx) + size_t(x)] = hi * headroom;
      }
  return m;
}

// One piece of a ray inside one majorant block: local-space ray parameters [t0, t1).
struct MajorantSegment {
  float t0, t1, majorant;
};

// Visits the blocks a ray o + t·d (local coordinates, the grid in [0,1]³) crosses within
// [t_min, t_max], in order, calling visit(segment) until it returns false (Amanatides and Woo
// 1987). The segments tile the part of [t_min, t_max] inside the grid exactly.
template <class Visit>
void traverse_majorants(const MajorantGrid& m, const Vec3f& o, const Vec3f& d, float t_min, float t_max,
                        Visit&& visit) {
  // Clip to the unit cube.
  float t0 = t_min, t1 = t_max;
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.f) {
      if (o[a] < 0.f || o[a] > 1.f) return;
      continue;
    }
    const float inv = 1.f / d[a];
    float near = (0.f - o[a]) * inv, far = (1.f - o[a]) * inv;
    if (near > far) std::swap(near, far);
    t0 = std::max(t0, near);
    t1 = std::min(t1, far);
  }
  if (!(t0 < t1)) return;
  const int counts[3] = {m.bx, m.by, m.bz};
  const int dims[3] = {m.voxels.x, m.voxels.y, m.voxels.z};
  int cell[3], step[3];
  float next[3], delta[3];
  const Vec3f start = o + d * t0;
  for (int a = 0; a < 3; ++a) {
    // Block size in local units: size[a] voxels of 1/dims each (the last block may be partial).
    const float size = float(m.size[a]) / float(dims[a]);
    cell[a] = std::clamp(int(std::floor(start[a] / size)), 0, counts[a] - 1);
    if (d[a] > 0.f) {
      step[a] = 1;
      next[a] = t0 + (float(cell[a] + 1) * size - start[a]) / d[a];
      delta[a] = size / d[a];
    } else if (d[a] < 0.f) {
      step[a] = -1;
      next[a] = t0 + (float(cell[a]) * size - start[a]) / d[a];
      delta[a] = -size / d[a];
    } else {
      step[a] = 0;
      next[a] = std::numeric_limits<float>::infinity();
      delta[a] = std::numeric_limits<float>::infinity();
    }
  }
  float t = t0;
  while (t < t1) {
    const int a = next[0] < next[1] ? (next[0] < next[2] ? 0 : 2) : (next[1] < next[2] ? 1 : 2);
    const float exit = std::min(next[a], t1);
    if (exit > t && !visit(MajorantSegment{t, exit, m.at(cell[0], cell[1], cell[2])})) return;
    t = std::max(t, exit);
    cell[a] += step[a];
    if (cell[a] < 0 || cell[a] >= counts[a]) return;
    next[a] += delta[a];
  }
}

}  // namespace bl
