#pragma once
// Pinhole camera with Mitsuba 3's ray convention, so references from it compare pixel for pixel:
// film point (px, py) in [0,W]×[0,H], px right, py down, row 0 on top;
// d = normalize(forward + (2px/W − 1)·tx·right + (1 − 2py/H)·ty·up), with tx, ty from the fov
// on its axis and the aspect ratio. Rays start on the near plane.
#include <cmath>
#include <string>

#include "engine/core/math.h"

namespace bl {

struct Ray {
  Vec3f origin, direction;
  float tmin = 0.f, tmax = 1e30f;
};

struct Camera {
  std::string name;
  Vec3f origin{0, 0, 0}, target{0, 0, -1}, up{0, 1, 0};
  float fov_degrees = 40.f;
  // The film axis `fov_degrees` spans (Mitsuba 3's fov_axis): x, y, the diagonal, or the smaller
  // or larger side (whichever it is at the current resolution).
  enum class FovAxis { X, Y, Diagonal, Smaller, Larger } fov_axis = FovAxis::X;
  int width = 256, height = 256;
  float near_clip = 1e-3f;
  int medium = -1;  // index into Scene::media the camera sits in, -1 = vacuum

  // Derived frame; call update() after changing any field above.
  Vec3f forward, right, true_up;
  float tan_x = 0, tan_y = 0;
  void update() {
    forward = normalize(target - origin);
    right = normalize(cross(forward, up));
    true_up = cross(right, forward);
    float t = std::tan(fov_degrees * kPi / 360.f);
    float aspect = float(width) / float(height);
    FovAxis axis = fov_axis;
    if (axis == FovAxis::Smaller) axis = aspect >= 1.f ? FovAxis::Y : FovAxis::X;
    if (axis == FovAxis::Larger) axis = aspect >= 1.f ? FovAxis::X : FovAxis::Y;
    if (axis == FovAxis::Diagonal) {
      const float diagonal = std::sqrt(1.f + aspect * aspect);
      tan_x = t * aspect / diagonal;
      tan_y = t / diagonal;
    } else {
      tan_x = axis == FovAxis::X ? t : t * aspect;
      tan_y = axis == FovAxis::X ? t / aspect : t;
    }
  }
  Ray generate(float px, float py) const {
    Vec3f d = normalize(forward + right * ((2.f * px / float(width) - 1.f) * tan_x) +
                        true_up * ((1.f - 2.f * py / float(height)) * tan_y));
    Ray r;
    r.origin = origin;
    r.direction = d;
    r.tmin = near_clip / dot(d, forward);
    return r;
  }
};

}  // namespace bl
