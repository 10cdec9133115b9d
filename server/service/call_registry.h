// The calls in flight, so that the end of the server's drain reaches their
// work: a SIGTERM stops accepting calls at once, lets those in flight run
// for the drain period, then raises every one's cancellation flag, which
// the core polls between GL jobs, ray batches and points; the calls then
// answer UNAVAILABLE (retry on another replica) before gRPC's own cut-off.
#pragma once

#include <atomic>
#include <cstddef>
#include <mutex>
#include <set>

#include "common/status.h"

namespace visq::service {

class CallRegistry {
 public:
  // A call's flag, raised at once when the drain has already ended.
  void Add(std::atomic<bool>* cancelled);
  // Before the flag goes (the call's reactor is deleted).
  void Remove(std::atomic<bool>* cancelled);
  // Raises every registered flag, and every one added later.
  // Returns how many calls were told to stop.
  size_t EndDrain();
  bool drain_ended() const { return drain_ended_.load(); }
  size_t in_flight() const;
  // What a call that stopped answers: its own status, or UNAVAILABLE once
  // the drain has ended and the stop was the drain's.
  Status Final(Status status) const;

 private:
  mutable std::mutex mutex_;
  std::set<std::atomic<bool>*> calls_;
  std::atomic<bool> drain_ended_{false};
};

}  // namespace visq::service
