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
  bool always = false;  // boundary, non-manifold, crease or seam, or inconsistently wound: a candidate from everywhere
  bool consistent = true;  // a two-face edge traversed in opposite directions by its faces (consistent winding)
};

struct EdgeTable {
  std::vector<MeshEdge> edges;
  std::vector<uint32_t> copies;  // pairs (vertex at p0, vertex at p1) per adjacent face
};

// Whether an edge is a discontinuity seen from `eye`: always for boundary, non-manifold and
// crease edges, for the others when one face is front- and the other back-facing.
bool candidate_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye);

// Whether a two-face edge of consistent winding is a fold seen from `eye` (both faces turned towards
// it, or both away; with a face wound the other way round the facing test says nothing):
// its jump is between its own faces, so a side ray that meets neither (near an outline the fold
// runs along) measures another edge's jump. The boundary terms count a fold's sample only where
// both side rays meet one of its faces (on_faces).
bool fold_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye);
inline bool on_faces(const MeshEdge& e, const Hit& hit) {
  return hit.mesh == e.mesh && (uint32_t(hit.triangle) == e.f0 || uint32_t(hit.triangle) == e.f1);
}

// The edges of the meshes in `wanted` that can be a discontinuity seen from somewhere (all but
// those between two coplanar faces with continuous shading), or, given an eye, those that are one
// seen from it.
EdgeTable edge_topology(const Scene& scene, const std::vector<int>& wanted, const Vec3f* eye = nullptr);

// Adds the end gradients ga (at the edge's p0) and gb (at p1) to every face's copy of them (a
// welded edge splits them evenly between the faces' copies).
void add_to_edge(const EdgeTable& table, const MeshEdge& e, const Vec3d& ga, const Vec3d& gb, std::vector<Vec3d>& g);

}  // namespace bl::edges

namespace bl::edges {

// A bounding hierarchy over a table's edges for sampling, from a point x, an edge that can be a
// discontinuity seen from x, in O(log edges) instead of a scan. Each node bounds its edges' end
// points (a box) and their faces' normals (a cone); a node whose faces all face x, or all face
// away from it, holds no silhouette from x and is skipped unless it holds edges that are
// candidates from everywhere (boundary, non-manifold, crease). Children are chosen in proportion
// to edge length over squared distance (near, long edges first); within a leaf, by length.
struct EdgeTree {
  struct Node {
    Vec3f lo, hi;
    Vec3f axis{0.f, 0.f, 1.f};      // normal cone of the faces
    float cos_angle = -1.f;         // cosine of its half-angle; -1: no bound
    float length = 0.f;             // total edge length
    bool always = false;            // holds an edge that is a candidate from everywhere
    int left = -1, right = -1;      // children; leaf when left < 0
    uint32_t first = 0, count = 0;  // leaf: edges order[first, first + count)
  };
  std::vector<Node> nodes;
  std::vector<uint32_t> order;  // edge indices grouped by leaf
};
EdgeTree build_edge_tree(const Scene& scene, const EdgeTable& table);

// Samples an edge of `table` from x with u in [0, 1): its index and its probability. False when
// no node can hold a discontinuity seen from x. The edge may still not be a candidate from x
// (check with candidate_from; its contribution is then zero). Each level rescales u, so u needs
// 53 bits (PathSampler::get_double): with a float's 24 the choice at depth d is made with 24 − d
// bits, ~2⁻²⁴/p apart for an edge of probability p (±0.6% for p = 1e-5).
bool sample_edge(const EdgeTable& table, const EdgeTree& tree, const Vec3f& x, double u, uint32_t* edge,
                 double* probability);

}  // namespace bl::edges
