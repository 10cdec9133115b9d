#include "server_process.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>

#include "visq_client.h"

namespace visq::testing {
namespace fs = std::filesystem;

std::unique_ptr<ServerProcess> ServerProcess::Start(const Options& options) {
  std::unique_ptr<ServerProcess> process(new ServerProcess());
  static std::atomic<int> counter{0};
  const fs::path base = fs::temp_directory_path() /
                        ("visq-server-" + std::to_string(::getpid()) + "-" + std::to_string(counter++));
  process->log_path_ = base.string() + ".log";
  const std::string port_file = base.string() + ".port";
  std::error_code ec;
  fs::remove(port_file, ec);

  std::vector<std::string> args = {VISQ_SERVER_BINARY, "--address", "127.0.0.1:0", "--scene-repo",
                                   options.scene_repo.string(), "--port-file", port_file, "--gpu-debug"};
  args.insert(args.end(), options.extra_args.begin(), options.extra_args.end());
  const pid_t pid = ::fork();
  if (pid == 0) {
    // Child: log to a file, exec the real binary.
    std::FILE* log = std::fopen(process->log_path_.c_str(), "w");
    if (log != nullptr) {
      ::dup2(fileno(log), STDOUT_FILENO);
      ::dup2(fileno(log), STDERR_FILENO);
    }
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    ::execv(argv[0], argv.data());
    std::perror("execv visq-server");
    ::_exit(127);
  }
  process->pid_ = pid;

  // Wait for the port file, then for health SERVING.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (std::chrono::steady_clock::now() < deadline) {
    std::ifstream in(port_file);
    if (in >> process->port_ && process->port_ > 0) break;
    int status = 0;
    if (::waitpid(pid, &status, WNOHANG) == pid) {
      process->pid_ = -1;
      ADD_FAILURE() << "visq-server exited during start-up:\n" << process->Log();
      return nullptr;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (process->port_ <= 0) {
    ADD_FAILURE() << "visq-server wrote no port in 60 s:\n" << process->Log();
    return nullptr;
  }
  client::Client client({.address = process->address()});
  const Status serving = client.WaitUntilServing(std::chrono::seconds(120));
  if (!serving.ok()) {
    ADD_FAILURE() << serving.message() << "\n" << process->Log();
    return nullptr;
  }
  return process;
}

ServerProcess::~ServerProcess() {
  if (pid_ > 0) Stop();
}

int ServerProcess::Stop() {
  if (pid_ <= 0) return -1;
  ::kill(pid_, SIGTERM);
  int status = 0;
  for (int i = 0; i < 600; ++i) {  // 30 s, then SIGKILL
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      return status;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ::kill(pid_, SIGKILL);
  ::waitpid(pid_, &status, 0);
  pid_ = -1;
  return status;
}

void ServerProcess::Kill() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGKILL);
  int status = 0;
  ::waitpid(pid_, &status, 0);
  pid_ = -1;
}

std::string ServerProcess::Log() const {
  std::ifstream in(log_path_);
  std::stringstream out;
  out << in.rdbuf();
  return out.str();
}

}  // namespace visq::testing
