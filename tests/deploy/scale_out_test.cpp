// Scale-out on loopback: two visq-server replicas sharing one scene
// repository behind nginx, which hashes the x-visq-scene header the client
// sends. Queries for a scene keep reaching the replica that holds it,
// scenes spread over both, and when one replica dies the other takes its
// scenes over from the shared repository.
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <fstream>
#include <map>
#include <set>
#include <thread>

#include <gtest/gtest.h>

#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using testing::ScratchDir;
using testing::ServerProcess;

int FreeLoopbackPort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = 0;
  ::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address));
  socklen_t length = sizeof(address);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
  ::close(fd);
  return ntohs(address.sin_port);
}

// nginx in the foreground with its own prefix, stopped with the object.
class Nginx {
 public:
  Nginx(const fs::path& prefix, int port, const std::vector<std::string>& replicas) : prefix_(prefix) {
    std::string command = std::string(VISQ_SOURCE_DIR) + "/deploy/nginx/render.sh " + prefix.string() +
                          " 127.0.0.1:" + std::to_string(port);
    for (const auto& r : replicas) command += " " + r;
    command += " > " + (prefix / "nginx.conf").string();
    ok_ = std::system(command.c_str()) == 0;
    if (!ok_) return;
    pid_ = ::fork();
    if (pid_ == 0) {
      const std::string conf = (prefix / "nginx.conf").string(), dir = prefix.string();
      ::execl("/usr/sbin/nginx", "nginx", "-p", dir.c_str(), "-c", conf.c_str(), "-g", "daemon off;",
              static_cast<char*>(nullptr));
      ::_exit(127);
    }
  }
  ~Nginx() {
    if (pid_ > 0) {
      ::kill(pid_, SIGQUIT);
      int status = 0;
      ::waitpid(pid_, &status, 0);
    }
  }
  bool ok() const { return ok_ && pid_ > 0; }
  std::string ErrorLog() const {
    std::ifstream in(prefix_ / "error.log");
    std::stringstream text;
    text << in.rdbuf();
    return text.str();
  }

 private:
  fs::path prefix_;
  bool ok_ = false;
  pid_t pid_ = -1;
};

TEST(ScaleOut, ScenesStayOnOneReplicaSpreadOverBothAndFailOver) {
  if (!fs::exists("/usr/sbin/nginx")) GTEST_FAIL() << "nginx is not installed (deploy/install-deps.sh installs it)";
  ScratchDir repo, nginx_dir, files;
  auto replica_a = ServerProcess::Start({repo.path(), {"--no-preload", "--server-id", "replica-a"}});
  auto replica_b = ServerProcess::Start({repo.path(), {"--no-preload", "--server-id", "replica-b"}});
  ASSERT_NE(replica_a, nullptr);
  ASSERT_NE(replica_b, nullptr);
  const int port = FreeLoopbackPort();
  Nginx nginx(nginx_dir.path(), port, {replica_a->address(), replica_b->address()});
  ASSERT_TRUE(nginx.ok());
  client::Client client({.address = "127.0.0.1:" + std::to_string(port), .deadline = std::chrono::seconds(20)});
  ASSERT_TRUE(client.WaitUntilServing(std::chrono::seconds(30)).ok()) << nginx.ErrorLog();

  // Sixteen scenes uploaded through the router: each lands on the replica
  // its name hashes to, and is stored in the shared repository.
  Scene scene = MakeCornellBox();
  const fs::path file = files.path() / "box.glb";
  ASSERT_TRUE(WriteGltfFile(scene, file).ok());
  std::map<std::string, std::string> home;
  for (int i = 0; i < 16; ++i) {
    const std::string name = "scene" + std::to_string(i);
    auto info = client.UploadScene(file, name);
    ASSERT_TRUE(info.ok()) << name << ": " << info.status() << "\n" << nginx.ErrorLog();
    home[name] = client.last_server_id();
    ASSERT_FALSE(home[name].empty()) << "no x-visq-server-id in the response";
  }

  // Every query for a scene reaches its home replica, where it is resident.
  std::set<std::string> replicas_used;
  for (const auto& [name, replica] : home) {
    for (int repeat = 0; repeat < 3; ++repeat) {
      auto info = client.GetScene(name);
      ASSERT_TRUE(info.ok()) << name << " on " << client.last_server_id() << ": " << info.status();
      EXPECT_EQ(client.last_server_id(), replica) << name;
    }
    replicas_used.insert(replica);
  }
  EXPECT_EQ(replicas_used.size(), 2u) << "16 scenes should spread over both replicas";

  // Kill the home of scene0: the router retries on the other replica, which
  // loads the scene from the shared repository.
  const std::string victim = home["scene0"];
  (victim == "replica-a" ? replica_a : replica_b)->Kill();
  StatusOr<v1::SceneInfo> after = absl::UnavailableError("not tried");
  for (int attempt = 0; attempt < 5 && !after.ok(); ++attempt) {
    after = client.GetScene("scene0", false, /*load_if_stored=*/true);
    if (!after.ok()) std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  ASSERT_TRUE(after.ok()) << after.status() << "\n" << nginx.ErrorLog();
  EXPECT_NE(client.last_server_id(), victim);
  EXPECT_EQ(after->triangle_count(), scene.TriangleCount());
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

TEST(ScaleOut, ShardedBakeOverTwoReplicasEqualsTheSingleServerBakeBitForBit) {
  ScratchDir repo;
  auto replica_a = ServerProcess::Start({repo.path(), {"--seed-samples", "--server-id", "replica-a"}});
  auto replica_b = ServerProcess::Start({repo.path(), {"--server-id", "replica-b"}});
  ASSERT_NE(replica_a, nullptr);
  ASSERT_NE(replica_b, nullptr);
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_resolution(32);
  request.set_d_max(1.0);
  request.set_seed(11);
  request.set_first_direction(0);
  request.set_direction_count(8);
  request.set_total_directions(8);
  request.set_partial_only(true);

  client::Client single({.address = replica_a->address()});
  auto whole = single.ComputeObscurances(request, nullptr);
  ASSERT_TRUE(whole.ok()) << whole.status();
  auto sharded = client::ShardedBake({replica_a->address(), replica_b->address()}, client::ClientOptions{}, request,
                                     /*shards=*/4);
  ASSERT_TRUE(sharded.ok()) << sharded.status();
  EXPECT_EQ(sharded->partial.sums, whole->partial.sums);
  EXPECT_EQ(sharded->partial.counts, whole->partial.counts);
  EXPECT_EQ(sharded->partial.DirectionCount(), 8u);
  uint64_t total = 0;
  for (uint64_t c : whole->partial.counts) total += c;
  EXPECT_GT(total, 0u) << "the comparison must not be between empty bakes";
}

}  // namespace
}  // namespace visq
