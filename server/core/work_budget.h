// The server's budget for memory held by work in flight: the answers being
// computed (bitmasks, grids, images) and their copies on the way out. A
// request reserves its estimate before it starts; it waits while others hold
// the budget (until its deadline or cancellation), and one that could never
// fit is RESOURCE_EXHAUSTED at once. Scenes, GPU buffers and caches have
// bounds of their own (--max-scene-bytes, --light-cache-bytes).
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <optional>
#include <string>

#include "common/job_options.h"
#include "common/status.h"

namespace visq::core {

// What a streamed answer may hold written but not yet sent within its own
// reservation (the estimates of streamed answers count it; the server's
// --stream-queue-bytes may lower it). Beyond it its writer
// (service/reactors.h, ProducedStreamReactor) parks each further message in
// the budget's spare memory (TryReserveSpare), so that the work ends and
// frees its worker while the reader catches up, and makes the work wait
// where no spare memory is left: a slow reader holds back memory the
// budget has room for, else the work, never more.
inline constexpr uint64_t kStreamedAnswerQueueBytes = uint64_t{64} << 20;

class WorkMemoryBudget {
 public:
  // 0: half of the memory this process may use, the smaller of physical
  // memory and its cgroup's limit (resource_limits::ProcessMemoryLimit).
  explicit WorkMemoryBudget(uint64_t capacity_bytes);
  WorkMemoryBudget(const WorkMemoryBudget&) = delete;
  WorkMemoryBudget& operator=(const WorkMemoryBudget&) = delete;

  // Held bytes, returned when it goes.
  class Reservation {
   public:
    Reservation() = default;
    Reservation(Reservation&& other) noexcept;
    Reservation& operator=(Reservation&& other) noexcept;
    ~Reservation();

    // Moves `bytes` of this reservation (all of it, at most) into a lasting
    // one of their own, for a part of the work the server keeps after the
    // call (a bake's updater, until the scene's next whole bake or unload).
    // What lasting reservations hold is not waited for: a request that
    // could fit only once they go is refused at once.
    [[nodiscard]] Reservation KeepLasting(uint64_t bytes);
    uint64_t bytes() const { return bytes_; }

   private:
    friend class WorkMemoryBudget;
    Reservation(WorkMemoryBudget* budget, uint64_t bytes, bool lasting = false)
        : budget_(budget), bytes_(bytes), lasting_(lasting) {}
    WorkMemoryBudget* budget_ = nullptr;
    uint64_t bytes_ = 0;
    bool lasting_ = false;
  };

  // `what` names the request's part that needs the memory ("width x height
  // x samples"), for the error.
  [[nodiscard]] StatusOr<Reservation> Reserve(uint64_t bytes, const std::string& what, const JobOptions& job);

  // `bytes` at once if, with them, at least a quarter of the capacity stays
  // free for the reservations of calls still to start; else nothing, without
  // waiting. For answers already made that wait for their reader.
  [[nodiscard]] std::optional<Reservation> TryReserveSpare(uint64_t bytes);

  // Releasing at least this much returns the process's free memory to the
  // system (malloc_trim).
  static constexpr uint64_t kTrimAfterBytes = uint64_t{64} << 20;

  uint64_t capacity() const { return capacity_; }
  // Where capacity() came from, for the start-up log: "as given", or
  // "half of cgroup v2 memory.max /sys/fs/cgroup/memory.max (34359738368 bytes)".
  const std::string& capacity_source() const { return capacity_source_; }
  uint64_t in_use() const;
  uint64_t peak() const;

 private:
  void Release(uint64_t bytes, bool lasting);

  uint64_t capacity_ = 0;
  std::string capacity_source_;
  mutable std::mutex mutex_;
  std::condition_variable released_;
  uint64_t in_use_ = 0;
  uint64_t lasting_ = 0;  // of in_use_, held by lasting reservations
  uint64_t peak_ = 0;
};

}  // namespace visq::core
