#pragma once
// Opening backlight's plugins (plugin_api.h) on first use.
//
// A plugin `libbacklight_<name>.so` is looked for in $BACKLIGHT_PLUGIN_DIR when that is set (and
// only there), else next to the running executable (all of backlight's executables and plugins
// are built into bin/), else in the build tree's bin/ (for the Python module and for tests run
// from elsewhere). Opened once per process and never closed.
#include <string>

#include "engine/plugins/plugin_api.h"

namespace bl::plugin {

// The plugin's table. A plugin that cannot be found, opened or that was built for another
// interface is an InputError "<for_path>: <what> needs the <name> plugin (<reason>)": the
// file that asked for it is named, as for any other input problem.
const OiioApi& oiio(const std::string& for_path, const std::string& what);
const OpenVdbApi& openvdb(const std::string& for_path, const std::string& what);

}  // namespace bl::plugin
