#pragma once
// Strict JSON reading shared by the scene loader and the optimizer config: every key must be
// consumed (unknown keys are reported with their JSON pointer), values are type- and
// range-checked, and errors are one line "<file>: <pointer>: <problem>".
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/core/math.h"

namespace bl {

using nlohmann::json;

// A JSON object being read: remembers which keys were consumed so leftovers can be reported.
class Node {
 public:
  // A node with no keys of its own, for reporting errors at `pointer` (it must not refer to a
  // temporary: Node keeps a reference to its JSON).
  static Node at_pointer(std::string pointer, const std::string& file) {
    static const json empty = json::object();
    return Node(empty, std::move(pointer), file);
  }
  Node(const json& j, std::string pointer, const std::string& file) : j_(j), ptr_(std::move(pointer)), file_(file) {
    if (!j_.is_object()) fail("expected an object");
  }
  [[noreturn]] void fail(const std::string& msg) const {
    throw file_error(file_, (ptr_.empty() ? "/" : ptr_) + ": " + msg);
  }
  [[noreturn]] void fail_at(const std::string& key, const std::string& msg) const {
    throw file_error(file_, ptr_ + "/" + key + ": " + msg);
  }
  bool has(const std::string& key) const { return j_.contains(key); }
  const json& at(const std::string& key) {
    if (!j_.contains(key)) fail("missing required key '" + key + "'");
    used_.insert(key);
    return j_.at(key);
  }
  const json* find(const std::string& key) {
    if (!j_.contains(key)) return nullptr;
    used_.insert(key);
    return &j_.at(key);
  }
  Node child(const std::string& key) { return Node(at(key), ptr_ + "/" + key, file_); }
  // The whole object, for iterating over free-form keys (mark each one with mark_used).
  const json& at_all() {
    for (auto it = j_.begin(); it != j_.end(); ++it) used_.insert(it.key());
    return j_;
  }
  void mark_used(const std::string& key) { used_.insert(key); }
  std::string pointer(const std::string& key) const { return ptr_ + "/" + key; }
  const std::string& pointer() const { return ptr_; }  // this node's own
  const std::string& file() const { return file_; }
  // Reports the first key nobody read.
  void finish() const {
    for (auto it = j_.begin(); it != j_.end(); ++it)
      if (!used_.count(it.key())) fail("unknown key '" + it.key() + "'");
  }

  double number(const std::string& key, double fallback, double lo = -1e30, double hi = 1e30) {
    const json* v = find(key);
    if (!v) return fallback;
    return checked_number(*v, key, lo, hi);
  }
  double number_required(const std::string& key, double lo = -1e30, double hi = 1e30) {
    return checked_number(at(key), key, lo, hi);
  }
  double checked_number(const json& v, const std::string& key, double lo, double hi) const {
    if (!v.is_number()) fail_at(key, "expected a number");
    double d = v.get<double>();
    if (!std::isfinite(d)) fail_at(key, "not a finite number");
    if (d < lo || d > hi) {
      std::ostringstream s;
      s << "value " << d << " outside the valid range [" << lo << ", " << hi << "]";
      fail_at(key, s.str());
    }
    return d;
  }
  // A whole number in [lo, hi]; 2.5 is an error, not 2.
  long integer(const std::string& key, long fallback, long lo, long hi) {
    return find(key) ? integer_required(key, lo, hi) : fallback;
  }
  long integer_required(const std::string& key, long lo, long hi) {
    double d = checked_number(at(key), key, double(lo), double(hi));
    if (d != std::floor(d)) fail_at(key, "expected a whole number");
    return long(d);
  }
  bool boolean(const std::string& key, bool fallback) {
    const json* v = find(key);
    if (!v) return fallback;
    if (!v->is_boolean()) fail_at(key, "expected true or false");
    return v->get<bool>();
  }
  std::string string(const std::string& key) {
    const json& v = at(key);
    if (!v.is_string()) fail_at(key, "expected a string");
    return v.get<std::string>();
  }
  std::string string(const std::string& key, const std::string& fallback) { return has(key) ? string(key) : fallback; }
  Vec3f vec3(const std::string& key) { return vec3_of(at(key), pointer(key)); }
  Vec3f vec3(const std::string& key, Vec3f fallback) { return has(key) ? vec3(key) : fallback; }
  Vec3f vec3_of(const json& v, const std::string& where) const {
    if (!v.is_array() || v.size() != 3) throw file_error(file_, where + ": expected [x, y, z]");
    Vec3f r;
    for (int i = 0; i < 3; ++i) {
      if (!v[size_t(i)].is_number()) throw file_error(file_, where + ": expected numbers");
      r[i] = v[size_t(i)].get<float>();
      if (!std::isfinite(r[i])) throw file_error(file_, where + ": not a finite number");
    }
    return r;
  }

 private:
  const json& j_;
  std::string ptr_;
  const std::string& file_;
  std::set<std::string> used_;
};

inline std::string line_col(const std::string& text, size_t byte) {
  size_t line = 1, col = 1;
  for (size_t i = 0; i < std::min(byte, text.size()); ++i) {
    if (text[i] == '\n') {
      ++line;
      col = 1;
    } else {
      ++col;
    }
  }
  return std::to_string(line) + ":" + std::to_string(col > 1 ? col - 1 : 1);
}

// The whole of an input file (scene, optimizer config, XML, mesh): a regular file within
// limits::kFileBytes. A FIFO would block forever and /dev/zero would never end.
inline std::string read_input_file(const std::string& path) {
  namespace fs = std::filesystem;
  require_input_file(path);
  limits::require_at_most(path, "file size", uint64_t(fs::file_size(path)), limits::kFileBytes);
  std::ifstream f(path, std::ios::binary);
  if (!f) throw file_error(path, "cannot open");
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}
inline std::string read_json_file(const std::string& path) { return read_input_file(path); }

// Parses `text` (the contents of `file`); syntax errors report line:column.
inline json parse_json_text(const std::string& text, const std::string& file) {
  // nlohmann's parser and every copy of a json value recurse: bound the depth first.
  limits::check_json_depth(file, text);
  // A key given twice in one object: nlohmann keeps the last without a word (a setting written
  // twice, the first forgotten). Keys of each open object are collected while parsing.
  std::vector<std::set<std::string>> open_objects;
  std::string duplicate;
  const json::parser_callback_t on_event = [&](int, json::parse_event_t event, json& parsed) {
    if (event == json::parse_event_t::object_start) {
      open_objects.emplace_back();
    } else if (event == json::parse_event_t::object_end) {
      if (!open_objects.empty()) open_objects.pop_back();
    } else if (event == json::parse_event_t::key && !open_objects.empty() && duplicate.empty() &&
               !open_objects.back().insert(parsed.get<std::string>()).second) {
      duplicate = parsed.get<std::string>();
    }
    return true;
  };
  try {
    json j = json::parse(text, on_event);
    if (!duplicate.empty())
      throw file_error(file, "key '" + duplicate.substr(0, 200) + "' appears twice in one object");
    return j;
  } catch (const json::parse_error& e) {
    std::string msg = e.what();
    if (auto p = msg.find("parse error"); p != std::string::npos) msg = msg.substr(p);
    throw file_error(file, line_col(text, e.byte) + ": malformed JSON (" + msg + ")");
  } catch (const json::exception& e) {
    // e.g. a number too large for a double ("1e999")
    std::string msg = e.what();
    if (auto p = msg.find("] "); p != std::string::npos) msg = msg.substr(p + 2);
    throw file_error(file, "invalid JSON (" + msg + ")");
  }
}

// What is wrong with `name` as the name of a scene object whose parameters are "<name>.<key>" and
// whose outputs are files named after it (gradients, an optimizer's targets and snapshots), or ""
// when nothing is: empty, a '.' (the parameter separator), a '/' or '\\' (it would name a file in
// another folder, "../x" one outside the output folder), a NUL byte or another control character.
inline std::string object_name_problem(const std::string& name) {
  if (name.empty()) return "is empty";
  for (char ch : name) {
    if (ch == '.') return "contains '.' (parameters are named <object>.<key>)";
    if (ch == '/' || ch == '\\') return "contains a path separator (outputs are files named after it)";
    if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) return "contains a control character or NUL byte";
  }
  return "";
}

struct Camera;
// Reads a camera object (scene format, scenes/README.md); used by scenes and optimizer configs.
Camera parse_camera(Node& n, const std::string& default_name);

}  // namespace bl
