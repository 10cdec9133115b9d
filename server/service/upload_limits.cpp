#include "service/upload_limits.h"

#include <vector>

#include <absl/strings/str_cat.h>

namespace visq::service {

using Clock = std::chrono::steady_clock;

struct UploadLimits::Watch::Entry {
  // Recursive: `on_idle` cancels the call, and gRPC may run the call's end
  // (and so ~Watch) on this same thread before the cancel returns.
  std::recursive_mutex mutex;
  bool alive = true;     // under `mutex`
  bool fired = false;    // under `mutex`
  std::atomic<bool> watching{true};
  std::atomic<Clock::rep> last{Clock::now().time_since_epoch().count()};
  Clock::rep limit = 0;
  std::function<void()> on_idle;
};

UploadLimits::Slot::~Slot() { limits_.Release(client_); }

void UploadLimits::Watch::Touch() { entry_->last = Clock::now().time_since_epoch().count(); }

void UploadLimits::Watch::Stop() {
  // Under the entry's lock: once Stop returns, `on_idle` cannot start.
  std::lock_guard lock(entry_->mutex);
  entry_->watching = false;
}

void UploadLimits::Watch::Resume() {
  entry_->last = Clock::now().time_since_epoch().count();
  entry_->watching = true;
}

UploadLimits::Watch::~Watch() {
  {
    std::lock_guard lock(entry_->mutex);
    entry_->alive = false;
  }
  std::lock_guard lock(limits_.mutex_);
  limits_.watched_.erase(entry_.get());
}

UploadLimits::UploadLimits(Options options) : options_(options) {
  if (options_.idle.count() > 0 || options_.stream_stall.count() > 0) watchdog_ = std::thread([this] { WatchLoop(); });
}

UploadLimits::~UploadLimits() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (watchdog_.joinable()) watchdog_.join();
}

StatusOr<std::unique_ptr<UploadLimits::Slot>> UploadLimits::Acquire(const std::string& client) {
  std::lock_guard lock(mutex_);
  if (options_.max_in_flight > 0 && in_flight_ >= options_.max_in_flight)
    return absl::ResourceExhaustedError(absl::StrCat("the server has ", in_flight_,
                                                     " uploads in flight, its limit (--max-uploads-in-flight); "
                                                     "retry when one has ended"));
  int& mine = per_client_[client];
  if (options_.max_per_client > 0 && mine >= options_.max_per_client)
    return absl::ResourceExhaustedError(absl::StrCat("this client (", client, ") has ", mine,
                                                     " uploads in flight, its limit (--max-uploads-per-client); "
                                                     "retry when one has ended"));
  ++mine;
  ++in_flight_;
  return std::unique_ptr<Slot>(new Slot(*this, client));
}

void UploadLimits::Release(const std::string& client) {
  std::lock_guard lock(mutex_);
  --in_flight_;
  if (auto it = per_client_.find(client); it != per_client_.end() && --it->second <= 0) per_client_.erase(it);
}

std::unique_ptr<UploadLimits::Watch> UploadLimits::StartWatch(std::function<void()> on_idle) {
  return StartWatch(std::move(on_idle), options_.idle, true);
}

std::unique_ptr<UploadLimits::Watch> UploadLimits::StartStallWatch(std::function<void()> on_stall) {
  return StartWatch(std::move(on_stall), options_.stream_stall, false);
}

std::unique_ptr<UploadLimits::Watch> UploadLimits::StartWatch(std::function<void()> on_idle,
                                                              std::chrono::milliseconds limit, bool watching) {
  auto entry = std::make_shared<Watch::Entry>();
  entry->on_idle = std::move(on_idle);
  entry->limit = std::chrono::duration_cast<Clock::duration>(limit).count();
  entry->watching = watching;
  std::lock_guard lock(mutex_);
  if (limit.count() > 0) watched_.emplace(entry.get(), entry);
  return std::unique_ptr<Watch>(new Watch(*this, std::move(entry)));
}

void UploadLimits::WatchLoop() {
  // Wakes a few times per limit, so an idle upload or a stalled answer ends
  // within about 1.25 of its limit.
  Clock::duration period = std::chrono::seconds(1);
  for (const std::chrono::milliseconds limit : {options_.idle, options_.stream_stall})
    if (limit.count() > 0) period = std::min<Clock::duration>(period, limit / 4);
  std::unique_lock lock(mutex_);
  while (!wake_.wait_for(lock, period, [this] { return stopping_; })) {
    // Which streams have sent nothing for the idle limit.
    const Clock::rep now = Clock::now().time_since_epoch().count();
    std::vector<std::shared_ptr<Watch::Entry>> idle;
    for (const auto& [key, entry] : watched_)
      if (entry->watching && now - entry->last.load() > entry->limit) idle.push_back(entry);
    lock.unlock();
    // Each ends once, outside the limits' lock: its end gives back its slot.
    for (const auto& entry : idle) {
      std::lock_guard entry_lock(entry->mutex);
      if (!entry->alive || entry->fired || !entry->watching) continue;
      entry->fired = true;
      entry->on_idle();
    }
    lock.lock();
  }
}

std::string UploadLimits::ClientOfPeer(const std::string& peer) {
  if (peer.rfind("ipv4:", 0) != 0 && peer.rfind("ipv6:", 0) != 0) return peer;
  const size_t colon = peer.rfind(':');
  return colon > 5 ? peer.substr(0, colon) : peer;
}

}  // namespace visq::service
