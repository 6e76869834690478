#pragma once
// How far apart two shapes of one mesh are: the optimizer's shape error for `<shape>.positions`.
#include <cstdint>
#include <vector>

namespace bl {

// Symmetric mean point-to-surface distance ("Chamfer distance" of the surfaces at the vertices):
// ½ (mean over a's vertices of the distance to b's surface + mean over b's vertices of the distance
// to a's surface). `a` and `b` are [N, 3] positions of the same triangles `indices` (the surfaces
// may differ in any way; only the triangles' index lists are shared). Unlike the vertex error
// (RMSE of a − b), it does not count vertices sliding along the surface, which images cannot see.
// Exact closest points, brute force over triangles (parallel; 2562 vertices × 5120 triangles take
// ~0.2 s): returns −1 when N × triangles exceeds 5·10⁸ (~20 s) rather than running for minutes.
double surface_distance(const std::vector<float>& a, const std::vector<float>& b, const std::vector<uint32_t>& indices);

}  // namespace bl
