#include "service/call_registry.h"

#include "absl/strings/str_cat.h"

namespace visq::service {

void CallRegistry::Add(std::atomic<bool>* cancelled, bool computes) {
  {
    std::lock_guard lock(mutex_);
    calls_[cancelled] = computes;
    if (drain_ended_) *cancelled = true;
  }
  if (computes) WorkBegan();
}

void CallRegistry::Remove(std::atomic<bool>* cancelled) {
  bool computed = false;
  {
    std::lock_guard lock(mutex_);
    const auto it = calls_.find(cancelled);
    if (it == calls_.end()) return;
    computed = it->second;
    calls_.erase(it);
  }
  if (computed) WorkEnded();
}

void CallRegistry::WorkBegan() {
  if (activity_) activity_(true);
}

void CallRegistry::WorkEnded() {
  if (activity_) activity_(false);
}

size_t CallRegistry::EndDrain() {
  std::lock_guard lock(mutex_);
  drain_ended_ = true;
  for (const auto& [cancelled, computes] : calls_) *cancelled = true;
  return calls_.size();
}

size_t CallRegistry::in_flight() const {
  std::lock_guard lock(mutex_);
  return calls_.size();
}

Status CallRegistry::Final(Status status) const {
  if (!drain_ended_ || status.code() != absl::StatusCode::kCancelled) return status;
  return absl::UnavailableError(absl::StrCat("the server is shutting down: its drain period ended before this call's "
                                             "answer (retry on another replica); the work stopped at: ",
                                             status.message()));
}

}  // namespace visq::service
