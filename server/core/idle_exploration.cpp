#include "core/idle_exploration.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <utility>

#include "common/check.h"
#include "common/job_timing.h"

namespace visq::core {

IdleExplorer::IdleExplorer(CostModel& model, IdleExplorationOptions options)
    : model_(model), options_(options), thread_([this] { Loop(); }) {}

IdleExplorer::~IdleExplorer() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
    pending_.clear();
  }
  preempt_ = true;
  wake_.notify_all();
  thread_.join();
}

void IdleExplorer::CallBegan() {
  std::lock_guard lock(mutex_);
  ++calls_in_flight_;
  preempt_ = true;
}

void IdleExplorer::CallEnded() {
  {
    std::lock_guard lock(mutex_);
    if (calls_in_flight_ > 0) --calls_in_flight_;
    last_call_end_ = std::chrono::steady_clock::now();
  }
  wake_.notify_all();
}

void IdleExplorer::Offer(EqualAnswerOption option, size_t first_probe) {
  VISQ_CHECK(option.probes_outlive_the_call && first_probe < option.probes.size());
  {
    std::lock_guard lock(mutex_);
    if (stopping_) return;
    if (const auto resting = resting_until_.find(option.plan.cost_key); resting != resting_until_.end()) {
      if (std::chrono::steady_clock::now() < resting->second) return;
      resting_until_.erase(resting);
    }
    for (auto it = pending_.begin(); it != pending_.end(); ++it)
      if (it->option.plan.cost_key == option.plan.cost_key) {
        pending_.erase(it);
        break;
      }
    pending_.push_back({std::move(option), first_probe});
    while (pending_.size() > options_.max_pending) {
      pending_.pop_front();
      ++figures_.probes_dropped;
    }
  }
  wake_.notify_all();
}

IdleExplorer::Figures IdleExplorer::figures() const {
  std::lock_guard lock(mutex_);
  Figures figures = figures_;
  figures.pending = static_cast<uint32_t>(pending_.size());
  return figures;
}

bool IdleExplorer::QuietLocked(std::chrono::steady_clock::time_point now,
                               std::chrono::steady_clock::duration& wait) const {
  const auto quiet = std::chrono::microseconds(static_cast<int64_t>(options_.quiet_ms * 1000.0));
  if (calls_in_flight_ > 0) {
    wait = quiet;  // woken by the call's end
    return false;
  }
  wait = last_call_end_ + quiet - now;
  return wait <= std::chrono::steady_clock::duration::zero();
}

void IdleExplorer::Loop() {
  std::unique_lock lock(mutex_);
  while (!stopping_) {
    if (pending_.empty()) {
      wake_.wait(lock);
      continue;
    }
    std::chrono::steady_clock::duration wait{};
    if (!QuietLocked(std::chrono::steady_clock::now(), wait)) {
      if (calls_in_flight_ > 0)
        wake_.wait(lock);
      else
        wake_.wait_for(lock, wait);
      continue;
    }
    Pending next = std::move(pending_.front());
    pending_.pop_front();
    preempt_ = false;  // no call is in flight: a call beginning from now on raises it
    lock.unlock();

    const CallOptions call{StopToken{&preempt_, SteadyTime::max()}, nullptr, "[idle probe]"};
    const auto start = std::chrono::steady_clock::now();
    double probe_ms = 0.0;
    const Status probed = ProbeOutsideARequest(model_, next.option, next.first_probe, options_.probe_budget_ms,
                                               call, probe_ms);
    const double ms = MillisecondsSince(start);

    lock.lock();
    figures_.total_ms += ms;
    if (probed.ok()) {
      ++figures_.probes_run;
      spdlog::debug("[idle probe] {} measured in {:.1f} ms", next.option.plan.cost_key, ms);
    } else if (preempt_.load() && !stopping_) {
      // A call arrived: the probe waits for the next quiet spell, unless
      // a newer one for the same series came meanwhile.
      ++figures_.probes_preempted;
      bool replaced = false;
      for (const Pending& waiting : pending_)
        replaced = replaced || waiting.option.plan.cost_key == next.option.plan.cost_key;
      next.longest_ms = std::max(next.longest_ms, ms);
      if (++next.preempted >= kMostPreemptions) {
        // What it learned: the method's probe costs more than it ran.
        model_.RecordCutProbe(next.option.plan.cost_key, next.longest_ms);
        resting_until_[next.option.plan.cost_key] = std::chrono::steady_clock::now() + kRestAfterOutlasting;
        ++figures_.probes_dropped;
        spdlog::debug("[idle probe] {} stopped by calls {} times: left, cut at {:.0f} ms", next.option.plan.cost_key,
                      next.preempted, next.longest_ms);
      } else if (!replaced) {
        pending_.push_front(std::move(next));
      }
    } else if (!stopping_) {
      ++figures_.probes_dropped;
      spdlog::info("[idle probe] {} failed: {}", next.option.plan.cost_key, probed.message());
    }
  }
}

}  // namespace visq::core
