// The calls in flight, so that the end of the server's drain reaches their
// work: a SIGTERM stops accepting calls at once, lets those in flight run
// for the drain period, then raises every one's cancellation flag, which
// the core polls between GL jobs, ray batches and points; the calls then
// answer UNAVAILABLE (retry on another replica) before gRPC's own cut-off.
#pragma once

#include <atomic>
#include <cstddef>
#include <functional>
#include <mutex>
#include <map>

#include "common/status.h"

namespace visq::service {

class CallRegistry {
 public:
  // A call's flag, raised at once when the drain has already ended.
  // `computes`: the call uses the compute workers or the GL thread (every
  // query), not only metadata; only such calls keep the server busy for
  // the activity listener.
  void Add(std::atomic<bool>* cancelled, bool computes = true);
  // Before the flag goes (the call's reactor is deleted).
  void Remove(std::atomic<bool>* cancelled);
  // A call that the drain leaves to run out (an upload) but that keeps the
  // server busy all the same.
  void WorkBegan();
  void WorkEnded();
  // Told of every call beginning (true) and ending (false), before the
  // server accepts calls: the core's idle exploration waits for quiet.
  void SetActivityListener(std::function<void(bool began)> listener) { activity_ = std::move(listener); }
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
  std::map<std::atomic<bool>*, bool> calls_;  // each call's flag, and whether it computes
  std::atomic<bool> drain_ended_{false};
  std::function<void(bool began)> activity_;
};

}  // namespace visq::service
