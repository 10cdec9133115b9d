#include "core/work_budget.h"

#include <malloc.h>

#include <algorithm>
#include <chrono>
#include <utility>

#include "resource_limits/resource_limits.h"

namespace visq::core {
namespace {

// When the machine cannot say how much memory it has, nor a cgroup.
constexpr uint64_t kUnknownMemoryBudget = uint64_t{4} << 30;

// A cancellation is a flag nobody signals: a wait for memory looks at it
// this often.
constexpr auto kPollStop = std::chrono::milliseconds(50);

}  // namespace

WorkMemoryBudget::WorkMemoryBudget(uint64_t capacity_bytes) {
  if (capacity_bytes != 0) {
    capacity_ = capacity_bytes;
    capacity_source_ = "as given";
    return;
  }
  // Half: the rest is for the scenes, their structures and the caches,
  // which have bounds of their own.
  const resource_limits::MemoryLimit& usable = resource_limits::ProcessMemoryLimit();
  if (usable.bytes == 0) {
    capacity_ = kUnknownMemoryBudget;
    capacity_source_ = "neither physical memory nor a cgroup limit could be read: 4 GiB";
    return;
  }
  capacity_ = usable.bytes / 2;
  capacity_source_ = absl::StrCat("half of ", usable.source, " (", usable.bytes, " bytes)");
}

WorkMemoryBudget::Reservation::Reservation(Reservation&& other) noexcept
    : budget_(std::exchange(other.budget_, nullptr)),
      bytes_(std::exchange(other.bytes_, 0)),
      lasting_(std::exchange(other.lasting_, false)) {}

WorkMemoryBudget::Reservation& WorkMemoryBudget::Reservation::operator=(Reservation&& other) noexcept {
  if (this != &other) {
    if (budget_ != nullptr) budget_->Release(bytes_, lasting_);
    budget_ = std::exchange(other.budget_, nullptr);
    bytes_ = std::exchange(other.bytes_, 0);
    lasting_ = std::exchange(other.lasting_, false);
  }
  return *this;
}

WorkMemoryBudget::Reservation WorkMemoryBudget::Reservation::KeepLasting(uint64_t bytes) {
  bytes = std::min(bytes, bytes_);
  if (budget_ == nullptr || bytes == 0) return Reservation();
  bytes_ -= bytes;
  if (!lasting_) {
    std::lock_guard lock(budget_->mutex_);
    budget_->lasting_ += bytes;
  }
  return Reservation(budget_, bytes, /*lasting=*/true);
}

WorkMemoryBudget::Reservation::~Reservation() {
  if (budget_ != nullptr) budget_->Release(bytes_, lasting_);
}

StatusOr<WorkMemoryBudget::Reservation> WorkMemoryBudget::Reserve(uint64_t bytes, const std::string& what,
                                                                  const JobOptions& job) {
  if (bytes > capacity_)
    return absl::ResourceExhaustedError(absl::StrCat(what, ": needs about ", bytes,
                                                     " bytes while it runs, above the server's budget for work in "
                                                     "flight of ",
                                                     capacity_, " (--max-work-bytes)"));
  std::unique_lock lock(mutex_);
  // Polled in short waits: a cancellation sets a flag, it does not notify.
  while (in_use_ + bytes > capacity_) {
    // Lasting reservations go only with their scene's next bake or unload:
    // waiting for them would last until the deadline.
    if (bytes > capacity_ - lasting_)
      return absl::ResourceExhaustedError(absl::StrCat(
          what, ": needs about ", bytes, " bytes while it runs; of the server's budget for work in flight of ",
          capacity_, " (--max-work-bytes), ", lasting_,
          " are held by results it keeps (obscurance solutions for UpdateObscurances, until their scene's next "
          "whole bake or unload)"));
    if (job.stop.Stopped())
      return job.stop.Check(absl::StrCat(what, ": while waiting for ", bytes,
                                         " bytes of the budget for work in flight (--max-work-bytes)"));
    released_.wait_until(lock, std::min(job.stop.deadline, std::chrono::steady_clock::now() + kPollStop));
  }
  in_use_ += bytes;
  peak_ = std::max(peak_, in_use_);
  return Reservation(this, bytes);
}

std::optional<WorkMemoryBudget::Reservation> WorkMemoryBudget::TryReserveSpare(uint64_t bytes) {
  std::lock_guard lock(mutex_);
  const uint64_t spare_limit = capacity_ - capacity_ / 4;
  if (bytes > spare_limit || in_use_ > spare_limit - bytes) return std::nullopt;
  in_use_ += bytes;
  peak_ = std::max(peak_, in_use_);
  return Reservation(this, bytes);
}

void WorkMemoryBudget::Release(uint64_t bytes, bool lasting) {
  {
    std::lock_guard lock(mutex_);
    in_use_ -= bytes;
    if (lasting) lasting_ -= bytes;
  }
  released_.notify_all();
  // glibc keeps freed memory of a large answer in its arenas (1.4 GB after
  // four maps at the cap): hand it back to the system once it goes.
  if (bytes >= kTrimAfterBytes) malloc_trim(0);
}

uint64_t WorkMemoryBudget::in_use() const {
  std::lock_guard lock(mutex_);
  return in_use_;
}

uint64_t WorkMemoryBudget::peak() const {
  std::lock_guard lock(mutex_);
  return peak_;
}

}  // namespace visq::core
