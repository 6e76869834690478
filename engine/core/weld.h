#pragma once
// Welding vertices by position: copies of a vertex that a uv seam, a hard edge or split normals
// made (a cube's corners, a sphere's seam and poles) get one id. Positions weld when bitwise
// equal, −0 taken as +0 (a sphere's pole copies differ only there); positions that are merely
// close do not (a sphere's seam: cos 2π ≠ 1 in float). Shared by the edges of the boundary terms
// (engine/integrators/edges.cpp), the large-steps Laplacian (engine/optimize/large_steps.cpp) and
// `check`'s directions for vertex positions (engine/integrators/gradient.cpp).
#include <cstdint>
#include <cstring>
#include <unordered_map>

#include "engine/core/sampler.h"  // mix64

namespace bl {

class PositionWelder {
 public:
  // The id of position (x, y, z): 0, 1, … in order of first appearance.
  uint32_t id(float x, float y, float z) {
    x += 0.f, y += 0.f, z += 0.f;  // −0 + 0 = +0
    Key key;
    std::memcpy(&key.x, &x, 4);
    std::memcpy(&key.y, &y, 4);
    std::memcpy(&key.z, &z, 4);
    return ids_.emplace(key, uint32_t(ids_.size())).first->second;
  }
  // Distinct positions so far.
  size_t count() const { return ids_.size(); }
  void reserve(size_t n) { ids_.reserve(n); }

 private:
  struct Key {
    uint32_t x, y, z;
    bool operator==(const Key& o) const { return x == o.x && y == o.y && z == o.z; }
  };
  struct Hash {
    size_t operator()(const Key& k) const { return size_t(mix64((uint64_t(k.x) << 32 | k.y) ^ mix64(k.z))); }
  };
  std::unordered_map<Key, uint32_t, Hash> ids_;
};

}  // namespace bl
