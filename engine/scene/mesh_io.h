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

// A UV sphere of `segments` around × segments/2 rings, radius 1 at the origin, with normals
// and uvs (u around the +z axis, v from the south pole).
Mesh make_sphere(int segments = 64);

}  // namespace bl
