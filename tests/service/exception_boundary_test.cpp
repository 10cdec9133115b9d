// An exception from a call's work is that call's failure, never the
// process's end: the executor's threads outlive a task that throws, and
// CatchExceptions turns what the work throws into INTERNAL.
#include <atomic>
#include <chrono>
#include <fstream>
#include <ios>
#include <iterator>
#include <new>
#include <stdexcept>
#include <string>
#include <thread>

#include <gtest/gtest.h>

#include "service/exception_boundary.h"
#include "service/executor.h"

namespace visq::service {
namespace {

TEST(ExceptionBoundary, AThrowingTaskLeavesTheExecutorServing) {
  std::atomic<int> ran{0};
  {
    Executor executor(1);
    executor.Post([] { throw std::runtime_error("a task that throws"); });
    executor.Post([] { throw 42; });
    executor.Post([&] { ++ran; });
  }  // runs what is queued, then joins
  EXPECT_EQ(ran.load(), 1);
}

TEST(ExceptionBoundary, WhatTheWorkThrowsIsAnInternalStatus) {
  // libstdc++ throws std::__ios_failure reading a folder through an ifstream.
  const Status folder = CatchExceptions("req-1", "LoadScene", []() -> Status {
    std::ifstream in("/");
    in.exceptions(std::ios::badbit);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    return absl::OkStatus();
  });
  EXPECT_EQ(folder.code(), absl::StatusCode::kInternal) << folder;

  const StatusOr<int> allocation =
      CatchExceptions("req-2", "GetScene", []() -> StatusOr<int> { throw std::bad_alloc(); });
  ASSERT_FALSE(allocation.ok());
  EXPECT_EQ(allocation.status().code(), absl::StatusCode::kInternal);
  EXPECT_NE(allocation.status().message().find("bad_alloc"), std::string::npos) << allocation.status();

  const Status odd = CatchExceptions("req-3", "GetStats", []() -> Status { throw 7; });
  EXPECT_EQ(odd.code(), absl::StatusCode::kInternal);

  const StatusOr<int> fine = CatchExceptions("req-4", "GetStats", []() -> StatusOr<int> { return 5; });
  ASSERT_TRUE(fine.ok());
  EXPECT_EQ(*fine, 5);
}

}  // namespace
}  // namespace visq::service
