#pragma once
// Reverse-mode AD scalar for the taped baseline.
// A Var is a float value plus the index of the tape entry that produced it; index kConstant
// means the value does not depend on any parameter (activity analysis): operations on constants
// are plain float arithmetic and record nothing. An entry stores up to two operand indices and
// the local partials (16 bytes); parameter reads record a leaf entry naming the parameter
// element. One tape per worker thread; `current_tape` selects it.
#include <cmath>
#include <cstdint>
#include <memory>
#include <type_traits>
#include <vector>

#include "engine/core/params.h"

namespace bl {

struct TapeEntry {
  uint32_t a, b;  // operand entries, kNone when absent; a == kLeaf: b is a flat parameter index
  float da, db;   // ∂result/∂a, ∂result/∂b; for a leaf, da is its weight (result = weight · θ_b)
};
static_assert(sizeof(TapeEntry) == 16);

// Entries live in fixed-size chunks: growing never copies or over-allocates (a doubling vector
// would briefly need three times the tape), so the baseline's memory is the tape itself.
struct Tape {
  static constexpr uint32_t kNone = 0xffffffffu, kLeaf = 0xfffffffeu;
  static constexpr size_t kChunkBits = 18, kChunk = size_t(1) << kChunkBits;  // 4 MB per chunk
  std::vector<std::unique_ptr<TapeEntry[]>> chunks;
  size_t count = 0;

  uint32_t push(uint32_t a, float da, uint32_t b, float db) {
    if ((count & (kChunk - 1)) == 0 && (count >> kChunkBits) == chunks.size())
      chunks.push_back(std::make_unique_for_overwrite<TapeEntry[]>(kChunk));  // written before read
    chunks[count >> kChunkBits][count & (kChunk - 1)] = {a, b, da, db};
    return uint32_t(count++);
  }
  size_t size() const { return count; }
  void clear() { count = 0; }  // keeps the chunks for the next recording
  const TapeEntry& operator[](size_t i) const { return chunks[i >> kChunkBits][i & (kChunk - 1)]; }
};

inline thread_local Tape* current_tape = nullptr;

struct Var {
  static constexpr uint32_t kConstant = Tape::kNone;
  float v = 0.f;
  uint32_t index = kConstant;
  Var() = default;
  Var(float x) : v(x) {}  // NOLINT: constants promote implicitly
  Var(float x, uint32_t i) : v(x), index(i) {}
  bool active() const { return index != kConstant; }
};

inline float value_of(const Var& a) { return a.v; }

// Records result = f(a, b) with partials (da, db) when any operand is active.
inline Var record(float value, const Var& a, float da, const Var& b, float db) {
  if (!a.active() && !b.active()) return Var(value);
  // Identities need no entry: the result is the active operand itself (same value, same
  // derivative), e.g. 0 + x when a sum starts from zero, or 1 · x.
  if (!a.active() && value == b.v && db == 1.f) return b;
  if (!b.active() && value == a.v && da == 1.f) return a;
  if (!b.active()) return Var(value, current_tape->push(a.index, da, Tape::kNone, 0.f));
  if (!a.active()) return Var(value, current_tape->push(b.index, db, Tape::kNone, 0.f));
  return Var(value, current_tape->push(a.index, da, b.index, db));
}
inline Var record(float value, const Var& a, float da) {
  if (!a.active()) return Var(value);
  if (value == a.v && da == 1.f) return a;
  return Var(value, current_tape->push(a.index, da, Tape::kNone, 0.f));
}

inline Var operator+(const Var& a, const Var& b) { return record(a.v + b.v, a, 1.f, b, 1.f); }
inline Var operator-(const Var& a, const Var& b) { return record(a.v - b.v, a, 1.f, b, -1.f); }
inline Var operator*(const Var& a, const Var& b) { return record(a.v * b.v, a, b.v, b, a.v); }
inline Var operator/(const Var& a, const Var& b) {
  float inv = 1.f / b.v;
  return record(a.v / b.v, a, inv, b, -a.v * inv * inv);
}
inline Var operator-(const Var& a) { return record(-a.v, a, -1.f); }
// Mixed with plain numbers: one operand, one entry (or none).
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator+(const Var& a, U b) {
  return record(a.v + float(b), a, 1.f);
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator+(U a, const Var& b) {
  return record(float(a) + b.v, b, 1.f);
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator-(const Var& a, U b) {
  return record(a.v - float(b), a, 1.f);
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator-(U a, const Var& b) {
  return record(float(a) - b.v, b, -1.f);
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator*(const Var& a, U b) {
  return record(a.v * float(b), a, float(b));
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator*(U a, const Var& b) {
  return record(float(a) * b.v, b, float(a));
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator/(const Var& a, U b) {
  return record(a.v / float(b), a, 1.f / float(b));
}
template <class U, std::enable_if_t<std::is_arithmetic_v<U>, int> = 0>
Var operator/(U a, const Var& b) {
  return record(float(a) / b.v, b, -float(a) / (b.v * b.v));
}

template <class B>
bool operator<(const Var& a, const B& b) {
  return a.v < value_of(b);
}
template <class B>
bool operator>(const Var& a, const B& b) {
  return a.v > value_of(b);
}

inline Var sqrt(const Var& a) {
  float r = std::sqrt(a.v);
  return record(r, a, 0.5f / r);
}
inline Var exp(const Var& a) {
  float r = std::exp(a.v);
  return record(r, a, r);
}
inline Var log(const Var& a) { return record(std::log(a.v), a, 1.f / a.v); }
inline Var abs(const Var& a) { return record(std::abs(a.v), a, a.v < 0 ? -1.f : 1.f); }
inline Var pow(const Var& a, float e) { return record(std::pow(a.v, e), a, e * std::pow(a.v, e - 1.f)); }

// Reverse sweep: propagates the adjoints in `adjoint` (one per entry, seeded at the outputs) from
// the last entry to the first, and calls leaf(flat_parameter_index, adjoint · weight) per leaf.
// done(n) hears of every n entries swept (in blocks of 2^20, for a progress bar).
struct NoSweepProgress {
  void operator()(size_t) const {}
};
template <class LeafFn, class Done = NoSweepProgress>
void reverse_sweep(const Tape& tape, std::vector<float>& adjoint, LeafFn&& leaf, Done&& done = {}) {
  constexpr size_t kBlock = size_t(1) << 20;
  for (size_t end = tape.size(); end > 0;) {
    const size_t begin = end > kBlock ? end - kBlock : 0;
    for (size_t i = end; i-- > begin;) {
      const float g = adjoint[i];
      if (g == 0.f) continue;
      const TapeEntry& e = tape[i];
      if (e.a == Tape::kLeaf) {
        leaf(e.b, g * e.da);
        continue;
      }
      if (e.a != Tape::kNone) adjoint[e.a] += g * e.da;
      if (e.b != Tape::kNone) adjoint[e.b] += g * e.db;
    }
    done(end - begin);
    end = begin;
  }
}

// Parameter reads become leaves when the parameter wants a gradient, constants otherwise.
template <>
struct ParamLoad<Var> {
  static Var load(const Param& p, size_t index) {
    if (!p.requires_grad) return Var(p.value[index]);
    return Var(p.value[index], current_tape->push(Tape::kLeaf, 1.f, uint32_t(p.tape_offset + index), 0.f));
  }
  static Var load_weighted(const Param& p, size_t index, float weight) {
    const float value = p.value[index] * weight;
    if (!p.requires_grad) return Var(value);
    return Var(value, current_tape->push(Tape::kLeaf, weight, uint32_t(p.tape_offset + index), 0.f));
  }
};

}  // namespace bl
