// The GPU's public face: one worker thread that owns the EGL context and runs
// every GL command. Nothing outside gpu/ sees a GL type; callers hand the
// worker jobs (the algorithm entry points in gpu/ do this) and wait for them.
#pragma once

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "common/job_timing.h"
#include "common/status.h"

namespace visq::gpu {

struct GpuOptions {
  // "auto": an EGL device that is not a software renderer (an NVIDIA GPU),
  // else Mesa surfaceless (llvmpipe). "surfaceless": Mesa only. "device:N":
  // the N-th EGL device. Empty: $VISQ_EGL_DEVICE, else "auto" (a choice
  // made here is never overridden by the environment).
  std::string device;
  // Route KHR_debug messages to the log and check glGetError after steps.
  bool debug = false;
  // Fault injection, for tests of the recovery path: the N-th job (1-based,
  // counting every job including the start-up self-test) is treated as if
  // the GPU had reset during it. 0: never.
  uint64_t lose_context_at_job = 0;
};

struct DeviceInfo {
  std::string egl_platform;  // "device" or "surfaceless"
  std::string egl_device;    // DRM node or extension summary
  std::string gl_vendor;
  std::string gl_renderer;
  std::string gl_version;
  bool software = false;     // llvmpipe or another CPU rasterizer
};

using SteadyTime = std::chrono::steady_clock::time_point;

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

inline constexpr int kInteractive = 0;
inline constexpr int kBatch = 10;

using ::visq::JobTiming;

class GpuWorker {
 public:
  // Starts the GL thread and waits until it has a context (or failed to get
  // one: the error names the EGL call and error).
  [[nodiscard]] static StatusOr<std::unique_ptr<GpuWorker>> Start(const GpuOptions& options);
  ~GpuWorker();  // finishes queued jobs, then destroys the context on its thread
  GpuWorker(const GpuWorker&) = delete;
  GpuWorker& operator=(const GpuWorker&) = delete;

  const DeviceInfo& device() const;
  size_t queue_depth() const;
  // Starts at 1; +1 for every context made after a loss.
  uint64_t context_generation() const;
  // Contexts lost since start.
  uint64_t contexts_lost() const;

  // Runs `body` on the GL thread and waits for it. A job whose deadline has
  // passed or that was cancelled before it starts does not run
  // (DEADLINE_EXCEEDED / CANCELLED). A GL error raised by the job fails it
  // with INTERNAL; the next job starts from a clean error state. If the
  // context is lost during the job (a GPU reset), the job fails with
  // INTERNAL, the worker makes a new context and bumps context_generation():
  // GPU-resident data from earlier generations is gone and is rebuilt by
  // whoever cached it (they compare generations before use).
  [[nodiscard]] Status Run(const JobOptions& options, std::function<Status()> body,
                           JobTiming* timing = nullptr);
  // Queues `body` without waiting (GL object deletion from other threads).
  void Post(std::function<void()> body);

  class Impl;

 private:
  explicit GpuWorker(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Draws a known picture and reads it back: proves at start-up that the chosen
// device really rasterizes, not just that a context exists.
[[nodiscard]] Status RunSelfTest(GpuWorker& worker);

}  // namespace visq::gpu
