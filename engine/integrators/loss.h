#pragma once
// Image losses. Each is a mean over pixels and channels of a per-pixel term, so the image-space
// adjoint δI of a pixel depends only on that pixel — which lets the adjoint pass compute it the
// moment the pixel has been rendered.
#include <string>

#include "engine/core/math.h"
#include "engine/io/image_io.h"

namespace bl {

enum class LossType { L2, L1, RelativeL2 };

// Parses "l2", "l1", "rel_l2"; throws InputError otherwise.
LossType parse_loss(const std::string& name);
const char* loss_name(LossType t);

// Relative L2 divides by target² + ε so dark pixels do not dominate.
inline constexpr float kRelativeL2Epsilon = 1e-2f;

// The loss term of one pixel (summed over its channels, divided by `values` = W·H·3) and its
// gradient with respect to the pixel value.
double loss_pixel(LossType type, const Vec3f& value, const Vec3f& target, double values, Vec3f* gradient);

struct LossResult {
  double value = 0;
  Image adjoint;  // δI
};
LossResult compute_loss(LossType type, const Image& image, const Image& target);

// A low-pass loss: the loss of the k×k block means of `image` against those of `target`. The
// adjoint is full-size: every pixel of a block gets the block's δ / k², so a render's Monte Carlo
// noise is averaged over k² pixels before it enters δI.
LossResult compute_block_loss(LossType type, const Image& image, const Image& target, int k);

}  // namespace bl
