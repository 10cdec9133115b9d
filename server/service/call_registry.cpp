#include "service/call_registry.h"

#include "absl/strings/str_cat.h"

namespace visq::service {

void CallRegistry::Add(std::atomic<bool>* cancelled) {
  std::lock_guard lock(mutex_);
  calls_.insert(cancelled);
  if (drain_ended_) *cancelled = true;
}

void CallRegistry::Remove(std::atomic<bool>* cancelled) {
  std::lock_guard lock(mutex_);
  calls_.erase(cancelled);
}

size_t CallRegistry::EndDrain() {
  std::lock_guard lock(mutex_);
  drain_ended_ = true;
  for (std::atomic<bool>* cancelled : calls_) *cancelled = true;
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
