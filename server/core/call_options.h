// What every core query carries from its call: when its caller stops
// waiting, and whether it gave up. The transport fills it; the core turns
// it into job options (common/job_options.h) and chooses their priority itself (queries
// interactive, bakes batch), so a priority is a statement about the work,
// not about the protocol.
#pragma once

#include <atomic>
#include <memory>
#include <string>

#include "common/job_options.h"

namespace visq::core {

// The time a call spent on structures built on first use (the Embree BVH,
// the triangle index, the GPU buffers, local frames): building one, or
// waiting for another call's build of it. Reported apart from compute
// (Timing.build_ms). A call's waits follow one another, so they add up.
class BuildClock {
 public:
  void Add(double ms) { ms_.fetch_add(ms, std::memory_order_relaxed); }
  double ms() const { return ms_.load(std::memory_order_relaxed); }

 private:
  std::atomic<double> ms_{0.0};
};

struct CallOptions {
  // The call's deadline, and its flag, set when it is cancelled or drained.
  StopToken stop;
  // Shared by the copies of one call's options; null: not measured.
  std::shared_ptr<BuildClock> build_clock;
  // How the server's log names the call ("[r5 HiddenSampleMap]"), for the
  // core's own lines about it; empty: "[call]".
  std::string log_tag;

  double BuildMs() const { return build_clock ? build_clock->ms() : 0.0; }

  // GPU jobs for a query someone waits on, and for long batch work.
  JobOptions Job() const { return {kInteractive, stop}; }
  JobOptions BatchJob() const { return {kBatch, stop}; }
};

}  // namespace visq::core
