#pragma once
// Forward-mode dual numbers with N tangent directions.
// Derivative shaders of kernels with several inputs (GGX roughness, Fresnel colour) evaluate the
// kernel's own templated eval on Dual<S, N>, so the derivative can never drift from the eval it
// differentiates: there is one source of truth per kernel (DESIGN.md, property 2).
#include <array>
#include <cmath>
#include <type_traits>

#include "engine/core/math.h"  // value_of for plain scalars, used by the comparisons below

namespace bl {

template <class S, int N>
struct Dual {
  S v{};
  std::array<S, N> d{};
  Dual() = default;
  Dual(S value) : v(value) {}  // NOLINT: constants promote implicitly, as plain scalars do
  template <class U, std::enable_if_t<std::is_arithmetic_v<U> && !std::is_same_v<U, S>, int> = 0>
  Dual(U value) : v(S(value)) {}  // NOLINT
  // The k-th independent variable: value x, tangent e_k.
  static Dual variable(S x, int k) {
    Dual r(x);
    r.d[k] = S(1);
    return r;
  }
};

template <class S, int N>
S value_of(const Dual<S, N>& a) {
  return a.v;
}

#define BL_DUAL_BINARY(op, value_expr, grad_expr)                                        \
  template <class S, int N>                                                              \
  Dual<S, N> operator op(const Dual<S, N>& a, const Dual<S, N>& b) {                     \
    Dual<S, N> r;                                                                        \
    r.v = value_expr;                                                                    \
    for (int k = 0; k < N; ++k) r.d[k] = grad_expr;                                      \
    return r;                                                                            \
  }                                                                                      \
  template <class S, int N, class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0> \
  Dual<S, N> operator op(const Dual<S, N>& a, U b) {                                     \
    return a op Dual<S, N>(S(b));                                                        \
  }                                                                                      \
  template <class S, int N, class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0> \
  Dual<S, N> operator op(U a, const Dual<S, N>& b) {                                     \
    return Dual<S, N>(S(a)) op b;                                                        \
  }

BL_DUAL_BINARY(+, a.v + b.v, a.d[k] + b.d[k])
BL_DUAL_BINARY(-, a.v - b.v, a.d[k] - b.d[k])
BL_DUAL_BINARY(*, a.v* b.v, a.d[k] * b.v + a.v * b.d[k])
BL_DUAL_BINARY(/, a.v / b.v, (a.d[k] * b.v - a.v * b.d[k]) / (b.v * b.v))
#undef BL_DUAL_BINARY

template <class S, int N>
Dual<S, N> operator-(const Dual<S, N>& a) {
  Dual<S, N> r;
  r.v = -a.v;
  for (int k = 0; k < N; ++k) r.d[k] = -a.d[k];
  return r;
}

// Comparisons look at values only: branches are constants of differentiation.
template <class S, int N, class B>
bool operator<(const Dual<S, N>& a, const B& b) {
  return a.v < value_of(b);
}
template <class S, int N, class B>
bool operator>(const Dual<S, N>& a, const B& b) {
  return a.v > value_of(b);
}
template <class S, int N, class B>
bool operator<=(const Dual<S, N>& a, const B& b) {
  return a.v <= value_of(b);
}
template <class S, int N, class B>
bool operator>=(const Dual<S, N>& a, const B& b) {
  return a.v >= value_of(b);
}

// Unary functions: value f(v), tangent f'(v)·d.
template <class S, int N, class F, class DF>
Dual<S, N> dual_apply(const Dual<S, N>& a, F f, DF df) {
  Dual<S, N> r;
  r.v = f(a.v);
  S slope = df(a.v, r.v);
  for (int k = 0; k < N; ++k) r.d[k] = slope * a.d[k];
  return r;
}
template <class S, int N>
Dual<S, N> sqrt(const Dual<S, N>& a) {
  return dual_apply(
      a, [](S x) { return std::sqrt(x); }, [](S, S y) { return S(0.5) / y; });
}
template <class S, int N>
Dual<S, N> exp(const Dual<S, N>& a) {
  return dual_apply(
      a, [](S x) { return std::exp(x); }, [](S, S y) { return y; });
}
template <class S, int N>
Dual<S, N> log(const Dual<S, N>& a) {
  return dual_apply(
      a, [](S x) { return std::log(x); }, [](S x, S) { return S(1) / x; });
}
template <class S, int N>
Dual<S, N> abs(const Dual<S, N>& a) {
  return dual_apply(
      a, [](S x) { return std::abs(x); }, [](S x, S) { return x < 0 ? S(-1) : S(1); });
}
template <class S, int N>
Dual<S, N> pow(const Dual<S, N>& a, S e) {
  return dual_apply(
      a, [e](S x) { return std::pow(x, e); }, [e](S x, S) { return e * std::pow(x, e - 1); });
}

}  // namespace bl
