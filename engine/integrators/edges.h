#pragma once
// Edges of meshes as discontinuities of what a point sees (shared by the boundary terms): welded
// topology, candidate tests, and how an edge's end gradients reach every copy of its vertices.
#include <cstdint>
#include <vector>

#include "engine/scene/scene.h"

namespace bl::edges {

// An edge of a mesh after welding: its two end positions and, per adjacent face, that face's
// vertex indices at the two ends (copies of the same position when the mesh splits vertices).
struct MeshEdge {
  int mesh = 0;
  Vec3f p0, p1;
  uint32_t first_copy = 0, faces = 0;  // into EdgeTable::copies, `faces` pairs
  uint32_t f0 = 0, f1 = 0;             // the two faces of a two-face edge
  bool always = false;                 // boundary, non-manifold or crease: a candidate from everywhere
};

struct EdgeTable {
  std::vector<MeshEdge> edges;
  std::vector<uint32_t> copies;  // pairs (vertex at p0, vertex at p1) per adjacent face
};

// Whether an edge is a discontinuity seen from `eye`: always for boundary, non-manifold and
// crease edges, for the others when one face is front- and the other back-facing.
bool candidate_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye);

// The edges of the meshes in `wanted` that can be a discontinuity seen from somewhere (all but
// those between two coplanar faces with continuous shading), or, given an eye, those that are one
// seen from it.
EdgeTable edge_topology(const Scene& scene, const std::vector<int>& wanted, const Vec3f* eye = nullptr);

// Adds the end gradients ga (at the edge's p0) and gb (at p1) to every face's copy of them (a
// welded edge splits them evenly between the faces' copies).
void add_to_edge(const EdgeTable& table, const MeshEdge& e, const Vec3d& ga, const Vec3d& gb, std::vector<Vec3d>& g);

}  // namespace bl::edges
