#include "engine/integrators/edges.h"

#include <algorithm>
#include <cstring>
#include <unordered_map>

namespace bl::edges {

namespace {

// Welding key: a position's bits, −0 taken as +0 (a sphere's pole copies differ only there).
// Positions that are merely close do not weld (a sphere's seam: cos 2π ≠ 1 in float); their
// edges count as boundary edges, which costs samples but no bias where both sides see the same.
struct PositionKey {
  uint32_t x, y, z;
  bool operator==(const PositionKey& o) const { return x == o.x && y == o.y && z == o.z; }
};
struct PositionHash {
  size_t operator()(const PositionKey& k) const { return size_t(mix64((uint64_t(k.x) << 32 | k.y) ^ mix64(k.z))); }
};

uint32_t weld_id(const Vec3f& p, std::unordered_map<PositionKey, uint32_t, PositionHash>& ids) {
  const float x = p.x + 0.f, y = p.y + 0.f, z = p.z + 0.f;  // −0 + 0 = +0
  PositionKey key;
  std::memcpy(&key.x, &x, 4);
  std::memcpy(&key.y, &y, 4);
  std::memcpy(&key.z, &z, 4);
  return ids.emplace(key, uint32_t(ids.size())).first->second;
}

bool front_facing(const Mesh& m, uint32_t face, const Vec3f& eye) {
  return dot(m.face_normals[face], eye - m.positions[m.indices[3 * size_t(face)]]) > 0.f;
}

// Whether the shading is discontinuous across an edge between two faces (vertex indices of the
// faces' copies of its ends).
bool shading_crease(const Mesh& m, uint32_t f0, uint32_t f1, const uint32_t* c0, const uint32_t* c1) {
  const Vec3f &n0 = m.face_normals[f0], &n1 = m.face_normals[f1];
  if (dot(n0, n1) > 1.f - 1e-6f) return false;  // coplanar: the same plane on both sides
  if (m.normals.empty()) return true;           // flat shading
  for (int k = 0; k < 2; ++k) {
    const Vec3f &a = m.normals[c0[k]], &b = m.normals[c1[k]];
    if (a.x != b.x || a.y != b.y || a.z != b.z) return true;  // split normals
  }
  return false;
}

}  // namespace

// Whether an edge is a discontinuity seen from `eye`: always for boundary, non-manifold and
// crease edges, for the others when one face is front- and the other back-facing.
bool candidate_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye) {
  if (e.always) return true;
  const Mesh& m = scene.meshes[size_t(e.mesh)];
  return front_facing(m, e.f0, eye) != front_facing(m, e.f1, eye);
}

// The edges of the meshes in `wanted` that can be a discontinuity seen from somewhere (all but
// those between two coplanar faces with continuous shading), or, given an eye, those that are one
// seen from it.
EdgeTable edge_topology(const Scene& scene, const std::vector<int>& wanted, const Vec3f* eye) {
  EdgeTable table;
  for (int mi : wanted) {
    const Mesh& m = scene.meshes[size_t(mi)];
    if (scene.materials[size_t(m.material)].is_null) continue;  // invisible
    std::unordered_map<PositionKey, uint32_t, PositionHash> ids;
    std::vector<uint32_t> welded(m.vertex_count());
    for (size_t v = 0; v < welded.size(); ++v) welded[v] = weld_id(m.positions[v], ids);
    // (welded end a < welded end b, face, corner) for every face edge, grouped by ends.
    struct Record {
      uint64_t key;
      uint32_t face, corner;
    };
    std::vector<Record> records;
    records.reserve(m.indices.size());
    for (uint32_t f = 0; f < uint32_t(m.triangle_count()); ++f) {
      if (!(m.triangle_area(f) > 0.f)) continue;  // degenerate: no visible face
      for (uint32_t c = 0; c < 3; ++c) {
        const uint32_t a = welded[m.indices[3 * size_t(f) + c]], b = welded[m.indices[3 * size_t(f) + (c + 1) % 3]];
        if (a == b) continue;
        records.push_back({uint64_t(std::min(a, b)) << 32 | std::max(a, b), f, c});
      }
    }
    std::sort(records.begin(), records.end(),
              [](const Record& x, const Record& y) { return x.key != y.key ? x.key < y.key : x.face < y.face; });
    for (size_t i = 0; i < records.size();) {
      size_t j = i;
      while (j < records.size() && records[j].key == records[i].key) ++j;
      // Ends in the welded order: end 0 is the smaller welded id.
      const uint32_t end0 = uint32_t(records[i].key >> 32);
      MeshEdge e;
      e.mesh = mi;
      e.first_copy = uint32_t(table.copies.size());
      e.faces = uint32_t(j - i);
      for (size_t k = i; k < j; ++k) {
        const uint32_t f = records[k].face, c = records[k].corner;
        uint32_t va = m.indices[3 * size_t(f) + c], vb = m.indices[3 * size_t(f) + (c + 1) % 3];
        if (welded[va] != end0) std::swap(va, vb);
        table.copies.push_back(va);
        table.copies.push_back(vb);
      }
      const uint32_t* copies = table.copies.data() + e.first_copy;
      e.p0 = m.positions[copies[0]];
      e.p1 = m.positions[copies[1]];
      bool keep = true;
      e.always = e.faces != 2;  // boundary or non-manifold
      if (e.faces == 2) {
        e.f0 = records[i].face;
        e.f1 = records[i + 1].face;
        e.always = shading_crease(m, e.f0, e.f1, copies, copies + 2);
        keep = e.always || dot(m.face_normals[e.f0], m.face_normals[e.f1]) <= 1.f - 1e-6f;  // can be a silhouette
      }
      if (keep && eye) keep = candidate_from(scene, e, *eye);
      if (keep)
        table.edges.push_back(e);
      else
        table.copies.resize(e.first_copy);
      i = j;
    }
  }
  return table;
}

// Adds the end gradients ga (at the edge's p0) and gb (at p1) to every face's copy of them.
void add_to_edge(const EdgeTable& table, const MeshEdge& e, const Vec3d& ga, const Vec3d& gb, std::vector<Vec3d>& g) {
  const uint32_t* copies = table.copies.data() + e.first_copy;
  const double share = 1.0 / double(e.faces);
  for (uint32_t f = 0; f < e.faces; ++f) {
    g[copies[2 * f]] += ga * share;
    g[copies[2 * f + 1]] += gb * share;
  }
}

}  // namespace bl::edges
