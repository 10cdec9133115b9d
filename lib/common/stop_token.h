// The one way work under way learns that it should stop: its call was
// cancelled (or the server drains, which cancels every call), or its
// deadline passed. The transport makes one per call; the core hands it to
// every loop and GL job it starts, and each asks it between its steps.
// Structures shared by calls (a BVH, a triangle index) are stopped by the
// server's own flag, not by the call that happened to start them.
#pragma once

#include <atomic>
#include <chrono>
#include <string_view>

#include "common/status.h"

namespace visq {

using SteadyTime = std::chrono::steady_clock::time_point;

struct StopToken {
  // Set when the call is cancelled or the server drains; null: never.
  const std::atomic<bool>* cancelled = nullptr;
  // On the steady clock; max: none.
  SteadyTime deadline = SteadyTime::max();

  // Whether anything can stop the work at all (such work need not ask).
  bool CanStop() const { return cancelled != nullptr || deadline != SteadyTime::max(); }

  bool Stopped() const {
    return (cancelled != nullptr && cancelled->load(std::memory_order_relaxed)) ||
           (deadline != SteadyTime::max() && std::chrono::steady_clock::now() > deadline);
  }

  // OK while the work is still wanted; CANCELLED or DEADLINE_EXCEEDED, naming
  // `where`, once it is not.
  [[nodiscard]] Status Check(std::string_view where) const {
    if (cancelled != nullptr && cancelled->load(std::memory_order_relaxed))
      return absl::CancelledError(absl::StrCat(AbslView(where), ": the call was cancelled"));
    if (deadline != SteadyTime::max() && std::chrono::steady_clock::now() > deadline)
      return absl::DeadlineExceededError(absl::StrCat(AbslView(where), ": the call's deadline passed"));
    return absl::OkStatus();
  }
};

}  // namespace visq
