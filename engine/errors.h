#pragma once
// Errors caused by user input (scene files, images, flags). The CLI prints them as one line and
// exits with code 2; they are never assertions.
#include <stdexcept>
#include <string>

namespace bl {

struct InputError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// "<file>: <problem>" — the one-line form every loader uses.
inline InputError file_error(const std::string& file, const std::string& problem) {
  return InputError(file + ": " + problem);
}

}  // namespace bl
