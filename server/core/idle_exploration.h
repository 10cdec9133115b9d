// Probes that no request could pay for, run while the server is idle.
//
// The server's choice among methods that give the same answer (ChooseFastest)
// learns a method's cost on a scene by probing it: a small run of the
// request. Inside a request a probe costs its caller up to a share of the
// request, and a method's first probe pays one-time costs besides (a raster
// program compiled, a Hough table built: tens of ms on llvmpipe), so a small
// request that probes can take twice its time or more. A probe too large
// for a request's share is handed here instead: it runs once no call has
// been in flight for a quiet spell, stops the moment a call arrives (between
// GL jobs, ray batches or directions, like any call's work), and is run
// again at the next quiet spell. What it measures goes into the same cost
// model, so the next request weighs the method without paying for it.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <string>
#include <thread>

#include "core/accuracy_planner.h"

namespace visq::core {

struct IdleExplorationOptions {
  // How long no call must have been in flight before a probe starts: calls
  // that come in a burst (a client's loop) are not interleaved with probes.
  double quiet_ms = 100.0;
  // The most one probe may take; past it, it is recorded as cut at this
  // budget (CostModel::RecordCutProbe), so a method slow here is not probed
  // again for every request.
  double probe_budget_ms = 2000.0;
  // Options waiting for idle time; the oldest go first, and past this many
  // the oldest are dropped (each request can offer a few).
  size_t max_pending = 64;
};

class IdleExplorer {
 public:
  IdleExplorer(CostModel& model, IdleExplorationOptions options);
  // Stops a probe that is running, drops what waits and joins.
  ~IdleExplorer();
  IdleExplorer(const IdleExplorer&) = delete;
  IdleExplorer& operator=(const IdleExplorer&) = delete;

  // A call that computes began or ended (the service leaves metadata calls
  // out). A call beginning stops a probe that is running.
  void CallBegan();
  void CallEnded();

  // Runs `option`'s probes from `first_probe` on at the next quiet spell.
  // The option's probes must own what they run on (probes_outlive_the_call);
  // one left for the same cost series replaces an earlier one. A series
  // left after kMostPreemptions is not taken again for kRestAfterOutlasting.
  void Offer(EqualAnswerOption option, size_t first_probe);

  // A probe stopped this many times outlasts this server's quiet spells:
  // each try cost the call that stopped it the GL job or ray batch in
  // flight, so it is dropped, recorded as cut at the longest it ran.
  static constexpr int kMostPreemptions = 2;
  static constexpr std::chrono::seconds kRestAfterOutlasting{60};

  struct Figures {
    uint64_t probes_run = 0;        // finished: measured, or cut at the budget
    uint64_t probes_preempted = 0;  // stopped by a call arriving, and waiting again
    uint64_t probes_dropped = 0;    // over max_pending, failed, or stopped kMostPreemptions times
    uint32_t pending = 0;
    double total_ms = 0.0;  // spent probing, preempted probes included
  };
  Figures figures() const;

 private:
  struct Pending {
    EqualAnswerOption option;
    size_t first_probe = 0;
    int preempted = 0;       // times a call stopped it
    double longest_ms = 0.0;  // the longest it ran before one did
  };
  void Loop();
  // Whether a probe may start now (the lock held); else how long to wait.
  bool QuietLocked(std::chrono::steady_clock::time_point now, std::chrono::steady_clock::duration& wait) const;

  CostModel& model_;
  const IdleExplorationOptions options_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<Pending> pending_;
  // Series whose probe outlasted the quiet spells, and until when they rest.
  std::map<std::string, std::chrono::steady_clock::time_point> resting_until_;
  int calls_in_flight_ = 0;
  std::chrono::steady_clock::time_point last_call_end_ = std::chrono::steady_clock::now();
  // The running probe's cancellation flag: raised by a call beginning or
  // by the destructor.
  std::atomic<bool> preempt_{false};
  bool stopping_ = false;
  Figures figures_;
  std::thread thread_;  // last: started once everything above exists
};

}  // namespace visq::core
