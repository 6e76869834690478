#pragma once
// The OpenVDB file reader proper, run only inside the `backlight-vdb-read` helper process
// (tools/vdb_read.cpp). OpenVDB's reader trusts its input: on a crafted file it reads invalid
// bools, allocates what a length field says and loops over counts it never checks, so read_vdb
// (openvdb_io.h) runs this in a separate process with memory and time limits and reads back a
// .vol. Call it directly only on files you wrote yourself.
#include <functional>
#include <string>

#include "engine/scene/volume_io.h"

namespace bl {

// Built with AddressSanitizer: the reader process cannot have its address space limited (ASan's
// shadow memory alone reserves terabytes), so it gets ASan's RSS and allocation limits instead.
// BL_ADDRESS_SANITIZER is the same fact for the preprocessor (tools/vdb_read.cpp).
#if defined(__SANITIZE_ADDRESS__)
#define BL_ADDRESS_SANITIZER 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define BL_ADDRESS_SANITIZER 1
#endif
#endif
#ifndef BL_ADDRESS_SANITIZER
#define BL_ADDRESS_SANITIZER 0
#endif
inline constexpr bool kAddressSanitizer = BL_ADDRESS_SANITIZER;

void openvdb_initialize_once();
// The grid as described for read_vdb; errors are InputError "<file>: <problem>". `parsed`, when
// given, is called once OpenVDB has read the grid, before the dense copy is allocated.
VolumeGrid read_vdb_in_process(const std::string& path, const std::string& grid_name,
                               const std::function<void()>& parsed = {});

}  // namespace bl
