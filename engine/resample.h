#pragma once
// Resizing of image-shaped parameter buffers (H×W×C, row-major) for coarse-to-fine schedules and
// for comparing textures at the resolution the views resolve. Downsampling averages the source
// texels whose centres fall inside each target texel; upsampling interpolates bilinearly between
// texel centres (the texture lookup's convention) with clamped edges.
#include <vector>

namespace bl {

std::vector<float> resample(const std::vector<float>& src, int width, int height, int channels, int new_width,
                            int new_height);

}  // namespace bl
