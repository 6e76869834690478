// Distribution over MPI ranks (see dist.h). Only the main thread of a rank calls MPI
// (MPI_THREAD_FUNNELED); TBB workers never do.
#include <fcntl.h>
#include <mpi.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <climits>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <stdexcept>
#include <thread>

#include "engine/core/errors.h"
#include "engine/core/params.h"
#include "engine/dist/dist.h"
#include "engine/io/image_io.h"

namespace bl::dist {

namespace {

bool g_session = false;  // MPI initialized by a Session
int g_rank = 0, g_size = 1;
bool g_agreed = false;        // the first collective operation (the error agreement) has happened
bool g_blocks = false;        // BACKLIGHT_MPI_SPLIT=blocks
FILE* g_err = nullptr;        // the original stderr of a silenced rank
bool g_error_agreed = false;  // the error being thrown was agreed on: report it, do not abort
double g_mpi_seconds = 0, g_reduced_bytes = 0;

// Adds the lifetime of the scope to g_mpi_seconds.
struct MpiTimer {
  double start = MPI_Wtime();
  ~MpiTimer() { g_mpi_seconds += MPI_Wtime() - start; }
};

// The first collective of every rank: did any rank fail before reaching it?
void agree(bool failed, int code) {
  if (g_agreed || !g_session) return;
  g_agreed = true;
  int mine = failed ? g_rank : INT_MAX, lowest = INT_MAX;
  MPI_Allreduce(&mine, &lowest, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
  if (lowest == INT_MAX) return;
  MPI_Bcast(&code, 1, MPI_INT, lowest, MPI_COMM_WORLD);
  if (!failed) throw PeerFailed{code};
  if (lowest != g_rank) throw PeerFailed{code};  // a lower rank failed too; it prints
}

// Fault injection for tests/cli/test_mpi.sh: BACKLIGHT_MPI_FAIL=RANK:N makes rank RANK fail at
// its N-th collective operation, as a rank whose disk or memory gives out mid-run would.
int g_fail_rank = -1;
long g_fail_at = 0, g_collectives = 0;

void collective() {
  if (g_session && !g_agreed) agree(false, 0);
  if (++g_collectives == g_fail_at && g_rank == g_fail_rank)
    throw std::runtime_error("injected failure (BACKLIGHT_MPI_FAIL) at collective operation " +
                             std::to_string(g_collectives));
}

int owner(int tile, int tiles) {
  if (g_blocks) return int(int64_t(tile) * g_size / std::max(tiles, 1));
  return tile % g_size;
}

// Sums `n` elements in place over all ranks: chunks of `chunk` elements, each reduce-scattered
// (every slice summed once, by one rank) and all-gathered, so all ranks hold identical sums.
template <class T>
void sum_in_place(T* data, size_t n, MPI_Datatype type, size_t chunk) {
  const size_t ranks = size_t(g_size);
  chunk = std::max(ranks, chunk / ranks * ranks);
  std::vector<T> padded, slice(chunk / ranks);
  for (size_t offset = 0; offset < n; offset += chunk) {
    const size_t count = std::min(chunk, n - offset);
    const size_t per_rank = (count + ranks - 1) / ranks;
    T* block = data + offset;
    if (count != per_rank * ranks) {  // the last, partial chunk: pad with zeros
      padded.assign(per_rank * ranks, T(0));
      std::copy(block, block + count, padded.begin());
      block = padded.data();
    }
    MPI_Reduce_scatter_block(block, slice.data(), int(per_rank), type, MPI_SUM, MPI_COMM_WORLD);
    MPI_Allgather(slice.data(), int(per_rank), type, block, int(per_rank), type, MPI_COMM_WORLD);
    if (block != data + offset) std::copy(padded.begin(), padded.begin() + std::ptrdiff_t(count), data + offset);
  }
}

}  // namespace

namespace {
// FNV-1a over the command line and the bytes of the regular files it names as inputs (a scene, a
// config, a target image), so that ranks started with different commands, or reading different copies of
// those files (a stale copy on one node), are caught before they mix their shares.
uint64_t command_hash(int argc, char** argv) {
  uint64_t h = 1469598103934665603ull;
  auto add = [&](const char* data, size_t n) {
    for (size_t i = 0; i < n; ++i) h = (h ^ uint8_t(data[i])) * 1099511628211ull;
  };
  for (int i = 1; i < argc; ++i) {
    add(argv[i], std::strlen(argv[i]) + 1);
    // Outputs are not read (an old output only rank 0's node holds is no disagreement).
    const bool output = i > 1 && (std::strcmp(argv[i - 1], "-o") == 0 || std::strcmp(argv[i - 1], "--output") == 0);
    if (output) continue;
    std::error_code ec;
    const std::filesystem::path path(argv[i]);
    if (!std::filesystem::is_regular_file(path, ec) || std::filesystem::file_size(path, ec) > (uint64_t(64) << 20))
      continue;
    if (FILE* f = std::fopen(argv[i], "rb")) {
      char buffer[1 << 16];
      for (size_t n; (n = std::fread(buffer, 1, sizeof buffer, f)) > 0;) add(buffer, n);
      std::fclose(f);
    }
  }
  return h;
}
}  // namespace

Session::Session(int& argc, char**& argv) {
  // Only under a launcher (mpirun/srun set these): a plain `backlight ...` stays one process
  // and does not need a working MPI runtime.
  const bool launched = std::getenv("OMPI_COMM_WORLD_SIZE") || std::getenv("PMIX_RANK") || std::getenv("PMI_RANK") ||
                        std::getenv("PMI_SIZE");
  if (!launched) return;
  int provided = 0;
  MPI_Init_thread(&argc, &argv, MPI_THREAD_FUNNELED, &provided);
  if (provided < MPI_THREAD_FUNNELED) {
    std::fprintf(stderr, "backlight: this MPI library does not allow threads (MPI_THREAD_FUNNELED)\n");
    MPI_Abort(MPI_COMM_WORLD, 1);
  }
  g_session = true;
  MPI_Comm_rank(MPI_COMM_WORLD, &g_rank);
  MPI_Comm_size(MPI_COMM_WORLD, &g_size);
  // MPI's default error handler (abort every rank) is kept: a failed collective ends the run.
  if (const char* f = std::getenv("BACKLIGHT_MPI_FAIL"); f && std::sscanf(f, "%d:%ld", &g_fail_rank, &g_fail_at) != 2)
    g_fail_rank = -1;
  const char* split = std::getenv("BACKLIGHT_MPI_SPLIT");
  g_blocks = split && std::strcmp(split, "blocks") == 0;
  // Every rank must run the same command on the same files: different film sizes corrupted the
  // image gather's buffers, different sample counts mixed two renders into one image, silently.
  const uint64_t mine = command_hash(argc, argv);
  uint64_t lowest = 0, highest = 0;
  MPI_Allreduce(&mine, &lowest, 1, MPI_UINT64_T, MPI_MIN, MPI_COMM_WORLD);
  MPI_Allreduce(&mine, &highest, 1, MPI_UINT64_T, MPI_MAX, MPI_COMM_WORLD);
  if (lowest != highest) {
    if (g_rank == 0)
      std::fprintf(stderr,
                   "backlight: the ranks were started with different command lines, or read different copies of the "
                   "files they name (every rank must run the same command on the same files)\n");
    MPI_Finalize();
    std::exit(2);
  }
  if (g_rank != 0) {
    // Rank 0 prints; the others keep their stderr for error lines only.
    std::fflush(stdout);
    std::fflush(stderr);
    const int saved = dup(2);
    if (saved >= 0) g_err = fdopen(saved, "w");
    const int null = open("/dev/null", O_WRONLY);
    if (null >= 0) {
      dup2(null, 1);
      dup2(null, 2);
      close(null);
    }
  }
}

Session::~Session() {
  if (!g_session) return;
  std::fflush(stdout);
  std::fflush(stderr);
  MPI_Finalize();
  g_session = false;
}

bool built_with_mpi() { return true; }
int rank() { return g_rank; }
int size() { return g_size; }
bool owns_tile(int tile, int tiles) { return g_size == 1 || owner(tile, tiles) == g_rank; }

void complete_image(Image& image) {
  if (g_size == 1) return;
  collective();
  const MpiTimer timer;
  const int tiles_x = (image.width + kTile - 1) / kTile, tiles = tile_count(image.width, image.height);
  const size_t channels = size_t(image.channels);
  auto for_tiles_of = [&](int r, auto&& fn) {  // fn(x, y, value count of the row segment)
    for (int t = 0; t < tiles; ++t) {
      if (owner(t, tiles) != r) continue;
      const int x0 = (t % tiles_x) * kTile, y0 = (t / tiles_x) * kTile;
      const int x1 = std::min(x0 + kTile, image.width), y1 = std::min(y0 + kTile, image.height);
      for (int y = y0; y < y1; ++y) fn(x0, y, size_t(x1 - x0) * channels);
    }
  };
  std::vector<int> counts(size_t(g_size), 0), displacements(size_t(g_size), 0);
  for (int r = 0; r < g_size; ++r) {
    size_t n = 0;
    for_tiles_of(r, [&](int, int, size_t values) { n += values; });
    if (n > size_t(INT_MAX)) throw std::runtime_error("image too large to gather over MPI");
    counts[size_t(r)] = int(n);
    if (r > 0) {
      const int64_t d = int64_t(displacements[size_t(r) - 1]) + counts[size_t(r) - 1];
      if (d > INT_MAX) throw std::runtime_error("image too large to gather over MPI");
      displacements[size_t(r)] = int(d);
    }
  }
  std::vector<float> mine;
  mine.reserve(size_t(counts[size_t(g_rank)]));
  for_tiles_of(g_rank, [&](int x, int y, size_t values) {
    const float* row = &image.at(x, y, 0);
    mine.insert(mine.end(), row, row + values);
  });
  std::vector<float> all(size_t(displacements.back()) + size_t(counts.back()));
  MPI_Allgatherv(mine.data(), counts[size_t(g_rank)], MPI_FLOAT, all.data(), counts.data(), displacements.data(),
                 MPI_FLOAT, MPI_COMM_WORLD);
  for (int r = 0; r < g_size; ++r) {
    size_t at = size_t(displacements[size_t(r)]);
    for_tiles_of(r, [&](int x, int y, size_t values) {
      std::copy(all.begin() + std::ptrdiff_t(at), all.begin() + std::ptrdiff_t(at + values), &image.at(x, y, 0));
      at += values;
    });
  }
}

void reduce_gradients(ParamStore& params) {
  if (g_size == 1) return;
  collective();
  const MpiTimer timer;
  constexpr size_t kSmall = size_t(1) << 16, kChunk = size_t(1) << 22;
  for (auto& p : params.all()) {
    if (!p.requires_grad || p.grad.empty()) continue;
    g_reduced_bytes += double(p.grad.size()) * (p.grad.size() <= kSmall ? sizeof(double) : sizeof(float));
    if (p.grad.size() <= kSmall) {
      std::vector<double> g(p.grad.begin(), p.grad.end());
      sum_in_place(g.data(), g.size(), MPI_DOUBLE, kSmall);
      for (size_t i = 0; i < g.size(); ++i) p.grad[i] = float(g[i]);
    } else {
      sum_in_place(p.grad.data(), p.grad.size(), MPI_FLOAT, kChunk);
    }
  }
}

// One value reduced over all ranks with `op`.
template <class T>
T all_reduce(T v, MPI_Datatype type, MPI_Op op) {
  if (g_size == 1) return v;
  collective();
  const MpiTimer timer;
  T out{};
  MPI_Allreduce(&v, &out, 1, type, op, MPI_COMM_WORLD);
  return out;
}
uint64_t sum(uint64_t v) { return all_reduce(v, MPI_UINT64_T, MPI_SUM); }
bool any(bool v) { return all_reduce(int(v), MPI_INT, MPI_MAX) != 0; }
bool root_value(bool v) {
  if (g_size == 1) return v;
  collective();
  const MpiTimer timer;
  int x = v ? 1 : 0;
  MPI_Bcast(&x, 1, MPI_INT, 0, MPI_COMM_WORLD);
  return x != 0;
}
std::vector<double> gather(double v) {
  if (g_size == 1) return {v};
  collective();
  const MpiTimer timer;
  std::vector<double> all(g_rank == 0 ? size_t(g_size) : 0);
  MPI_Gather(&v, 1, MPI_DOUBLE, all.data(), 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
  return all;
}

FILE* error_stream() { return g_err ? g_err : stderr; }

int fail(int code, const std::string& message) {
  if (g_size == 1) {
    std::fprintf(stderr, "backlight: %s\n", message.c_str());
    return code;
  }
  if (!g_agreed || g_error_agreed) {
    try {
      agree(true, code);  // no-op when already agreed
    } catch (const PeerFailed& p) {
      return p.code;  // a lower rank failed as well and prints
    }
    const std::string who = g_rank == 0 ? "" : "rank " + std::to_string(g_rank) + ": ";
    std::fprintf(error_stream(), "backlight: %s%s\n", who.c_str(), message.c_str());
    std::fflush(error_stream());
    return code;
  }
  // Mid-run: the other ranks are in (or heading for) a collective operation that cannot complete.
  // An error every rank meets (a geometry refusal, an overflowing sum) printed one line per rank:
  // the others wait before they print, so rank 0's line and abort come first and end them.
  if (g_rank != 0) std::this_thread::sleep_for(std::chrono::seconds(2));
  std::fprintf(error_stream(), "backlight: rank %d: %s\n", g_rank, message.c_str());
  std::fflush(error_stream());
  MPI_Abort(MPI_COMM_WORLD, code);
  return code;
}

void finish() { collective(); }

void require_same(uint64_t value, const std::string& message) {
  if (g_size == 1) return;
  // Not counted as a collective for BACKLIGHT_MPI_FAIL: the injected failures stay where the
  // tests put them.
  if (g_session && !g_agreed) agree(false, 0);
  const MpiTimer timer;
  uint64_t lowest = 0, highest = 0;
  MPI_Allreduce(&value, &lowest, 1, MPI_UINT64_T, MPI_MIN, MPI_COMM_WORLD);
  MPI_Allreduce(&value, &highest, 1, MPI_UINT64_T, MPI_MAX, MPI_COMM_WORLD);
  if (lowest == highest) return;
  if (g_rank != 0) throw PeerFailed{2};
  g_error_agreed = true;
  throw InputError(message);
}

void agreed_step(const std::function<void()>& step) {
  if (g_size == 1) return step();
  std::exception_ptr error;
  int code = 0;
  try {
    step();
  } catch (const InputError&) {
    error = std::current_exception(), code = 2;
  } catch (const std::filesystem::filesystem_error&) {
    error = std::current_exception(), code = 2;
  } catch (const std::exception&) {
    error = std::current_exception(), code = 1;
  }
  collective();
  const MpiTimer timer;
  int mine = error ? g_rank : INT_MAX, lowest = INT_MAX;
  MPI_Allreduce(&mine, &lowest, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
  if (lowest == INT_MAX) return;
  MPI_Bcast(&code, 1, MPI_INT, lowest, MPI_COMM_WORLD);
  if (lowest != g_rank) throw PeerFailed{code};
  g_error_agreed = true;
  std::rethrow_exception(error);
}
double mpi_seconds() { return g_mpi_seconds; }
double reduced_bytes() { return g_reduced_bytes; }

double peak_rss_bytes() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_maxrss) * 1024.0;
}

}  // namespace bl::dist
