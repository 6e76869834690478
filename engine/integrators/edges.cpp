#include "engine/integrators/edges.h"

#include "engine/core/weld.h"

#include <algorithm>

namespace bl::edges {

namespace {

bool front_facing(const Mesh& m, uint32_t face, const Vec3f& eye) {
  return dot(m.face_normals[face], eye - m.positions[m.indices[3 * size_t(face)]]) > 0.f;
}

bool differ(const Vec3f& a, const Vec3f& b) { return a.x != b.x || a.y != b.y || a.z != b.z; }

// Whether the shading is discontinuous across an edge between two faces (vertex indices of the
// faces' copies of its ends): a fold of a flat-shaded mesh, or, folded or not, copies of its ends
// that differ in what shading reads — split normals, a uv seam of a textured material (a texture
// atlas: the two sides show different texels), different vertex colours. `textured`: the mesh's
// material reads a texture (without uvs each face's uv is its own barycentrics: every edge is a
// seam).
bool shading_crease(const Mesh& m, bool textured, uint32_t f0, uint32_t f1, const uint32_t* c0, const uint32_t* c1) {
  const Vec3f &n0 = m.face_normals[f0], &n1 = m.face_normals[f1];
  const bool coplanar = dot(n0, n1) > 1.f - 1e-6f;
  if (!coplanar && m.normals.empty()) return true;  // flat shading
  if (textured && m.uvs.empty()) return true;
  for (int k = 0; k < 2; ++k) {
    if (!m.normals.empty() && differ(m.normals[c0[k]], m.normals[c1[k]])) return true;  // split normals
    if (textured) {
      const Vec2f &a = m.uvs[c0[k]], &b = m.uvs[c1[k]];
      if (a.x != b.x || a.y != b.y) return true;  // uv seam
    }
    if (!m.colors.empty() && differ(m.colors[c0[k]], m.colors[c1[k]])) return true;
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

bool fold_from(const Scene& scene, const MeshEdge& e, const Vec3f& eye) {
  if (e.faces != 2 || !e.consistent) return false;
  const Mesh& m = scene.meshes[size_t(e.mesh)];
  return front_facing(m, e.f0, eye) == front_facing(m, e.f1, eye);
}

// The edges of the meshes in `wanted` that can be a discontinuity seen from somewhere (all but
// those between two coplanar faces with continuous shading), or, given an eye, those that are one
// seen from it.
EdgeTable edge_topology(const Scene& scene, const std::vector<int>& wanted, const Vec3f* eye) {
  EdgeTable table;
  for (int mi : wanted) {
    const Mesh& m = scene.meshes[size_t(mi)];
    const Material& material = scene.materials[size_t(m.material)];
    if (material.is_null) continue;  // invisible
    const bool textured =
        material.albedo.bitmap || material.specular.bitmap || material.roughness.bitmap || material.metallic.bitmap;
    PositionWelder welder;  // engine/core/weld.h
    std::vector<uint32_t> welded(m.vertex_count());
    for (size_t v = 0; v < welded.size(); ++v)
      welded[v] = welder.id(m.positions[v].x, m.positions[v].y, m.positions[v].z);
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
      int reversed = 0;  // faces that traverse the edge from end 1 to end 0
      for (size_t k = i; k < j; ++k) {
        const uint32_t f = records[k].face, c = records[k].corner;
        uint32_t va = m.indices[3 * size_t(f) + c], vb = m.indices[3 * size_t(f) + (c + 1) % 3];
        if (welded[va] != end0) std::swap(va, vb), ++reversed;
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
        // Two faces wound consistently traverse their edge in opposite directions. Where they do
        // not (an asset with a flipped face), one face normal points inwards and the facing test
        // of candidate_from would miss silhouettes: the edge is a candidate from everywhere.
        e.consistent = reversed == 1;
        e.always = !e.consistent || shading_crease(m, textured, e.f0, e.f1, copies, copies + 2);
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

namespace bl::edges {

namespace {

struct Build {
  const Scene& scene;
  const EdgeTable& table;
  EdgeTree& tree;
  std::vector<Vec3f> mid;

  // Normal cone of the faces of edges [first, first + count) of tree.order.
  void cone(EdgeTree::Node& n) const {
    Vec3d sum(0.0);
    auto faces = [&](auto&& f) {
      for (uint32_t k = n.first; k < n.first + n.count; ++k) {
        const MeshEdge& e = table.edges[tree.order[k]];
        const Mesh& m = scene.meshes[size_t(e.mesh)];
        if (e.faces != 2) continue;
        f(m.face_normals[e.f0]);
        f(m.face_normals[e.f1]);
      }
    };
    faces([&](const Vec3f& v) { sum += Vec3d(v); });
    const double len = length(sum);
    if (!(len > 1e-6)) return;  // no bound
    n.axis = Vec3f(sum / len);
    float c = 1.f;
    faces([&](const Vec3f& v) { c = std::min(c, dot(v, n.axis)); });
    n.cos_angle = c;
  }

  int node(uint32_t first, uint32_t count) {
    const int index = int(tree.nodes.size());
    tree.nodes.emplace_back();
    EdgeTree::Node n;
    n.first = first;
    n.count = count;
    n.lo = Vec3f(1e30f);
    n.hi = Vec3f(-1e30f);
    for (uint32_t k = first; k < first + count; ++k) {
      const MeshEdge& e = table.edges[tree.order[k]];
      for (const Vec3f& p : {e.p0, e.p1}) {
        n.lo = Vec3f(std::min(n.lo.x, p.x), std::min(n.lo.y, p.y), std::min(n.lo.z, p.z));
        n.hi = Vec3f(std::max(n.hi.x, p.x), std::max(n.hi.y, p.y), std::max(n.hi.z, p.z));
      }
      n.length += length(e.p1 - e.p0);
      n.always = n.always || e.always;
    }
    if (!n.always) cone(n);
    if (count > 4) {
      const Vec3f ext = n.hi - n.lo;
      const int axis = ext.x > ext.y ? (ext.x > ext.z ? 0 : 2) : (ext.y > ext.z ? 1 : 2);
      auto begin = tree.order.begin() + first, end = begin + count, middle = begin + count / 2;
      std::nth_element(begin, middle, end, [&](uint32_t a, uint32_t b) { return mid[a][axis] < mid[b][axis]; });
      n.left = node(first, count / 2);
      n.right = node(first + count / 2, count - count / 2);
    }
    tree.nodes[size_t(index)] = n;
    return index;
  }
};

// Whether every face of the node has x on the same side (then no edge in it is a silhouette).
bool one_sided_from(const EdgeTree::Node& n, const Vec3f& x) {
  if (n.always || n.cos_angle < 0.f) return false;
  const Vec3f c = (n.lo + n.hi) * 0.5f;
  const float r = 0.5f * length(n.hi - n.lo);
  const Vec3f to = x - c;
  const float d = length(to);
  if (!(d > r * 1.0001f)) return false;
  const double phi = std::asin(double(r / d));  // directions from the box towards x
  const double theta = std::acos(double(std::clamp(n.cos_angle, -1.f, 1.f)));
  const double beta = std::acos(double(std::clamp(dot(n.axis, to / d), -1.f, 1.f)));
  const double half_pi = 1.5707963267948966;
  return beta + theta + phi < half_pi || beta - theta - phi > half_pi;
}

double weight(const EdgeTree::Node& n, const Vec3f& x) {
  if (one_sided_from(n, x)) return 0.0;
  const Vec3f c = (n.lo + n.hi) * 0.5f;
  const Vec3f to = c - x;
  const double r2 = 0.25 * double(dot(n.hi - n.lo, n.hi - n.lo));
  return double(n.length) / (double(dot(to, to)) + r2 + 1e-12);
}

}  // namespace

EdgeTree build_edge_tree(const Scene& scene, const EdgeTable& table) {
  EdgeTree tree;
  if (table.edges.empty()) return tree;
  Build b{scene, table, tree, {}};
  b.mid.resize(table.edges.size());
  tree.order.resize(table.edges.size());
  for (uint32_t i = 0; i < uint32_t(table.edges.size()); ++i) {
    tree.order[i] = i;
    b.mid[i] = (table.edges[i].p0 + table.edges[i].p1) * 0.5f;
  }
  tree.nodes.reserve(2 * table.edges.size() / 4 + 1);
  b.node(0, uint32_t(table.edges.size()));
  return tree;
}

bool sample_edge(const EdgeTable& table, const EdgeTree& tree, const Vec3f& x, double u, uint32_t* edge,
                 double* probability) {
  if (tree.nodes.empty()) return false;
  double p = 1.0;
  int at = 0;
  if (one_sided_from(tree.nodes[0], x)) return false;
  while (tree.nodes[size_t(at)].left >= 0) {
    const EdgeTree::Node& n = tree.nodes[size_t(at)];
    const double wl = weight(tree.nodes[size_t(n.left)], x), wr = weight(tree.nodes[size_t(n.right)], x);
    if (!(wl + wr > 0)) return false;
    const double pl = wl / (wl + wr);
    if (u < pl) {
      p *= pl;
      u = std::min(u / pl, 1.0 - 1e-12);
      at = n.left;
    } else {
      p *= 1 - pl;
      u = std::min((u - pl) / (1 - pl), 1.0 - 1e-12);
      at = n.right;
    }
  }
  const EdgeTree::Node& leaf = tree.nodes[size_t(at)];
  double total = 0;
  for (uint32_t k = leaf.first; k < leaf.first + leaf.count; ++k) {
    const MeshEdge& e = table.edges[tree.order[k]];
    total += double(length(e.p1 - e.p0));
  }
  if (!(total > 0)) return false;
  double run = 0;
  for (uint32_t k = leaf.first; k < leaf.first + leaf.count; ++k) {
    const MeshEdge& e = table.edges[tree.order[k]];
    const double len = double(length(e.p1 - e.p0));
    run += len;
    if (u * total < run || k + 1 == leaf.first + leaf.count) {
      *edge = tree.order[k];
      *probability = p * len / total;
      return len > 0;
    }
  }
  return false;
}

}  // namespace bl::edges
