#pragma once
// Small vector math shared by the renderer, its kernels and the tests.
// Vec3 is templated on the scalar so that kernels written once run on float (primal),
// double (tests), forward-mode duals (derivative shaders) and tape variables (taped AD).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>

namespace bl {

inline constexpr float kPi = 3.14159265358979323846f;
inline constexpr float kInvPi = 0.31830988618379067154f;

// Plain-float math under the same unqualified names the AD scalars overload, so templated
// kernel code can call sqrt(x) for any scalar type.
using std::abs;
using std::acos;
using std::atan2;
using std::cos;
using std::exp;
using std::log;
using std::pow;
using std::sin;
using std::sqrt;
using std::tan;

// value_of strips derivative information; for plain numbers it is the identity.
inline float value_of(float x) { return x; }
inline double value_of(double x) { return x; }

template <class T>
struct Vec3 {
  T x{}, y{}, z{};
  Vec3() = default;
  Vec3(T x_, T y_, T z_) : x(x_), y(y_), z(z_) {}
  explicit Vec3(T s) : x(s), y(s), z(s) {}
  template <class U>
  explicit Vec3(const Vec3<U>& o) : x(T(o.x)), y(T(o.y)), z(T(o.z)) {}

  T& operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
  const T& operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  Vec3& operator+=(const Vec3& o) {
    x = x + o.x;
    y = y + o.y;
    z = z + o.z;
    return *this;
  }
  Vec3& operator-=(const Vec3& o) {
    x = x - o.x;
    y = y - o.y;
    z = z - o.z;
    return *this;
  }
  Vec3& operator*=(const Vec3& o) {
    x = x * o.x;
    y = y * o.y;
    z = z * o.z;
    return *this;
  }
};

using Vec3f = Vec3<float>;
using Vec3d = Vec3<double>;
// RGB radiance, reflectance and adjoint weights are all Vec3 of the active scalar.
template <class T>
using Spectrum = Vec3<T>;

struct Vec2f {
  float x = 0, y = 0;
};

template <class T>
Vec3<T> operator+(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.x + b.x, a.y + b.y, a.z + b.z};
}
template <class T>
Vec3<T> operator-(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.x - b.x, a.y - b.y, a.z - b.z};
}
template <class T>
Vec3<T> operator*(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.x * b.x, a.y * b.y, a.z * b.z};
}
template <class T>
Vec3<T> operator/(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.x / b.x, a.y / b.y, a.z / b.z};
}
template <class T>
Vec3<T> operator-(const Vec3<T>& a) {
  return {-a.x, -a.y, -a.z};
}
template <class T, class S>
Vec3<T> operator*(const Vec3<T>& a, const S& s) {
  return {a.x * s, a.y * s, a.z * s};
}
template <class T, class S>
Vec3<T> operator*(const S& s, const Vec3<T>& a) {
  return {s * a.x, s * a.y, s * a.z};
}
template <class T, class S>
Vec3<T> operator/(const Vec3<T>& a, const S& s) {
  // Plain floats: one division and three multiplications instead of three divisions (the path
  // loop divides by lengths and pdfs at every vertex; a division costs ~4x a multiplication).
  if constexpr (std::is_floating_point_v<T> && std::is_floating_point_v<S>) {
    const T inverse = T(1) / T(s);
    return {a.x * inverse, a.y * inverse, a.z * inverse};
  } else {
    return {a.x / s, a.y / s, a.z / s};
  }
}

template <class T>
T dot(const Vec3<T>& a, const Vec3<T>& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <class T>
Vec3<T> cross(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <class T>
T length(const Vec3<T>& a) {
  return sqrt(dot(a, a));
}
template <class T>
Vec3<T> normalize(const Vec3<T>& a) {
  return a / length(a);
}
inline float max_component(const Vec3f& a) { return std::max(a.x, std::max(a.y, a.z)); }
inline bool is_zero(const Vec3f& a) { return a.x == 0.f && a.y == 0.f && a.z == 0.f; }
inline bool is_finite(const Vec3f& a) { return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z); }
template <class T>
Vec3f value_of(const Vec3<T>& a) {
  return {value_of(a.x), value_of(a.y), value_of(a.z)};
}
inline float luminance(const Vec3f& c) { return 0.2126f * c.x + 0.7152f * c.y + 0.0722f * c.z; }

// Orthonormal frame around a unit normal (Duff et al. 2017, "Building an orthonormal basis, revisited").
struct Frame {
  Vec3f s, t, n;
  Frame() = default;
  explicit Frame(const Vec3f& normal) : n(normal) {
    float sign = std::copysign(1.0f, n.z);
    float a = -1.0f / (sign + n.z);
    float b = n.x * n.y * a;
    s = {1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x};
    t = {b, sign + n.y * n.y * a, -n.y};
  }
  Vec3f to_local(const Vec3f& v) const { return {dot(v, s), dot(v, t), dot(v, n)}; }
  Vec3f to_world(const Vec3f& v) const { return s * v.x + t * v.y + n * v.z; }
};

// Row-major 4x4 affine transform.
struct Transform {
  float m[4][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}};
  Vec3f point(const Vec3f& p) const {
    return {m[0][0] * p.x + m[0][1] * p.y + m[0][2] * p.z + m[0][3],
            m[1][0] * p.x + m[1][1] * p.y + m[1][2] * p.z + m[1][3],
            m[2][0] * p.x + m[2][1] * p.y + m[2][2] * p.z + m[2][3]};
  }
  Vec3f vector(const Vec3f& v) const {
    return {m[0][0] * v.x + m[0][1] * v.y + m[0][2] * v.z, m[1][0] * v.x + m[1][1] * v.y + m[1][2] * v.z,
            m[2][0] * v.x + m[2][1] * v.y + m[2][2] * v.z};
  }
  Transform operator*(const Transform& o) const {
    Transform r;
    for (int i = 0; i < 4; ++i)
      for (int j = 0; j < 4; ++j) {
        r.m[i][j] = 0;
        for (int k = 0; k < 4; ++k) r.m[i][j] += m[i][k] * o.m[k][j];
      }
    return r;
  }
  // Normals transform with the inverse transpose of the linear part.
  Vec3f normal(const Vec3f& n) const;
  static Transform scale(const Vec3f& s);
  static Transform translate(const Vec3f& t);
  static Transform rotate(const Vec3f& axis, float degrees);
};

inline Vec3f Transform::normal(const Vec3f& n) const {
  const float a = m[0][0], b = m[0][1], c = m[0][2], d = m[1][0], e = m[1][1], f = m[1][2], g = m[2][0], h = m[2][1],
              i = m[2][2];
  // Cofactor matrix = det * inverse transpose; the scale does not matter once normalized.
  Vec3f r{(e * i - f * h) * n.x + (f * g - d * i) * n.y + (d * h - e * g) * n.z,
          (c * h - b * i) * n.x + (a * i - c * g) * n.y + (b * g - a * h) * n.z,
          (b * f - c * e) * n.x + (c * d - a * f) * n.y + (a * e - b * d) * n.z};
  float det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g);
  if (det < 0) r = -r;
  return normalize(r);
}
inline Transform Transform::scale(const Vec3f& s) {
  Transform t;
  t.m[0][0] = s.x;
  t.m[1][1] = s.y;
  t.m[2][2] = s.z;
  return t;
}
inline Transform Transform::translate(const Vec3f& v) {
  Transform t;
  t.m[0][3] = v.x;
  t.m[1][3] = v.y;
  t.m[2][3] = v.z;
  return t;
}
inline Transform Transform::rotate(const Vec3f& axis_in, float degrees) {
  Vec3f a = normalize(axis_in);
  float th = degrees * kPi / 180.f, c = std::cos(th), s = std::sin(th), C = 1 - c;
  Transform t;
  t.m[0][0] = a.x * a.x * C + c;
  t.m[0][1] = a.x * a.y * C - a.z * s;
  t.m[0][2] = a.x * a.z * C + a.y * s;
  t.m[1][0] = a.y * a.x * C + a.z * s;
  t.m[1][1] = a.y * a.y * C + c;
  t.m[1][2] = a.y * a.z * C - a.x * s;
  t.m[2][0] = a.z * a.x * C - a.y * s;
  t.m[2][1] = a.z * a.y * C + a.x * s;
  t.m[2][2] = a.z * a.z * C + c;
  return t;
}

}  // namespace bl
