// What every queued job carries, whichever thread runs it (the GL thread's
// jobs are the ones that use it today): its priority, its deadline on the
// steady clock and its call's cancellation flag. The vocabulary the core
// and the transport compute deadlines in, below gpu/ (issue 48 §1).
#pragma once

#include <atomic>
#include <chrono>
#include <string_view>

#include "common/status.h"

namespace visq {

using SteadyTime = std::chrono::steady_clock::time_point;

// JobOptions::priority of a query someone waits on, and of long batch work.
inline constexpr int kInteractive = 0;
inline constexpr int kBatch = 10;

struct JobOptions {
  // Lower runs first; equal priorities run in arrival order. Small queries
  // use kInteractive so that long bakes (kBatch, split into steps) do not
  // starve them; nor do they starve a bake: after 8 jobs have overtaken
  // waiting work, the oldest waiting job runs.
  int priority = 0;
  SteadyTime deadline = SteadyTime::max();
  // Checked before the job starts, and by long jobs between steps.
  const std::atomic<bool>* cancelled = nullptr;
};

// OK while the job's call still wants it; CANCELLED or DEADLINE_EXCEEDED
// once it does not. Long jobs ask between passes, so a cancelled or expired
// request gives up the GL thread within one pass.
[[nodiscard]] inline Status StillWanted(const JobOptions& job, std::string_view where) {
  if (job.cancelled != nullptr && job.cancelled->load())
    return absl::CancelledError(absl::StrCat(AbslView(where), ": the call was cancelled"));
  if (std::chrono::steady_clock::now() > job.deadline)
    return absl::DeadlineExceededError(absl::StrCat(AbslView(where), ": the call's deadline passed"));
  return absl::OkStatus();
}

}  // namespace visq
