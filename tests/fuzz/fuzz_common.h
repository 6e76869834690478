#pragma once
// Shared by the libFuzzer harnesses in this folder (see README.md "Sanitizers and fuzzing").
// - Each input is written to ONE fixed file name in a per-process scratch folder
//   /tmp/backlight-fuzz/<pid>/, overwritten on every run and removed at exit.
// - Small valid assets (textures, an environment map, glTF meshes, .vol grids) live in the fixed folder
//   /tmp/backlight-fuzz/assets/, so seeds and dictionaries can name them: "../assets/tex.png"
//   from a scene in the scratch folder, or the absolute path (as `--set` needs).
// - bl::InputError is the loaders' documented way to reject input and is ignored; any other
//   exception escapes the harness, std::terminate aborts and libFuzzer reports it as a crash.
#include <fcntl.h>
#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "engine/io/image_io.h"

namespace bl::fuzz {

inline const std::string kRoot = "/tmp/backlight-fuzz";
inline const std::string kAssets = kRoot + "/assets";

// Copies `from` to `to` atomically (temp name + rename): concurrent harness processes share assets.
inline void install_file(const std::filesystem::path& from, const std::string& to) {
  const std::string tmp = to + ".tmp" + std::to_string(getpid());
  std::filesystem::copy_file(from, tmp, std::filesystem::copy_options::overwrite_existing);
  std::filesystem::rename(tmp, to);
}

// Creates the shared assets once per process (cheap; every write is atomic).
inline void make_assets() {
  namespace fs = std::filesystem;
  fs::create_directories(kAssets);
  Image tex(4, 4, 3), env(8, 4, 3);
  for (size_t i = 0; i < tex.data.size(); ++i) tex.data[i] = float(i % 7) / 7.f;
  for (size_t i = 0; i < env.data.size(); ++i) env.data[i] = 0.25f + float(i % 5);
  write_image(kAssets + "/tex.png", tex);
  write_image(kAssets + "/tex.exr", tex);
  write_image(kAssets + "/env.exr", env);
  const fs::path src(BL_SOURCE_DIR);
  for (const char* f : {"scene.gltf", "scene.bin", "checker.png"})
    install_file(src / "scenes/gltf" / f, kAssets + "/" + f);
  install_file(src / "tests/fuzz/corpus/fuzz_gltf/tiny.glb", kAssets + "/tiny.glb");
  install_file(src / "tests/fuzz/corpus/fuzz_mesh/quad.obj", kAssets + "/quad.obj");
  install_file(src / "tests/fuzz/corpus/fuzz_mesh/quad_binary.ply", kAssets + "/quad.ply");
  install_file(src / "tests/fuzz/corpus/fuzz_vol/grid_2x3x4.vol", kAssets + "/grid.vol");
  install_file(src / "tests/fuzz/corpus/fuzz_vol/one_voxel.vol", kAssets + "/albedo.vol");
}

// This process's scratch folder; the first call creates it (and the assets) and removes the
// folders of processes that no longer exist (a crashed run does not clean up after itself).
inline const std::string& scratch_dir() {
  // Never destroyed: the atexit handler below runs after static destructors would have.
  static const std::string& dir = *new std::string([] {
    namespace fs = std::filesystem;
    std::error_code ec;
    fs::create_directories(kRoot, ec);
    for (const auto& e : fs::directory_iterator(kRoot, ec)) {
      const std::string name = e.path().filename().string();
      if (name.empty() || name.find_first_not_of("0123456789") != std::string::npos) continue;
      if (kill(pid_t(std::stol(name)), 0) != 0 && errno == ESRCH) fs::remove_all(e.path(), ec);
    }
    make_assets();
    std::string d = kRoot + "/" + std::to_string(getpid());
    fs::create_directories(d);
    std::atexit([] {
      std::error_code ignored;
      std::filesystem::remove_all(scratch_dir(), ignored);
    });
    return d;
  }());
  return dir;
}

// Writes the input bytes to scratch_dir()/name and returns the path. The file is overwritten in
// place and then cut to size: truncating to zero first makes ext4 flush it on every close
// (auto_da_alloc), which halved the harnesses' speed.
inline std::string write_input(const std::string& name, const uint8_t* data, size_t size) {
  std::string path = scratch_dir() + "/" + name;
  const int fd = open(path.c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) std::abort();
  for (size_t done = 0; done < size;) {
    const ssize_t n = pwrite(fd, data + done, size - done, off_t(done));
    if (n <= 0) std::abort();
    done += size_t(n);
  }
  if (ftruncate(fd, off_t(size)) != 0) std::abort();
  close(fd);
  return path;
}

}  // namespace bl::fuzz
