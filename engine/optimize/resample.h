#pragma once
// Resizing of image-shaped parameter buffers (H×W×C, row-major) for coarse-to-fine schedules and
// for comparing textures at the resolution the views resolve. Downsampling averages the source
// texels whose centres fall inside each target texel; upsampling interpolates bilinearly between
// texel centres (the texture lookup's convention) with clamped edges.
#include <vector>

namespace bl {

std::vector<float> resample(const std::vector<float>& src, int width, int height, int channels, int new_width,
                            int new_height);

// The same rules per axis for volume grids [Z, Y, X, C] (x fastest): (x, y, z) → (nx, ny, nz).
std::vector<float> resample_grid(const std::vector<float>& src, int x, int y, int z, int channels, int nx, int ny,
                                 int nz);

}  // namespace bl
