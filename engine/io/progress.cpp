#include "engine/io/progress.h"

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <exception>

namespace bl {

std::string human_count(double v) {
  char buf[32];
  if (v >= 1e9)
    std::snprintf(buf, sizeof buf, "%.2f G", v / 1e9);
  else if (v >= 1e6)
    std::snprintf(buf, sizeof buf, "%.2f M", v / 1e6);
  else if (v >= 1e3)
    std::snprintf(buf, sizeof buf, "%.2f k", v / 1e3);
  else
    std::snprintf(buf, sizeof buf, "%.0f ", v);
  return buf;
}

std::string human_seconds(double s) {
  char buf[32];
  if (!std::isfinite(s)) return "?";
  if (s >= 3600)
    std::snprintf(buf, sizeof buf, "%dh%02dm", int(s / 3600), int(std::fmod(s, 3600) / 60));
  else if (s >= 60)
    std::snprintf(buf, sizeof buf, "%dm%02ds", int(s / 60), int(std::fmod(s, 60)));
  else
    std::snprintf(buf, sizeof buf, "%.1fs", s);
  return buf;
}

Progress::Progress(std::string label, uint64_t total, std::string unit, bool enabled)
    : label_(std::move(label)),
      unit_(std::move(unit)),
      total_(total),
      enabled_(enabled),
      tty_(isatty(STDERR_FILENO) != 0),
      start_(std::chrono::steady_clock::now()) {}

Progress::~Progress() {
  // When an error unwinds through a pass, the error line must be the only thing left to read.
  if (std::uncaught_exceptions() > 0) {
    if (enabled_ && tty_ && done_.load() > 0) std::fprintf(stderr, "\r\033[K");
    return;
  }
  finish();
}

double Progress::elapsed() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

void Progress::advance(uint64_t n) {
  uint64_t done = done_.fetch_add(n, std::memory_order_relaxed) + n;
  if (!enabled_) return;
  int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - start_).count();
  int64_t interval = tty_ ? 200'000'000 : 5'000'000'000;
  int64_t last = last_print_ns_.load(std::memory_order_relaxed);
  if (now - last < interval) return;
  if (!last_print_ns_.compare_exchange_strong(last, now)) return;
  print(done, false);
}

void Progress::finish() {
  if (finished_) return;
  finished_ = true;
  if (enabled_) print(done_.load(), true);
}

void Progress::set_ranks(int ranks) {
  std::lock_guard<std::mutex> lock(print_mutex_);
  ranks_ = ranks;
}

void Progress::set_done_before(uint64_t n) {
  {
    std::lock_guard<std::mutex> lock(print_mutex_);
    done_before_ = n;
  }
  done_ += n;
}

void Progress::set_note(const std::string& note) {
  std::lock_guard<std::mutex> lock(print_mutex_);
  note_ = note;
}

void Progress::print(uint64_t done, bool final) {
  std::lock_guard<std::mutex> lock(print_mutex_);
  double t = elapsed();
  double fraction = total_ ? double(done) / double(total_) : 1.0;
  const uint64_t here = done - std::min(done, done_before_);
  double rate = t > 0 ? double(here) / t : 0.0;
  double eta = rate > 0 ? double(total_ - std::min(done, total_)) / rate : INFINITY;
  rate *= double(ranks_);
  const std::string all = ranks_ > 1 ? " (" + std::to_string(ranks_) + " ranks)" : "";
  const int width = 28;
  int filled = int(fraction * width);
  std::string bar(size_t(filled), '=');
  if (filled < width) bar += '>', bar += std::string(size_t(width - filled - 1), ' ');
  std::fprintf(stderr, "%s%s [%s] %5.1f%% %s%s/s%s %s %s %s%s", tty_ ? "\r" : "", label_.c_str(), bar.c_str(),
               100.0 * fraction, human_count(rate).c_str(), unit_.c_str(), all.c_str(), note_.c_str(),
               final ? "elapsed" : "ETA", human_seconds(final ? t : eta).c_str(), (final || !tty_) ? "\n" : "\033[K");
  std::fflush(stderr);
}

}  // namespace bl
