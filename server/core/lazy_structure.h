// Structures a resident scene builds on first use (the Embree BVH, the exact
// method's triangle index, the GPU buffers): each is built once, on a thread
// of its own, and no lock that anything else takes is held while it builds.
// Concurrent first users wait for the one build, each only until its own
// deadline or cancellation; a build that fails leaves the structure unbuilt,
// so the next user starts it again. What is built is published for readers
// that never wait (bytes(), Built()): metadata calls report what exists and
// never wait behind a build.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/job_timing.h"
#include "common/status.h"
#include "core/call_options.h"

namespace visq::core {

// Runs builds, each on a thread of its own, and when destroyed asks those
// still running to stop (stop()) and waits for them. A thread per build
// rather than a pool: builds are rare (once per structure and scene
// version), and a pool of N would hold a small scene's build behind N large
// ones. Threads that finished are joined when the next build starts.
class StructureBuilds {
 public:
  StructureBuilds() = default;
  ~StructureBuilds();
  StructureBuilds(const StructureBuilds&) = delete;
  StructureBuilds& operator=(const StructureBuilds&) = delete;

  void Start(std::function<void()> build);
  // Says stop once the owner shuts down: long builds ask it and give up.
  StopToken stop() const { return {&stopping_}; }

 private:
  struct Running {
    std::thread thread;
    std::shared_ptr<std::atomic<bool>> done;
  };
  std::mutex mutex_;
  std::vector<Running> running_;
  std::atomic<bool> stopping_{false};
};

template <typename T>
class LazyStructure {
 public:
  using Result = StatusOr<std::shared_ptr<T>>;
  struct Build {
    std::function<Result()> make;            // runs on the build's own thread
    std::function<uint64_t(const T&)> bytes;  // what the built structure holds
    // False for a built structure that can no longer serve (GPU buffers of
    // a context lost since): it is built again. Empty: always usable.
    std::function<bool(const T&)> usable;
  };

  // The structure if it is built and usable, else null. Never waits.
  std::shared_ptr<T> Built(const Build& build) const {
    std::lock_guard lock(state_->mutex);
    return UsableLocked(build) ? state_->value : nullptr;
  }
  // Bytes of the built structure, 0 before. Lock-free.
  uint64_t bytes() const { return state_->bytes.load(std::memory_order_acquire); }
  bool building() const {
    std::lock_guard lock(state_->mutex);
    return state_->building;
  }

  // Starts the build unless the structure is built or being built; does
  // not wait (warming a scene at load).
  void Start(StructureBuilds& builds, const Build& build) {
    std::lock_guard lock(state_->mutex);
    if (!UsableLocked(build) && !state_->building) StartLocked(builds, build);
  }

  // The structure: at once when built; else after the build this call
  // starts or joins. CANCELLED or DEADLINE_EXCEEDED as soon as the call
  // stops wanting it (the build goes on for the next user). The time spent
  // waiting goes to the call's build clock.
  Result Get(StructureBuilds& builds, const CallOptions& call, const Build& build, const char* what) {
    std::unique_lock lock(state_->mutex);
    if (UsableLocked(build)) return state_->value;
    const auto start = std::chrono::steady_clock::now();
    struct Charge {
      const CallOptions& call;
      std::chrono::steady_clock::time_point start;
      ~Charge() {
        if (call.build_clock) call.build_clock->Add(MillisecondsSince(start));
      }
    } charge{call, start};
    if (!state_->building) StartLocked(builds, build);
    const uint64_t awaited = state_->started;
    // A cancellation is a flag nobody signals: look at it every 20 ms.
    constexpr auto kPoll = std::chrono::milliseconds(20);
    while (state_->finished < awaited) {
      VISQ_RETURN_IF_ERROR(call.stop.Check(absl::StrCat("waiting for the ", what, " build")));
      state_->done.wait_until(lock, std::min(call.stop.deadline, std::chrono::steady_clock::now() + kPoll));
    }
    if (UsableLocked(build)) return state_->value;
    return state_->failure;
  }

 private:
  struct State {
    std::mutex mutex;  // held only to read or publish, never during a build
    std::condition_variable done;
    std::shared_ptr<T> value;
    bool building = false;
    uint64_t started = 0;   // builds started, and
    uint64_t finished = 0;  // finished, one at a time
    Status failure;         // of the last build that finished
    std::atomic<uint64_t> bytes{0};
  };

  bool UsableLocked(const Build& build) const {
    return state_->value && (!build.usable || build.usable(*state_->value));
  }

  void StartLocked(StructureBuilds& builds, const Build& build) {
    state_->building = true;
    ++state_->started;
    // The thread holds the state, not this object: a scene unloaded during
    // its build is freed when the build ends.
    builds.Start([state = state_, build] {
      Result result = build.make();
      std::lock_guard lock(state->mutex);
      state->building = false;
      ++state->finished;
      if (result.ok()) {
        state->value = *std::move(result);
        state->bytes.store(build.bytes ? build.bytes(*state->value) : 0, std::memory_order_release);
        state->failure = absl::OkStatus();
      } else {
        state->failure = result.status();
      }
      state->done.notify_all();
    });
  }

  std::shared_ptr<State> state_ = std::make_shared<State>();
};

}  // namespace visq::core
