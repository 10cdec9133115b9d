// One real visq-server (sample scenes seeded) shared by every test of a
// suite, and a fresh client per test: starting a server per test would cost
// a GL context and a repository load each time.
#pragma once

#include <filesystem>
#include <memory>

#include <gtest/gtest.h>

#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq::testing {

// CRTP: each suite gets its own server. A suite that needs files in the
// repository before the server starts defines a static
// PrepareRepository(const std::filesystem::path&).
template <typename Suite>
class SharedServerSuite : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    repo_ = new ScratchDir();
    Suite::PrepareRepository(repo_->path());
    server_ = ServerProcess::Start({repo_->path(), {"--seed-samples"}}).release();
  }
  static void TearDownTestSuite() {
    delete server_;
    delete repo_;
    server_ = nullptr;
    repo_ = nullptr;
  }
  static void PrepareRepository(const std::filesystem::path&) {}

  void SetUp() override {
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<client::Client>(client::ClientOptions{.address = server_->address()});
  }

  inline static ScratchDir* repo_ = nullptr;
  inline static ServerProcess* server_ = nullptr;
  std::unique_ptr<client::Client> client_;
};

}  // namespace visq::testing
