#pragma once
// Triangle meshes from files: Wavefront OBJ (tinyobjloader) and PLY (read here: ASCII and binary,
// either byte order). The meshes come back in object space, not yet finalized (finalize_mesh);
// every error is an InputError with one line naming the file.
#include <string>

#include "engine/scene/scene.h"

namespace bl {

// Polygons are fan-triangulated; a vertex is one (position, normal, uv) combination.
// flip_tex_coords: v ← 1 − v, Mitsuba 3's default for OBJ files.
Mesh read_obj(const std::string& path, bool flip_tex_coords);

// Vertex properties x, y, z and optionally nx, ny, nz and u, v (or s, t / texture_u, texture_v);
// faces as `vertex_indices` (or `vertex_index`) lists, fan-triangulated.
Mesh read_ply(const std::string& path);

// Mitsuba 3's vertex normals for a mesh without them (Mesh::recompute_vertex_normals): each
// triangle's unit normal, from its winding, weighted by the triangle's angle at the vertex
// (Thürmer and Wüthrich 1998); degenerate triangles add nothing, and a vertex they leave without
// a normal gets (1, 0, 0), as in Mitsuba.
std::vector<Vec3f> angle_weighted_normals(const std::vector<Vec3f>& positions, const std::vector<uint32_t>& indices);

// A UV sphere of `segments` around × segments/2 rings, radius 1 at the origin, with normals
// and uvs (u around the +z axis, v from the south pole).
Mesh make_sphere(int segments = 64);

}  // namespace bl
