// Helpers every visq test may use: where the shared scenes are, scratch
// folders, shell commands. The GPU worker is in gpu_test_support.h and the
// server process in server_process.h, each its own small library, so a
// suite links (and waits for) only what it uses.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include <gtest/gtest.h>

namespace visq::testing {

// ../shared/scenes beside the checkout (or $VISQ_SHARED_SCENES), if present.
std::optional<std::filesystem::path> SharedScenesDir();

// Skips the current test, saying why, when the shared scenes are absent.
#define VISQ_REQUIRE_SHARED_SCENES(dir_var)                                                      \
  auto dir_var##_optional = ::visq::testing::SharedScenesDir();                                  \
  if (!dir_var##_optional) GTEST_SKIP() << "../shared/scenes is absent: real-scene test skipped"; \
  const std::filesystem::path dir_var = *dir_var##_optional

// A fresh temporary folder, removed with the object.
class ScratchDir {
 public:
  ScratchDir();
  ~ScratchDir();
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

// Runs a shell command (the visq CLI, say) and returns its standard output;
// `exit_status` receives pclose's status (0: success).
std::string RunCommand(const std::string& command, int* exit_status);

}  // namespace visq::testing
