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

// Seconds a call's stop may take beyond its limit in a sanitizer build. The
// limits the tests hold stops to (a second past a deadline or a drain) are
// the release build's; instrumented, the CPU side of one GL job grows
// several times (a volumetric shadow's first 4096^2 targets: 2.4 s in one
// job under ASan). The stop itself is still checked there.
#if defined(__has_feature)
#if __has_feature(address_sanitizer)
#define VISQ_TEST_SANITIZED 1
#endif
#endif
#if defined(__SANITIZE_ADDRESS__)
#define VISQ_TEST_SANITIZED 1
#endif
#ifdef VISQ_TEST_SANITIZED
inline constexpr double kSanitizedStopSlackSeconds = 5.0;
#else
inline constexpr double kSanitizedStopSlackSeconds = 0.0;
#endif

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
