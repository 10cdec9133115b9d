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

#include "common/gpu_device_info.h"
#include "common/job_options.h"
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

// The device record, the job options and the deadline type are lib/common's
// (common/gpu_device_info.h, common/job_options.h): the core and the
// transport name them without naming gpu/.
using DeviceInfo = ::visq::GpuDeviceInfo;
using ::visq::JobOptions;
using ::visq::kBatch;
using ::visq::kInteractive;
using ::visq::SteadyTime;
using ::visq::StopToken;
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
