// What every core query carries from its call: when its caller stops
// waiting, and whether it gave up. The transport fills it; the core turns
// it into GPU job options and chooses their priority itself (queries
// interactive, bakes batch), so a priority is a statement about the work,
// not about the protocol.
#pragma once

#include <atomic>

#include "visq/gpu/gpu_worker.h"

namespace visq {

struct CallOptions {
  gpu::SteadyTime deadline = gpu::SteadyTime::max();
  const std::atomic<bool>* cancelled = nullptr;  // set when the call is cancelled or drained

  // OK while the call still wants its answer (see gpu::StillWanted).
  [[nodiscard]] Status StillWanted(std::string_view where) const { return gpu::StillWanted(Job(), where); }
  bool Stopped() const {
    return (cancelled != nullptr && cancelled->load()) || gpu::SteadyTime::clock::now() > deadline;
  }

  // GPU jobs for a query someone waits on, and for long batch work.
  gpu::JobOptions Job() const { return {gpu::kInteractive, deadline, cancelled}; }
  gpu::JobOptions BatchJob() const { return {gpu::kBatch, deadline, cancelled}; }
};

}  // namespace visq
