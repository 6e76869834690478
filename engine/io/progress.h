#pragma once
// Progress bar on stderr with rate and ETA, safe to call from worker threads.
// On a terminal it redraws in place a few times a second; otherwise (logs, CI) it prints a line
// every few seconds so long runs still show they are alive.
#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <string>

namespace bl {

class Progress {
 public:
  Progress(std::string label, uint64_t total, std::string unit, bool enabled);
  ~Progress();
  void advance(uint64_t n);
  void finish();                           // prints the final state and a newline
  void set_note(const std::string& note);  // extra text after the rate (e.g. the current loss)
  double elapsed() const;
  // A pass split over `ranks` MPI ranks: `total` is this rank's share, and the rate shown is
  // that of all ranks, estimated as ranks × this rank's (tiles are interleaved, so shares are even).
  void set_ranks(int ranks);
  // Work done before this run (a resumed job's finished iterations): counted towards the
  // fraction, not towards the rate (they took no time here).
  void set_done_before(uint64_t n);

 private:
  void print(uint64_t done, bool final);
  std::string label_, unit_;
  uint64_t total_;
  bool enabled_, tty_, finished_ = false;
  std::atomic<uint64_t> done_{0};
  uint64_t done_before_ = 0;
  std::chrono::steady_clock::time_point start_;
  std::atomic<int64_t> last_print_ns_{0};
  std::mutex print_mutex_;
  std::string note_;
  int ranks_ = 1;
};

// "1.23 M" style formatting for rates and counts.
std::string human_count(double v);
std::string human_seconds(double s);

}  // namespace bl
