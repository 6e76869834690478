#pragma once
// Distribution over MPI ranks (engine/dist/dist_mpi.cpp when built with BACKLIGHT_MPI, else
// engine/dist/dist_single.cpp: one rank, every call trivial).
//
// The model: every rank loads the same scene and runs the same program; the pixels of each pass
// are divided among the ranks by 16×16 tiles; images are completed on every rank after a pass
// (so losses, validation and snapshots see the whole image everywhere); gradients are summed
// over ranks once per gradient computation (reduce_gradients); the optimizer then takes the same
// step on every rank, so parameters stay identical without being broadcast. Only rank 0 writes
// files and prints; the others' stdout and stderr go to /dev/null, except error lines.
//
// Errors: a failure before a rank's first collective operation is agreed on by all ranks at
// that operation (the lowest failing rank prints its one line, all exit with its code); a
// failure after it prints "backlight: rank N: ..." and aborts every rank (MPI_Abort).
// Without an MPI session (tests, the Python module) everything is one rank.
#include <cstdint>
#include <cstdio>
#include <functional>
#include <string>
#include <vector>

namespace bl {
struct Image;
class ParamStore;
}  // namespace bl

namespace bl::dist {

// Tiles of a pass: 16×16 pixels, numbered row by row (engine/integrators/render.cpp).
constexpr int kTile = 16;
inline int tile_count(int width, int height) { return ((width + kTile - 1) / kTile) * ((height + kTile - 1) / kTile); }

// MPI_Init / MPI_Finalize for the command-line program. Without one, one rank.
class Session {
 public:
  Session(int& argc, char**& argv);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;
};

bool built_with_mpi();
int rank();
int size();
inline bool is_root() { return rank() == 0; }
inline bool active() { return size() > 1; }

// How a pass's tiles are split: "interleaved" (tile t on rank t mod R, the default) or "blocks"
// (contiguous runs of tiles). BACKLIGHT_MPI_SPLIT selects one (for bench/mpi).
bool owns_tile(int tile, int tiles);

// Fills in the tiles other ranks rendered (every rank ends with the whole image, bitwise the
// one a single process renders). No-op on one rank.
void complete_image(Image& image);

// Sums the gradients of the parameters that require one over all ranks; every rank ends with the
// same sum. Buffers up to 64 Ki elements are summed in double; larger ones in float, in chunks
// of 4 Mi elements by reduce-scatter + all-gather (no rank holds a second copy of a big grid).
void reduce_gradients(ParamStore& params);

// Small collectives.
uint64_t sum(uint64_t v);
bool any(bool v);
bool root_value(bool v);               // rank 0's value, on every rank
std::vector<double> gather(double v);  // rank 0: one value per rank; others: empty

// The stream for error lines: stderr, also on ranks whose stderr is silenced.
FILE* error_stream();

// Thrown on a rank whose peers failed before the first collective operation (they print the
// error): exit with `code`, silently.
struct PeerFailed {
  int code;
};

// Requires `value` (a hash of what every rank loaded) to be the same on all ranks: when it is not,
// rank 0 throws InputError(message) and the others PeerFailed{2} (one agreed line, exit 2). A
// collective operation: a rank that failed before it is agreed on there, as at any first one.
void require_same(uint64_t value, const std::string& message);

// Runs `step`, which must not call collective operations, on every rank and agrees on its
// outcome like the first collective does: when it threw on some rank, the lowest such rank
// rethrows its exception (reported as one line, without an abort) and the others throw
// PeerFailed. For steps that fail alike on every rank (reading a checkpoint).
void agreed_step(const std::function<void()>& step);

// A rank's command failed with `code` and `message` (one line): prints and returns the exit
// code, or aborts every rank (see above). On one rank: prints "backlight: message".
int fail(int code, const std::string& message);

// End of a successful command: takes part in the agreement if no collective happened (may throw
// PeerFailed).
void finish();

// Peak resident set size of this process, in bytes (getrusage).
double peak_rss_bytes();

// Seconds this rank spent in MPI calls so far (waiting for slower ranks included) and the bytes
// of gradient it contributed to reductions: the cost of distribution, for gradients.json and
// bench/mpi. Zero on one rank.
double mpi_seconds();
double reduced_bytes();

}  // namespace bl::dist
