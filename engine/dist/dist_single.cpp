// One rank: the build without MPI (see dist.h).
#include <sys/resource.h>

#include "engine/dist/dist.h"

namespace bl::dist {

Session::Session(int&, char**&) {}
Session::~Session() = default;
bool built_with_mpi() { return false; }
int rank() { return 0; }
int size() { return 1; }
bool owns_tile(int, int) { return true; }
void complete_image(Image&) {}
void reduce_gradients(ParamStore&) {}
uint64_t sum(uint64_t v) { return v; }
bool any(bool v) { return v; }
bool root_value(bool v) { return v; }
std::vector<double> gather(double v) { return {v}; }
FILE* error_stream() { return stderr; }
int fail(int code, const std::string& message) {
  std::fprintf(stderr, "backlight: %s\n", message.c_str());
  return code;
}
void finish() {}
void require_same(uint64_t, const std::string&) {}
void agreed_step(const std::function<void()>& step) { step(); }
double peak_rss_bytes() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_maxrss) * 1024.0;
}

double mpi_seconds() { return 0; }
double reduced_bytes() { return 0; }

}  // namespace bl::dist
