#include "engine/scene/openvdb_io.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/io/image_io.h"
#include "engine/plugins/plugin.h"
#include "engine/scene/openvdb_reader.h"

extern char** environ;

namespace bl {

namespace fs = std::filesystem;

namespace {

// The reader runs in its own process (see openvdb_io.h): a path to it, a private folder for its
// output, its stderr collected while it runs, and a verdict from its exit status.
std::string reader_executable() {
  if (const char* env = std::getenv("BACKLIGHT_VDB_READER"); env && *env) return env;
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    const fs::path next = self.parent_path() / "backlight-vdb-read";
    if (::access(next.c_str(), X_OK) == 0) return next.string();
  }
#ifdef BL_VDB_READER_PATH
  if (::access(BL_VDB_READER_PATH, X_OK) == 0) return BL_VDB_READER_PATH;
#endif
  return "";
}

// Named backlight-vdb-<pid>-XXXXXX: a process killed while its reader ran never reaches the
// destructor, and its folder (holding up to the whole dense grid) stayed for ever (helper-45: 21
// MB after five interrupted renders). Each new one first removes those of processes gone.
struct PrivateDir {
  std::string path;
  PrivateDir() {  // in $TMPDIR, else /tmp; path stays empty when neither works
    const char* base = std::getenv("TMPDIR");
    for (const std::string& root : {std::string(base && *base ? base : "/tmp"), std::string("/tmp")}) {
      remove_abandoned(root);
      std::string pattern = root + "/backlight-vdb-" + std::to_string(::getpid()) + "-XXXXXX";
      if (::mkdtemp(pattern.data()) != nullptr) {
        path = pattern;
        return;
      }
    }
  }
  static void remove_abandoned(const std::string& root) {
    std::error_code ec;
    for (fs::directory_iterator it(root, ec), end; !ec && it != end; it.increment(ec)) {
      const std::string name = it->path().filename().string();
      const std::string prefix = "backlight-vdb-";
      const size_t dash = name.find('-', prefix.size());
      std::error_code e;
      if (name.rfind(prefix, 0) != 0 || dash == std::string::npos || name.size() != dash + 7 || !it->is_directory(e) ||
          !process_gone(name.substr(prefix.size(), dash - prefix.size())))
        continue;
      fs::remove_all(it->path(), e);
    }
  }
  ~PrivateDir() {
    std::error_code ec;
    if (!path.empty()) fs::remove_all(path, ec);
  }
};

struct Fd {
  int fd = -1;
  ~Fd() {
    if (fd >= 0) ::close(fd);
  }
};

}  // namespace

VolumeGrid read_vdb(const std::string& path, const std::string& grid_name, const VdbReadLimits& lim) {
  return with_path_errors([&] {
    // Checks that need no parsing stay here: quick, and the same messages as every loader.
    require_input_file(path);
    limits::require_at_most(path, "file size", uint64_t(fs::file_size(path)), limits::kFileBytes);
    const std::string reader = reader_executable();
    if (reader.empty())
      throw file_error(path,
                       "cannot read OpenVDB files: the helper 'backlight-vdb-read' is neither next to this "
                       "executable nor in the build tree (set BACKLIGHT_VDB_READER to its path)");
    PrivateDir dir;
    if (dir.path.empty()) throw file_error(path, "cannot create a temporary folder for the OpenVDB reader");
    size_t memory_mb = lim.memory_mb;
    if (memory_mb == 0) {
      const char* env = std::getenv("BACKLIGHT_VDB_MEMORY_MB");
      char* end = nullptr;
      const unsigned long long v = env ? std::strtoull(env, &end, 10) : 0;
      memory_mb = env && *env && *end == '\0' && v >= 64 && v <= (1ull << 30) ? size_t(v) : 4096;
    }
    const std::string out = dir.path + "/grid.vol", memory = std::to_string(memory_mb);
    std::vector<std::string> args = {reader, path, grid_name, out, memory};
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    // Under AddressSanitizer the address space cannot be limited (the shadow memory alone is
    // terabytes of it), so the reader gets ASan's own RSS and allocation limits instead.
    std::vector<std::string> env_strings;
    std::string asan = std::string("ASAN_OPTIONS=") + (std::getenv("ASAN_OPTIONS") ? std::getenv("ASAN_OPTIONS") : "");
    for (char** e = environ; *e; ++e)
      if ((!kAddressSanitizer || std::strncmp(*e, "ASAN_OPTIONS=", 13) != 0) &&
          std::strncmp(*e, "BACKLIGHT_VDB_PARENT=", 21) != 0)
        env_strings.emplace_back(*e);
    // The reader stops when this process dies (PR_SET_PDEATHSIG), checking that it was not gone
    // before it asked: a reader of a killed process parsed on and wrote into its folder.
    env_strings.push_back("BACKLIGHT_VDB_PARENT=" + std::to_string(::getpid()));
    if (kAddressSanitizer)
      env_strings.push_back(asan + (asan.back() == '=' ? "" : ":") + "hard_rss_limit_mb=" + memory +
                            ":max_allocation_size_mb=" + memory);
    std::vector<char*> envp;
    for (auto& e : env_strings) envp.push_back(e.data());
    envp.push_back(nullptr);

    int pipe_fds[2];
    if (::pipe2(pipe_fds, O_CLOEXEC) != 0) throw file_error(path, "cannot start the OpenVDB reader (pipe failed)");
    Fd read_end{pipe_fds[0]}, write_end{pipe_fds[1]};
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
    posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
    posix_spawn_file_actions_adddup2(&actions, write_end.fd, 2);
    pid_t pid = -1;
    const int spawned = ::posix_spawn(&pid, reader.c_str(), &actions, nullptr, argv.data(), envp.data());
    posix_spawn_file_actions_destroy(&actions);
    if (spawned != 0)
      throw file_error(path, "cannot start the OpenVDB reader '" + reader + "' (" + std::strerror(spawned) + ")");
    ::close(write_end.fd);
    write_end.fd = -1;

    // Collect its stderr (the last 64 KB: its verdict comes last) until it closes, or kill it at
    // the deadline.
    std::string messages;
    bool timed_out = false;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(lim.seconds);
    for (;;) {
      const double left = std::chrono::duration<double>(deadline - std::chrono::steady_clock::now()).count();
      if (left <= 0) {
        timed_out = true;
        ::kill(pid, SIGKILL);
        break;
      }
      pollfd p{read_end.fd, POLLIN, 0};
      const int ready = ::poll(&p, 1, int(std::min(left * 1000.0 + 1, 1000.0)));
      if (ready < 0 && errno != EINTR) break;
      if (ready <= 0) continue;
      char buf[4096];
      const ssize_t n = ::read(read_end.fd, buf, sizeof buf);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) break;  // EOF: the reader exited (or closed stderr)
      messages.append(buf, size_t(n));
      if (messages.size() > 65536) messages.erase(0, messages.size() - 65536);
    }
    int status = 0;
    while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
    }
    auto fail = [&](const std::string& why) { return file_error(path, "cannot read OpenVDB file (" + why + ")"); };
    if (timed_out) {
      char seconds[32];
      std::snprintf(seconds, sizeof seconds, "%g", lim.seconds);
      throw fail(std::string("the reader took longer than ") + seconds + " s and was stopped");
    }
    if (WIFSIGNALED(status)) throw fail(std::string("the reader crashed: ") + strsignal(WTERMSIG(status)));
    const int code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    if (code == 2) {
      // The reader's one-line InputError, "<file>: <problem>", is the last line it prints
      // (OpenVDB may warn on stderr before it).
      while (!messages.empty() && (messages.back() == '\n' || messages.back() == '\r')) messages.pop_back();
      std::string line =
          messages.substr(messages.find_last_of('\n') == std::string::npos ? 0 : messages.find_last_of('\n') + 1);
      if (line.empty()) line = path + ": cannot read OpenVDB file";
      // Grid names come from the file: no control characters reach the terminal.
      for (char& c : line)
        if ((unsigned char)c < 0x20 || c == 0x7f) c = '?';
      throw InputError(line);
    }
    if (code != 0)
      throw fail("the reader failed with exit code " + std::to_string(code) + "; its memory limit is " + memory +
                 " MB, set by BACKLIGHT_VDB_MEMORY_MB");
    try {
      return read_vol(out);
    } catch (const InputError& e) {
      throw fail(std::string("the reader's output is unreadable: ") + e.what());
    }
  });
}

void write_vdb(const std::string& path, const VolumeGrid& g, const std::string& grid_name) {
  if (g.channels != 1 && g.channels != 3) throw file_error(path, "OpenVDB grids are written with 1 or 3 channels");
  if (g.x <= 0 || g.y <= 0 || g.z <= 0 || g.data.size() != g.voxels_checked())
    throw file_error(path, "grid to write has sizes that do not match its values");
  if (!(g.bbox_max.x > g.bbox_min.x && g.bbox_max.y > g.bbox_min.y && g.bbox_max.z > g.bbox_min.z))
    throw file_error(path, "grid to write has an empty or inverted world box");
  const auto& vdb = plugin::openvdb(path, "writing an OpenVDB file");
  const fs::path p(path);
  const std::string tmp =
      (p.parent_path() / ("." + p.stem().string() + ".tmp" + std::to_string(getpid()) + ".vdb")).string();
  if (std::string error; !vdb.write(tmp, g, grid_name, &error)) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw file_error(path, error);
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw file_error(path, "cannot write (rename failed)");
  }
}

}  // namespace bl
