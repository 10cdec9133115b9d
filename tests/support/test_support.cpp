#include "test_support.h"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <random>

namespace visq::testing {
namespace fs = std::filesystem;

std::optional<fs::path> SharedScenesDir() {
  fs::path dir = VISQ_SHARED_SCENES_DIR;
  if (const char* env = std::getenv("VISQ_SHARED_SCENES"); env != nullptr && *env != '\0') dir = env;
  std::error_code ec;
  if (fs::is_regular_file(dir / "SOURCES.md", ec)) return fs::canonical(dir, ec);
  return std::nullopt;
}

ScratchDir::ScratchDir() {
  std::random_device random;
  path_ = fs::temp_directory_path() / ("visq-test-" + std::to_string(::getpid()) + "-" + std::to_string(random()));
  fs::create_directories(path_);
}

ScratchDir::~ScratchDir() {
  std::error_code ec;
  fs::remove_all(path_, ec);
}

std::string RunCommand(const std::string& command, int* exit_status) {
  std::string output;
  std::FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) {
    *exit_status = -1;
    return output;
  }
  char buffer[4096];
  while (size_t n = std::fread(buffer, 1, sizeof(buffer), pipe)) output.append(buffer, n);
  *exit_status = ::pclose(pipe);
  return output;
}

}  // namespace visq::testing
