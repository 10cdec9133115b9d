#include "postgres_cluster.h"

#include <netinet/in.h>
#include <pwd.h>
#include <sys/wait.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <sstream>

namespace visq::testing {
namespace fs = std::filesystem;
namespace {

// The newest Debian PostgreSQL server installed (its initdb and pg_ctl).
fs::path ServerBinaries() {
  fs::path best;
  int best_major = 0;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator("/usr/lib/postgresql", ec)) {
    const int major = std::atoi(entry.path().filename().c_str());
    if (major > best_major && fs::exists(entry.path() / "bin" / "initdb") && fs::exists(entry.path() / "bin" / "pg_ctl")) {
      best_major = major;
      best = entry.path() / "bin";
    }
  }
  return best;
}

// A port free on loopback at this moment.
int FreePort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof(address);
  int port = 0;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) == 0)
    port = ntohs(address.sin_port);
  ::close(fd);
  return port;
}

std::string ReadLog(const fs::path& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

bool PostgresCluster::Installed() { return !ServerBinaries().empty(); }

std::unique_ptr<PostgresCluster> PostgresCluster::Start(std::string* why) {
  std::unique_ptr<PostgresCluster> cluster(new PostgresCluster());
  cluster->bin_ = ServerBinaries();
  if (cluster->bin_.empty()) {
    *why = "PostgreSQL is not installed (no /usr/lib/postgresql/<major>/bin/initdb; deploy/install-deps.sh installs it)";
    return nullptr;
  }
  if (::geteuid() == 0) {
    // The server refuses root: the cluster's folder becomes nobody's.
    const passwd* nobody = ::getpwnam("nobody");
    if (nobody == nullptr || ::chown(cluster->dir_.path().c_str(), nobody->pw_uid, nobody->pw_gid) != 0) {
      *why = "running as root and cannot hand the cluster's folder to 'nobody'";
      return nullptr;
    }
    cluster->as_user_ = "runuser -u nobody -- ";
  }
  const fs::path data = cluster->dir_.path() / "data";
  // initdb's output is redirected by this process's shell; the server's
  // log is made by pg_ctl, as the cluster's user.
  const fs::path initdb_log = cluster->dir_.path() / "initdb.log";
  const fs::path log = cluster->dir_.path() / "server.log";
  if (cluster->Run("'" + (cluster->bin_ / "initdb").string() + "' -D '" + data.string() +
                   "' -U visq -A trust --no-sync -E UTF8 --locale=C > '" + initdb_log.string() + "' 2>&1") != 0) {
    *why = "initdb failed: " + ReadLog(initdb_log);
    return nullptr;
  }
  // Loopback TCP only, its socket folder its own; fsync off: the test kills
  // visq's servers, never this one.
  for (int attempt = 0; attempt < 3 && !cluster->running_; ++attempt) {
    cluster->port_ = FreePort();
    const std::string options = "-c listen_addresses=127.0.0.1 -p " + std::to_string(cluster->port_) +
                                " -k '" + cluster->dir_.path().string() + "' -c fsync=off -c max_connections=50";
    cluster->running_ = cluster->Run("'" + (cluster->bin_ / "pg_ctl").string() + "' -D '" + data.string() + "' -l '" +
                                     log.string() + "' -o \"" + options + "\" -w -t 60 start > /dev/null 2>&1") == 0;
  }
  if (!cluster->running_) {
    *why = "pg_ctl start failed: " + ReadLog(log);
    return nullptr;
  }
  return cluster;
}

PostgresCluster::~PostgresCluster() {
  if (running_)
    Run("'" + (bin_ / "pg_ctl").string() + "' -D '" + (dir_.path() / "data").string() +
        "' -m immediate -w stop > /dev/null 2>&1");
}

std::string PostgresCluster::Uri(const std::string& database) const {
  return "postgresql://visq@127.0.0.1:" + std::to_string(port_) + "/" + database;
}

bool PostgresCluster::CreateDatabase(const std::string& name) const {
  return Run("'" + (bin_ / "createdb").string() + "' -h 127.0.0.1 -p " + std::to_string(port_) + " -U visq '" + name +
             "' > /dev/null 2>&1") == 0;
}

int PostgresCluster::Run(const std::string& command) const {
  const int status = std::system((as_user_ + command).c_str());
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

}  // namespace visq::testing
