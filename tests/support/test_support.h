// Helpers shared by visq's tests: where the shared scenes are, scratch
// folders, a GPU worker for GL tests, and the real server process.
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "visq/gpu/gpu_worker.h"

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

// One GPU worker (llvmpipe here) shared by every test of an executable, with
// GL error checks on. Fails the test if no context can be made.
gpu::GpuWorker& SharedGpuWorker();

// Runs a shell command (the visq CLI, say) and returns its standard output;
// `exit_status` receives pclose's status (0: success).
std::string RunCommand(const std::string& command, int* exit_status);

// A visq-server child process on a free loopback port, stopped (SIGTERM,
// then SIGKILL) with the object.
class ServerProcess {
 public:
  struct Options {
    std::filesystem::path scene_repo;
    std::vector<std::string> extra_args;
  };
  // Starts the binary and waits until health reports SERVING.
  static std::unique_ptr<ServerProcess> Start(const Options& options);
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  std::string address() const { return "127.0.0.1:" + std::to_string(port_); }
  int port() const { return port_; }
  int pid() const { return pid_; }
  // Sends SIGTERM and waits; returns the exit status.
  int Stop();
  // SIGKILL, for crash tests.
  void Kill();
  std::string Log() const;

 private:
  ServerProcess() = default;
  int pid_ = -1;
  int port_ = 0;
  std::filesystem::path log_path_;
};

}  // namespace visq::testing
