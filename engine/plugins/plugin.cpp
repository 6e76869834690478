#include "engine/plugins/plugin.h"

#include <dlfcn.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <map>
#include <mutex>

#include "engine/core/errors.h"

namespace bl::plugin {

namespace fs = std::filesystem;

namespace {

// Where `file` is: the folders in the order of plugin.h, the first that has it.
std::string find_plugin(const std::string& file, std::string* looked_in) {
  std::vector<fs::path> dirs;
  if (const char* env = std::getenv("BACKLIGHT_PLUGIN_DIR"); env && *env) {
    dirs.push_back(env);
  } else {
    std::error_code ec;
    const fs::path self = fs::read_symlink("/proc/self/exe", ec);
    if (!ec) dirs.push_back(self.parent_path());
#ifdef BL_PLUGIN_DIR
    dirs.push_back(BL_PLUGIN_DIR);
#endif
  }
  for (const auto& d : dirs) {
    const fs::path candidate = d / file;
    if (::access(candidate.c_str(), R_OK) == 0) return candidate.string();
    if (!looked_in->empty()) *looked_in += ", ";
    *looked_in += d.string();
  }
  return "";
}

// dlopen + dlsym of `entry`, once per plugin; the table or a reason why not. The entry point is
// called through its own type (`const Api* ()`): UBSan checks function pointer types.
template <class Api>
const Api* open_plugin(const std::string& name, const char* entry, std::string* reason) {
  static std::mutex mutex;
  static std::map<std::string, std::pair<const Api*, std::string>> opened;
  std::lock_guard<std::mutex> lock(mutex);
  if (auto it = opened.find(name); it != opened.end()) {
    *reason = it->second.second;
    return it->second.first;
  }
  const std::string file = "libbacklight_" + name + ".so";
  std::string looked_in;
  const std::string path = find_plugin(file, &looked_in);
  const Api* table = nullptr;
  if (path.empty()) {
    *reason = file + " not found in " + looked_in + "; BACKLIGHT_PLUGIN_DIR names the folder holding it";
  } else if (void* handle = ::dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL); !handle) {
    const char* e = ::dlerror();
    *reason = "cannot open " + path + ": " + (e ? e : "unknown error");
  } else if (void* fn = ::dlsym(handle, entry); !fn) {
    *reason = path + " has no " + entry;
  } else {
    using Entry = const Api* (*)();
    table = reinterpret_cast<Entry>(fn)();
    if (!table || table->abi != kPluginAbi) {
      *reason = path + " was built for another version of backlight";
      table = nullptr;
    }
  }
  opened[name] = {table, *reason};
  return table;
}

template <class Api>
const Api& get(const std::string& name, const char* entry, const std::string& for_path, const std::string& what) {
  std::string reason;
  const Api* table = open_plugin<Api>(name, entry, &reason);
  if (!table) throw file_error(for_path, what + " needs the " + name + " plugin (" + reason + ")");
  return *table;
}

}  // namespace

const OiioApi& oiio(const std::string& for_path, const std::string& what) {
  return get<OiioApi>("oiio", "backlight_oiio_plugin", for_path, what);
}
const OpenVdbApi& openvdb(const std::string& for_path, const std::string& what) {
  return get<OpenVdbApi>("openvdb", "backlight_openvdb_plugin", for_path, what);
}

}  // namespace bl::plugin
