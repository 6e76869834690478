#pragma once
// Taped reverse-mode AD of the whole render: the baseline prb is measured against, and a test
// oracle for it. The path loop of engine/integrators/path.h runs on the tape scalar (engine/core/tape.h); every
// parameter-dependent operation of every sample is recorded, the loss is computed from the
// finished image, and one reverse sweep per thread tape writes the gradients.
#include "engine/integrators/gradient.h"

namespace bl {

GradientResult taped_gradient(Scene& scene, const GradientRequest& request);

// Physical memory in bytes, or this process's cgroup memory limit where that is lower (for the
// default budget: 80% of it).
size_t physical_memory_bytes();
// The memory limit of the cgroup `proc_cgroup` (/proc/self/cgroup) names under `root`
// (/sys/fs/cgroup): v2 memory.max, v1 memory/<path>/memory.limit_in_bytes, then the v1 root's; 0
// when there is none ("max", v1's ~2^63). In a container the machine's RAM is not what the
// process may use.
size_t cgroup_memory_limit(const std::string& proc_cgroup, const std::string& root);
// Parses "512MB", "4GB", "1.5G", "100000" (bytes). Throws InputError.
size_t parse_memory_size(const std::string& text);

}  // namespace bl
