// The farm bake's two Jobs (deploy/k8s/farm-bake/) on loopback, as a
// cluster would run their pods: each container's command and args exactly
// as the manifest gives them, with the image's ENV under the container's
// env, JOB_COMPLETION_INDEX 0 .. completions-1, the real visq-server and
// visq binaries on PATH, and every volume a scratch folder (the claims
// shared by all pods, each pod's emptyDir its own). The bake pods and the
// merge pod run at once, as they do when both Jobs are applied together.
// Only the bake's size is made small. The merged sums must equal one whole
// bake's bit for bit.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <regex>
#include <thread>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "deploy_files.h"
#include "server_process.h"
#include "test_support.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using namespace deploy_testing;
using testing::ScratchDir;
using testing::ServerProcess;

std::string Bytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// One pod of a Job: its container's command as a child process.
class Pod {
 public:
  // `claims`: claimName -> folder, shared by every pod; `scratch`: this
  // pod's own folder, for its emptyDirs and working directory.
  Pod(const YAML::Node& job, const std::map<std::string, fs::path>& claims, const fs::path& scratch,
      std::map<std::string, std::string> extra_env)
      : log_(scratch / "pod.log") {
    const YAML::Node spec = job["spec"]["template"]["spec"];
    const YAML::Node container = spec["containers"][0];
    // Where each mount path of the container lies here.
    std::map<std::string, fs::path> mounts;
    for (const auto& mount : container["volumeMounts"]) {
      const std::string name = mount["name"].as<std::string>();
      for (const auto& volume : spec["volumes"]) {
        if (volume["name"].as<std::string>() != name) continue;
        fs::path dir = volume["persistentVolumeClaim"]
                           ? claims.at(volume["persistentVolumeClaim"]["claimName"].as<std::string>())
                           : scratch / ("volume-" + name);
        fs::create_directories(dir);
        mounts[mount["mountPath"].as<std::string>()] = dir;
      }
    }
    // The image's ENV, then the container's (which wins, as in a pod).
    std::map<std::string, std::string> env = DockerEnv();
    for (const auto& [name, value] : EnvOf(container)) env[name] = value;
    for (auto& [name, value] : extra_env) env[name] = value;
    // Each value once, by the longest mount path it lies under (a folder
    // here may itself lie under /tmp).
    for (auto& [name, value] : env) {
      const std::string* best = nullptr;
      for (const auto& [path, dir] : mounts)
        if ((value == path || value.rfind(path + "/", 0) == 0) && (!best || path.size() > best->size())) best = &path;
      if (best) value = mounts[*best].string() + value.substr(best->size());
    }
    // /tmp is the pod's emptyDir; TMPDIR says so to the script, which
    // falls back to /tmp in a pod.
    if (mounts.count("/tmp")) env["TMPDIR"] = mounts["/tmp"].string();
    env["HOME"] = scratch.string();
    const fs::path bin = scratch / "bin";
    fs::create_directories(bin);
    fs::create_symlink(VISQ_SERVER_BINARY, bin / "visq-server");
    fs::create_symlink(VISQ_CLI_BINARY, bin / "visq");
    env["PATH"] = bin.string() + ":/usr/bin:/bin";

    std::vector<std::string> argv;
    for (const auto& word : container["command"]) argv.push_back(word.as<std::string>());
    for (const auto& word : container["args"]) argv.push_back(word.as<std::string>());
    std::vector<std::string> envp;
    for (const auto& [name, value] : env) envp.push_back(name + "=" + value);
    pid_ = ::fork();
    if (pid_ == 0) {
      // A process group of its own, so that a failed test stops the pod's
      // server with its shell.
      ::setpgid(0, 0);
      std::FILE* log = std::fopen(log_.c_str(), "w");
      if (log != nullptr) {
        ::dup2(fileno(log), STDOUT_FILENO);
        ::dup2(fileno(log), STDERR_FILENO);
      }
      if (::chdir(scratch.c_str()) != 0) ::_exit(126);
      std::vector<char*> a, e;
      for (auto& s : argv) a.push_back(s.data());
      for (auto& s : envp) e.push_back(s.data());
      a.push_back(nullptr);
      e.push_back(nullptr);
      ::execve(a[0], a.data(), e.data());
      ::_exit(127);
    }
  }
  ~Pod() {
    if (pid_ > 0) {
      ::kill(-pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
  }
  // The exit status, or -1 if it still runs after `limit` (then killed):
  // a guard against a hang, not a measurement.
  int Wait(std::chrono::seconds limit) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (pid_ > 0) {
      int status = 0;
      if (::waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      }
      if (std::chrono::steady_clock::now() > end) return -1;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return -1;
  }
  std::string Log() const { return Bytes(log_); }

 private:
  fs::path log_;
  pid_t pid_ = -1;
};

TEST(FarmBakeJob, ThePodsCommandsMergeToOneWholeBakeBitForBit) {
  const YAML::Node bake = FindManifest("Job", "visq-bake");
  const YAML::Node merge = FindManifest("Job", "visq-bake-merge");
  ASSERT_TRUE(bake && merge);
  const int pods = bake["spec"]["completions"].as<int>();
  ASSERT_GE(pods, 2);

  // The replicas' repository with the sample scenes, and a server on it
  // for the reference bake.
  ScratchDir repo, shards, scratch;
  auto reference = ServerProcess::Start({repo.path(), {"--seed-samples"}});
  ASSERT_NE(reference, nullptr);
  const std::map<std::string, fs::path> claims = {{"visq-scenes", repo.path()}, {"visq-bake-shards", shards.path()}};

  // The manifest's bake, at a test's size: a 32 x 32 atlas, 2 directions
  // a pod.
  const auto bake_env = EnvOf(bake["spec"]["template"]["spec"]["containers"][0]);
  const std::string flags =
      std::regex_replace(bake_env.at("VISQ_BAKE_FLAGS"), std::regex(R"(--resolution \d+)"), "--resolution 32");
  ASSERT_NE(flags.find("--resolution 32"), std::string::npos) << flags;
  const int per_pod = 2;
  const std::map<std::string, std::string> size = {{"VISQ_BAKE_FLAGS", flags},
                                                   {"VISQ_BAKE_DIRECTIONS_PER_POD", std::to_string(per_pod)}};

  std::vector<std::unique_ptr<Pod>> bakers;
  Pod merger(merge, claims, scratch.path() / "merge", {});
  for (int i = 0; i < pods; ++i) {
    auto env = size;
    env["JOB_COMPLETION_INDEX"] = std::to_string(i);
    bakers.push_back(std::make_unique<Pod>(bake, claims, scratch.path() / ("bake-" + std::to_string(i)), env));
  }
  for (int i = 0; i < pods; ++i) {
    const int code = bakers[i]->Wait(std::chrono::seconds(300));
    ASSERT_EQ(code, 0) << "bake pod " << i << ":\n" << bakers[i]->Log();
  }
  const fs::path out = shards.path() / fs::path(bake_env.at("VISQ_BAKE_SHARDS")).lexically_relative("/shards");
  std::string listing;
  for (const auto& entry : fs::directory_iterator(out)) listing += " " + entry.path().filename().string();
  ASSERT_EQ(merger.Wait(std::chrono::seconds(120)), 0) << merger.Log() << "\nin " << out << ":" << listing;

  for (int i = 0; i < pods; ++i) EXPECT_TRUE(fs::exists(out / ("shard-" + std::to_string(i) + ".vqp"))) << i;
  const auto summary = nlohmann::json::parse(Bytes(out / "merge.json"));
  EXPECT_EQ(summary["complete"], true) << summary;
  EXPECT_EQ(summary["total_directions"], pods * per_pod) << summary;
  EXPECT_GT(summary["estimated_texels"].get<int>(), 0) << "the comparison must not be between empty bakes";
  EXPECT_TRUE(fs::exists(out / "whole.npy"));

  // One whole bake of the same flags on one server.
  int status = 0;
  const fs::path whole = scratch.path() / "whole.vqp";
  const std::string output = testing::RunCommand(
      std::string(VISQ_CLI_BINARY) + " --server " + reference->address() + " obscurance " + flags + " --directions " +
          std::to_string(pods * per_pod) + " --partial-out " + whole.string() + " 2>&1",
      &status);
  ASSERT_EQ(status, 0) << output;
  EXPECT_EQ(Bytes(out / "whole.vqp"), Bytes(whole)) << "the farm's merged sums differ from one bake's";
}

}  // namespace
}  // namespace visq
