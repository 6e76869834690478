// backlight-vdb-read FILE GRID OUT.vol MEMORY_MB — the OpenVDB reader process behind read_vdb
// (engine/scene/openvdb_io.h). Parses FILE with OpenVDB under an address-space limit of
// MEMORY_MB, writes the dense grid as OUT.vol, and exits 0; on a bad file it prints the one-line
// error "<file>: <problem>" on stderr and exits 2. Not meant to be run by hand.
#include <malloc.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <new>
#include <string>

#include <tbb/global_control.h>

#include "engine/core/errors.h"
#include "engine/scene/openvdb_reader.h"
#include "engine/scene/volume_io.h"

// While OpenVDB parses, no single allocation may exceed this. A legitimate parse allocates nodes
// (at most ~1 MB each), decompression buffers of one leaf, and metadata no longer than the file;
// a crafted length field asks for gigabytes at once (a 2.7 KB file made the reader fill a 3.5 GB
// string before failing: 21 s at the default limit). The dense copy comes after the parse and is
// checked against the grid limits instead. Not under ASan: its allocator has its own limits.
namespace {
std::atomic<size_t> single_allocation_cap{~size_t(0)};
std::atomic<size_t> refused_allocation{0};  // the request the cap refused, if any
}  // namespace

#if !BL_ADDRESS_SANITIZER
void* operator new(size_t n) {
  if (n > single_allocation_cap.load(std::memory_order_relaxed)) {
    refused_allocation = n;
    throw std::bad_alloc();
  }
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, size_t) noexcept { std::free(p); }
#endif

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: backlight-vdb-read FILE GRID OUT.vol MEMORY_MB (used by backlight)\n");
    return 64;
  }
  // Dies with backlight: a reader whose parent was killed parsed on and wrote into a folder
  // nobody would remove. The parent's pid in the environment closes the race of a parent gone
  // before the request.
  prctl(PR_SET_PDEATHSIG, SIGKILL);
  if (const char* parent = std::getenv("BACKLIGHT_VDB_PARENT"); parent && std::atol(parent) != long(getppid()))
    return 3;
  const std::string path = argv[1];
  char* end = nullptr;
  const unsigned long long memory_mb = std::strtoull(argv[4], &end, 10);
  if (*end != '\0' || memory_mb == 0) return 64;
  // The address-space limit must not be eaten by reservations: one malloc arena reserves 64 MB
  // per thread, so arenas and OpenVDB's TBB parallelism (bounding boxes, tree walks) stay small.
  mallopt(M_ARENA_MAX, 2);
  tbb::global_control threads(tbb::global_control::max_allowed_parallelism, 2);
  const rlimit no_core{0, 0};
  setrlimit(RLIMIT_CORE, &no_core);
  // ASan reserves terabytes of address space for its shadow: it gets ASAN_OPTIONS limits instead.
  if (!bl::kAddressSanitizer) {
    const rlimit as{rlim_t(memory_mb) << 20, rlim_t(memory_mb) << 20};
    setrlimit(RLIMIT_AS, &as);
  }
  try {
    // The cap: 64 MB plus the file's size (the longest metadata string it can hold).
    std::error_code ec;
    const auto file_bytes = std::filesystem::file_size(path, ec);
    single_allocation_cap = (size_t(64) << 20) + (ec ? 0 : size_t(file_bytes));
    const bl::VolumeGrid grid = bl::read_vdb_in_process(path, argv[2], [] { single_allocation_cap = ~size_t(0); });
    bl::write_vol(argv[3], grid);
    return 0;
  } catch (const bl::InputError& e) {
    std::fprintf(stderr, "%s\n", e.what());
  } catch (const std::bad_alloc&) {
    if (const size_t n = refused_allocation.load())
      std::fprintf(stderr, "%s: cannot read OpenVDB file (corrupt: a length field asks for %.0f MB at once)\n",
                   path.c_str(), double(n) / (1 << 20));
    else
      std::fprintf(stderr,
                   "%s: cannot read OpenVDB file (needs more memory than the reader's limit of %llu MB, set by "
                   "BACKLIGHT_VDB_MEMORY_MB)\n",
                   path.c_str(), memory_mb);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: cannot read OpenVDB file (%s)\n", path.c_str(), e.what());
  }
  return 2;
}
