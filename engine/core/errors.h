#pragma once
// Errors caused by user input (scene files, images, flags). The CLI prints them as one line and
// exits with code 2; they are never assertions.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <stdexcept>
#include <string>

namespace bl {

struct InputError : std::runtime_error {
  // One line whatever the input held: control characters (a newline in a glTF material name, a
  // file name, an extension name) become '?'.
  explicit InputError(std::string message) : std::runtime_error(one_line(std::move(message))) {}

 private:
  static std::string one_line(std::string s) {
    for (char& c : s)
      if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = '?';
    return s;
  }
};

// `name` for a one-line message: control characters and NUL as \xNN, at most `max` characters
// (a name inside a message; std::string::npos for a path that must be given whole).
inline std::string printable_name(const std::string& name, size_t max = 64) {
  std::string out;
  for (char ch : name.substr(0, max)) {
    if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) {
      char hex[8];
      std::snprintf(hex, sizeof hex, "\\x%02x", unsigned(static_cast<unsigned char>(ch)));
      out += hex;
    } else {
      out += ch;
    }
  }
  return name.size() > max ? out + "..." : out;
}

// "<file>: <problem>" — the one-line form every loader uses.
inline InputError file_error(const std::string& file, const std::string& problem) {
  return InputError(file + ": " + problem);
}

// Runs `f`, turning a std::filesystem error (a path component too long, a permission, a file
// where a folder was expected) into the one-line InputError of the path it names: such errors
// come from the paths a user gave, never from a bug.
template <class F>
auto with_path_errors(F&& f) -> decltype(f()) {
  try {
    return f();
  } catch (const std::filesystem::filesystem_error& e) {
    const std::string path = e.path1().empty() ? std::string("(path)") : e.path1().string();
    throw file_error(path.size() > 200 ? path.substr(0, 200) + "..." : path, e.code().message());
  }
}

// An input file named by the user: the name holds no NUL byte (the operating system would read
// only the part before it, while format detection saw the whole name), the file exists, and it
// is a regular file (a FIFO would block forever, /dev/zero would never end).
inline void require_input_file(const std::string& path) {
  if (path.find('\0') != std::string::npos)
    throw file_error(path.substr(0, path.find('\0')) + "\\0...", "file name contains a NUL byte");
  if (!std::filesystem::exists(path)) throw file_error(path, "file not found");
  if (!std::filesystem::is_regular_file(path)) throw file_error(path, "not a regular file");
}

// Checks, without creating anything, that `dir` can become an output folder: it is a folder, or
// its nearest existing ancestor is one that we may write into.
inline void check_output_folder(const std::string& dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  fs::path p = fs::absolute(fs::path(dir), ec);
  if (ec) throw file_error(dir, "not a usable output folder (" + ec.message() + ")");
  if (fs::exists(p, ec) && !fs::is_directory(p, ec))
    throw file_error(dir, "exists and is not a folder (outputs go into a folder)");
  while (!p.empty() && !fs::exists(p, ec)) {
    if (ec) throw file_error(dir, "not a usable output folder (" + ec.message() + ")");
    if (p == p.parent_path()) break;
    p = p.parent_path();
  }
  if (!fs::is_directory(p, ec))
    throw file_error(dir, "cannot create the output folder: '" + p.string() + "' is not a folder");
  if (::access(p.c_str(), W_OK) != 0)
    throw file_error(dir, "cannot create the output folder: '" + p.string() + "' is not writable");
}

// Creates folder `dir` (and its parents) for outputs, or explains in one line why it cannot.
inline void ensure_output_folder(const std::string& dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (fs::exists(dir, ec) && !fs::is_directory(dir, ec))
    throw file_error(dir, "exists and is not a folder (outputs go into a folder)");
  fs::create_directories(dir, ec);
  if (ec) throw file_error(dir, "cannot create the output folder (" + ec.message() + ")");
}

}  // namespace bl
