// A PostgreSQL cluster of its own for a test: initdb in a scratch folder,
// listening on a free loopback port, stopped and removed with the object.
// Debian's server binaries (/usr/lib/postgresql/<major>/bin); PostgreSQL
// refuses to run as root, so under uid 0 it runs as `nobody` (runuser).
#pragma once

#include <filesystem>
#include <memory>
#include <string>

#include "test_support.h"

namespace visq::testing {

class PostgresCluster {
 public:
  // Whether Debian's PostgreSQL server is installed (a test skips, saying
  // so, where it is not).
  static bool Installed();
  // nullptr with `why` set when it does not start.
  static std::unique_ptr<PostgresCluster> Start(std::string* why);
  ~PostgresCluster();
  PostgresCluster(const PostgresCluster&) = delete;
  PostgresCluster& operator=(const PostgresCluster&) = delete;

  // postgresql://visq@127.0.0.1:<port>/<database>
  std::string Uri(const std::string& database = "postgres") const;
  // Makes a database (createdb); false on failure.
  bool CreateDatabase(const std::string& name) const;

 private:
  PostgresCluster() = default;
  // Runs a PostgreSQL program as the cluster's user; its exit status.
  int Run(const std::string& command) const;

  ScratchDir dir_;
  std::filesystem::path bin_;
  std::string as_user_;  // "runuser -u nobody -- " under root, else empty
  int port_ = 0;
  bool running_ = false;
};

}  // namespace visq::testing
