#include "engine/integrators/loss.h"

#include <cmath>

#include "engine/core/errors.h"

namespace bl {

LossType parse_loss(const std::string& name) {
  if (name == "l2") return LossType::L2;
  if (name == "l1") return LossType::L1;
  if (name == "rel_l2") return LossType::RelativeL2;
  throw InputError("unknown loss '" + name + "' (expected l2, l1 or rel_l2)");
}

const char* loss_name(LossType t) {
  switch (t) {
    case LossType::L2:
      return "l2";
    case LossType::L1:
      return "l1";
    case LossType::RelativeL2:
      return "rel_l2";
  }
  return "?";
}

double loss_pixel(LossType type, const Vec3f& value, const Vec3f& target, double values, Vec3f* gradient) {
  double sum = 0;
  for (int c = 0; c < 3; ++c) {
    double d = double(value[c]) - double(target[c]);
    double g = 0;
    switch (type) {
      case LossType::L2:
        sum += d * d;
        g = 2 * d;
        break;
      case LossType::L1:
        sum += std::abs(d);
        g = d > 0 ? 1 : (d < 0 ? -1 : 0);
        break;
      case LossType::RelativeL2: {
        double w = 1.0 / (double(target[c]) * target[c] + kRelativeL2Epsilon);
        sum += d * d * w;
        g = 2 * d * w;
        break;
      }
    }
    if (gradient) (*gradient)[c] = float(g / values);
  }
  return sum / values;
}

LossResult compute_loss(LossType type, const Image& image, const Image& target) {
  if (image.width != target.width || image.height != target.height)
    throw InputError("target is " + std::to_string(target.width) + "x" + std::to_string(target.height) +
                     " but the render is " + std::to_string(image.width) + "x" + std::to_string(image.height));
  LossResult r;
  r.adjoint = Image(image.width, image.height, 3);
  const double values = double(image.pixel_count()) * 3.0;
  for (int y = 0; y < image.height; ++y)
    for (int x = 0; x < image.width; ++x) {
      Vec3f v{image.at(x, y, 0), image.at(x, y, 1), image.at(x, y, 2)};
      Vec3f t{target.at(x, y, 0), target.at(x, y, 1), target.at(x, y, 2)};
      Vec3f g;
      r.value += loss_pixel(type, v, t, values, &g);
      for (int c = 0; c < 3; ++c) r.adjoint.at(x, y, c) = g[c];
    }
  return r;
}

LossResult compute_block_loss(LossType type, const Image& image, const Image& target, int k) {
  if (image.width != target.width || image.height != target.height)
    throw InputError("target is " + std::to_string(target.width) + "x" + std::to_string(target.height) +
                     " but the render is " + std::to_string(image.width) + "x" + std::to_string(image.height));
  if (k < 1 || image.width % k != 0 || image.height % k != 0)
    throw InputError("loss blocks of " + std::to_string(k) + " do not divide the " + std::to_string(image.width) + "x" +
                     std::to_string(image.height) + " render");
  LossResult blocks = compute_loss(type, box_downsample(image, k), box_downsample(target, k));
  LossResult r{blocks.value, Image(image.width, image.height, 3)};
  const float share = 1.f / float(k * k);
  for (int y = 0; y < image.height; ++y)
    for (int x = 0; x < image.width; ++x)
      for (int c = 0; c < 3; ++c) r.adjoint.at(x, y, c) = blocks.adjoint.at(x / k, y / k, c) * share;
  return r;
}

}  // namespace bl
