#pragma once
// One limits policy for everything read from input (scenes, glTF, images, grids, configs, flags),
// and overflow-safe size arithmetic to apply it. Sizes are checked before anything is allocated:
// a 69-byte PNG claiming 100000×100000 pixels, or a glTF accessor claiming 2^62 elements, is a
// one-line error, not a 120 GB allocation or a wrapped multiplication.
//
// The limits are far above what a 2-core / 24 GB machine renders usefully, and far below what
// would overflow 64-bit sizes or exhaust memory by themselves.
#include <algorithm>
#include <cstdint>
#include <initializer_list>
#include <string>

#include "engine/core/errors.h"

namespace bl::limits {

inline constexpr uint64_t kImageSide = 65536;             // width or height of an image, film or texture
inline constexpr uint64_t kImagePixels = 1ull << 28;      // width × height (268 M pixels, ~3 GB as RGB float)
inline constexpr uint64_t kSpp = 1ull << 20;              // samples per pixel in one pass
inline constexpr uint64_t kCheckDirections = 1ull << 16;  // `check --directions`: two renders each
inline constexpr uint64_t kGridVoxels = 1ull << 30;       // voxels of a volume grid (4 GB as float)
inline constexpr uint64_t kMeshElements = 1ull << 28;     // vertices, or triangles, of one mesh
// Worker threads (--threads, backlight.set_threads): far more than any machine has, so that
// oversubscription stays possible, and far below what breaks: --threads 1000000000 made Embree
// fail to allocate for its thread pool ("Embree error 4: out of memory") and then hang, while
// 10^6 still rendered the Cornell box (170 MB).
inline constexpr uint64_t kThreads = 1ull << 16;
// All meshes of one scene (or one glTF file) together, every instance counted: a glTF node tree
// can instance one mesh thousands of times, and a mesh can list one accessor in many primitives,
// so a 100 KB file could otherwise ask for 10^10 vertices.
inline constexpr uint64_t kSceneElements = 1ull << 28;  // vertices, or triangles, of a whole scene
inline constexpr uint64_t kShapes = 1ull << 20;         // meshes (primitive instances) of a scene
// Values of all parameters of a scene together (4 GB as float; the gradients double it): many
// materials naming one compressible 4096² texture would otherwise copy it once each.
inline constexpr uint64_t kParamValues = 1ull << 30;
inline constexpr uint64_t kFileBytes = 4ull << 30;  // one file read whole (a glTF buffer, a grid)
inline constexpr int kJsonDepth = 64;               // nesting of JSON arrays and objects
inline constexpr int kNodeDepth = 64;               // nesting of glTF nodes
// Coordinates (vertices, camera positions) beyond this magnitude are rejected: hit points and
// ray offsets computed from them must stay finite in float arithmetic (Embree aborts on NaN rays).
inline constexpr double kCoordinate = 1e18;
// Expected tentative collisions of delta and ratio tracking across one majorant block of a grid
// medium (majorant × block diagonal): beyond it the block is optically solid (transmittance
// e^-1e6) and tracking its thin parts would take hours (at ~1e20 steps no longer advance in
// float: a hang).
inline constexpr double kOpticalDepth = 1e6;

// a · b, or false when it does not fit in 64 bits.
inline bool checked_mul(uint64_t a, uint64_t b, uint64_t& out) { return !__builtin_mul_overflow(a, b, &out); }
// a + b, or false when it does not fit in 64 bits.
inline bool checked_add(uint64_t a, uint64_t b, uint64_t& out) { return !__builtin_add_overflow(a, b, &out); }

// "<where>: <what> <value> exceeds the limit of <limit>" (as InputError) unless value ≤ limit.
inline void require_at_most(const std::string& where, const std::string& what, uint64_t value, uint64_t limit) {
  if (value > limit)
    throw InputError(where + ": " + what + " " + std::to_string(value) + " exceeds the limit of " +
                     std::to_string(limit));
}

// total += amount, then "<where>: <what> <total> exceeds the limit of <limit>" (as InputError)
// unless the new total is within `limit`. For running totals over a scene (vertices of every
// instance, shapes, parameter values), checked before the next part is allocated where possible.
inline void add_to_total(const std::string& where, const std::string& what, uint64_t& total, uint64_t amount,
                         uint64_t limit) {
  if (!checked_add(total, amount, total))
    throw InputError(where + ": " + what + " overflows (exceeds the limit of " + std::to_string(limit) + ")");
  require_at_most(where, what, total, limit);
}

// The product of `factors` (e.g. width, height, channels), checked against overflow and `limit`.
inline uint64_t checked_product(const std::string& where, const std::string& what,
                                std::initializer_list<uint64_t> factors, uint64_t limit) {
  uint64_t p = 1;
  for (uint64_t f : factors)
    if (!checked_mul(p, f, p))
      throw InputError(where + ": " + what + " overflows (exceeds the limit of " + std::to_string(limit) + ")");
  require_at_most(where, what, p, limit);
  return p;
}

// An image (or film) of w × h pixels: each side and the total within the limits.
inline void check_image_size(const std::string& where, uint64_t width, uint64_t height) {
  require_at_most(where, "image width", width, kImageSide);
  require_at_most(where, "image height", height, kImageSide);
  checked_product(where, "pixel count", {width, height}, kImagePixels);
}

// The deepest nesting of JSON arrays and objects in `text` (strings and escapes skipped), so that
// depth can be bounded before any recursive parser (nlohmann, tinygltf) or copy sees the text.
inline int json_nesting_depth(const std::string& text) {
  int depth = 0, deepest = 0;
  bool in_string = false;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (in_string) {
      if (c == '\\')
        ++i;
      else if (c == '"')
        in_string = false;
    } else if (c == '"') {
      in_string = true;
    } else if (c == '[' || c == '{') {
      deepest = std::max(deepest, ++depth);
    } else if (c == ']' || c == '}') {
      --depth;
    }
  }
  return deepest;
}

inline void check_json_depth(const std::string& file, const std::string& text) {
  const int depth = json_nesting_depth(text);
  if (depth > kJsonDepth)
    throw file_error(
        file, "JSON nesting depth " + std::to_string(depth) + " exceeds the limit of " + std::to_string(kJsonDepth));
}

}  // namespace bl::limits
