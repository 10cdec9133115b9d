// The real visq-server binary as a child process, for tests that drive it
// through client/ on loopback.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

namespace visq::testing {

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
