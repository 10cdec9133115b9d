// What every handler shares: the unary-call pattern (authorize, run on the
// executor, log and finish), the prepared server-streaming pattern, and the
// call's deadline for GPU jobs.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <type_traits>
#include <vector>

#include <grpcpp/server_context.h>

#include "common/job_options.h"
#include "core/call_options.h"
#include "core/work_budget.h"
#include "service/chunked_responses.h"
#include "service/exception_boundary.h"
#include "service/request_log.h"
#include "service/status_conversion.h"
#include "service/visibility_service.h"

namespace visq::service {

// Which pool a unary call runs on: metadata calls (list, get, unload,
// stats) have threads of their own, so they answer in milliseconds while
// every compute thread is busy.
enum class Lane { kCompute, kMetadata };

// A unary reactor that remembers a cancellation (the client's, or the
// server's at shutdown), so work in progress can stop.
class CancellableUnaryReactor final : public grpc::ServerUnaryReactor {
 public:
  CancellableUnaryReactor(CallRegistry& calls, bool computes) : calls_(calls) { calls_.Add(&cancelled_, computes); }
  void OnCancel() override { cancelled_ = true; }
  void OnDone() override {
    calls_.Remove(&cancelled_);
    delete this;
  }
  const std::atomic<bool>& cancelled() const { return cancelled_; }

 private:
  CallRegistry& calls_;
  std::atomic<bool> cancelled_{false};
};

// A unary call: tags the response with the server id, authorizes, runs
// `work(RequestLog&)`, or `work(RequestLog&, const std::atomic<bool>&
// cancelled)` for work that can stop part-way, on the lane's executor, and
// finishes with its status.
template <typename Work>
grpc::ServerUnaryReactor* RunUnaryCall(const ServiceContext& ctx, grpc::CallbackServerContext* context,
                                       const char* method, Work work, Lane lane = Lane::kCompute) {
  context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
  auto* reactor = new CancellableUnaryReactor(ctx.calls, lane == Lane::kCompute);
  auto log = std::make_shared<RequestLog>(context, method, &ctx.metrics);
  if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
    log->Done(authorized);
    reactor->Finish(ToGrpcStatus(authorized));
    return reactor;
  }
  Executor& executor = lane == Lane::kMetadata ? ctx.metadata_executor : ctx.executor;
  executor.Post([reactor, log, method, calls = &ctx.calls, work = std::move(work)]() mutable {
    Status status = CatchExceptions(log->id(), method, [&]() -> Status {
      if constexpr (std::is_invocable_v<Work&, RequestLog&, const std::atomic<bool>&>)
        return work(*log, reactor->cancelled());
      else
        return work(*log);
    });
    status = calls->Final(std::move(status));
    log->Done(status);
    reactor->Finish(ToGrpcStatus(status));
  });
  return reactor;
}

// The call's deadline on the steady clock, which GPU jobs are queued with:
// a job whose client gave up never reaches the GPU.
inline SteadyTime SteadyDeadline(const grpc::CallbackServerContext* context) {
  const auto deadline = context->deadline();
  if (deadline == std::chrono::system_clock::time_point::max()) return SteadyTime::max();
  const auto left = deadline - std::chrono::system_clock::now();
  return std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(left);
}

// The call's deadline and cancellation for the core, so a request whose
// client gave up stops (the core chooses the GPU priority), and the clock of
// its waits for lazily built structures (Timing.build_ms).
inline core::CallOptions CallOptionsFor(grpc::CallbackServerContext* context, const std::atomic<bool>* cancelled,
                                        const RequestLog& log) {
  return {StopToken{cancelled, SteadyDeadline(context)}, std::make_shared<core::BuildClock>(), log.Tag()};
}

// The figures' timing for a streamed answer; transfer_ms and total_ms are as
// of the first message (the chunks after it are built as they are written).
inline void SetStreamTiming(double queue_ms, double compute_ms, double build_ms, double before_transfer_ms,
                            const RequestLog& log, v1::Timing* timing) {
  timing->set_queue_ms(queue_ms);
  timing->set_compute_ms(compute_ms);
  timing->set_build_ms(build_ms);
  timing->set_transfer_ms(log.ElapsedMs() - before_transfer_ms);
  timing->set_total_ms(log.ElapsedMs());
}

// Server-streaming answers: computes the answer on the executor, then
// writes its messages in order, each built as the previous one is written
// (chunked_responses.h). `compute`'s first message carries the timing.
template <typename Response>
class PreparedStreamReactor final : public grpc::ServerWriteReactor<Response> {
 public:
  using Compute =
      std::function<StatusOr<ChunkedResponses<Response>>(const std::atomic<bool>& cancelled, const RequestLog& log)>;
  PreparedStreamReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx, const char* method,
                        Compute compute)
      : calls_(ctx.calls), log_(context, method, &ctx.metrics),
        stall_(ctx.uploads.StartStallWatch([this, context] {
          cancelled_ = true;
          context->TryCancel();
        })) {
    calls_.Add(&cancelled_);
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Done(authorized);
      return;
    }
    ctx.executor.Post([this, method, compute = std::move(compute)] {
      StatusOr<ChunkedResponses<Response>> messages =
          CatchExceptions(log_.id(), method, [&] { return compute(cancelled_, log_); });
      if (!messages.ok()) {
        Done(messages.status());
        return;
      }
      messages_.emplace(*std::move(messages));
      WriteNext();
    });
  }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      Done(absl::CancelledError("client went away"));
      return;
    }
    WriteNext();
  }
  void OnCancel() override { cancelled_ = true; }
  void OnDone() override {
    calls_.Remove(&cancelled_);
    stall_.reset();
    delete this;
  }

 private:
  void WriteNext() {
    if (cancelled_ || !messages_->Next(current_)) {
      stall_->Stop();
      messages_.reset();  // the answer's memory goes before the call ends
      Done(cancelled_ ? absl::CancelledError("the call was cancelled while its answer was written")
                      : absl::OkStatus());
      return;
    }
    stall_->Resume();
    this->StartWrite(&current_);
  }

  void Done(const Status& given) {
    const Status status = calls_.Final(given);
    log_.Done(status);
    this->Finish(ToGrpcStatus(status));
  }

  CallRegistry& calls_;
  RequestLog log_;
  std::atomic<bool> cancelled_{false};
  std::unique_ptr<UploadLimits::Watch> stall_;  // --stream-stall-seconds, while a write waits for the client
  std::optional<ChunkedResponses<Response>> messages_;
  Response current_;
};

// Server-streaming answers written while they are made: `produce` runs on
// the executor and hands each message to `out.Write` as soon as it is built;
// what `produce` returns is written last (the figures that need the whole
// answer: its bound and timing). Up to --stream-queue-bytes wait to be sent
// within the call's own reservation; beyond that a message parks in the work
// budget's spare memory (core::WorkMemoryBudget::TryReserveSpare), so the
// work ends and its worker serves other calls while the reader catches up,
// and where none is spare Write waits: a slow reader holds back the work
// rather than growing memory past the budget. Write fails once the call is
// cancelled or when the client has read nothing for the stall limit
// (--stream-stall-seconds), which also ends a call whose produced answer
// waits, whole, for a client that reads nothing.
template <typename Response>
class ProducedStreamReactor final : public grpc::ServerWriteReactor<Response> {
 public:

  using Produce = std::function<StatusOr<Response>(const std::atomic<bool>& cancelled, const RequestLog& log,
                                                   ProducedStreamReactor& out)>;
  ProducedStreamReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx, const char* method,
                        Produce produce)
      : context_(context), calls_(ctx.calls), log_(context, method, &ctx.metrics), budget_(ctx.engine.work_budget()),
        queue_limit_(std::min(ctx.uploads.options().stream_queue_bytes, core::kStreamedAnswerQueueBytes)),
        stall_seconds_(std::chrono::duration<double>(ctx.uploads.options().stream_stall).count()),
        stall_(ctx.uploads.StartStallWatch([this] {
          {
            std::lock_guard lock(mutex_);
            cancelled_ = true;
            stalled_ = true;
          }
          progress_.notify_all();
          context_->TryCancel();
        })) {
    calls_.Add(&cancelled_);
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Done(authorized);
      return;
    }
    ctx.executor.Post([this, method, produce = std::move(produce)] {
      StatusOr<Response> last = CatchExceptions(log_.id(), method, [&] { return produce(cancelled_, log_, *this); });
      Status status = last.status();
      if (status.ok()) status = Write(*std::move(last));
      FinishProducing(status);
    });
  }

  // Queues `message` for writing, after those before it. Producer thread.
  [[nodiscard]] Status Write(Response message) {
    const auto start = std::chrono::steady_clock::now();
    struct AddTime {
      double& total;
      std::chrono::steady_clock::time_point start;
      ~AddTime() {
        total += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
      }
    } add_time{write_ms_, start};
    const uint64_t bytes = message.ByteSizeLong();
    std::unique_lock lock(mutex_);
    std::optional<core::WorkMemoryBudget::Reservation> parked;
    if (!cancelled_ && queued_bytes_ > queue_limit_) parked = budget_.TryReserveSpare(bytes);
    if (!parked) progress_.wait(lock, [&] { return cancelled_ || queued_bytes_ <= queue_limit_; });
    if (stalled_)
      return absl::DeadlineExceededError(
          absl::StrCat("the client read nothing for ", stall_seconds_, " s (--stream-stall-seconds)"));
    if (cancelled_) return absl::CancelledError("the call was cancelled while its answer was written");
    queued_bytes_ += bytes;
    queue_.push_back({std::move(message), bytes, parked ? std::move(*parked) : core::WorkMemoryBudget::Reservation()});
    if (writing_) return absl::OkStatus();
    StartNext(lock);
    return absl::OkStatus();
  }

  // Milliseconds the producer has spent in Write, waiting for the reader
  // included: transfer, not compute. Producer thread.
  double write_ms() const { return write_ms_; }

  // Keeps `owner` (what the answer's memory reservation or arrays are) until
  // the call ends.
  void Keep(std::shared_ptr<const void> owner) {
    std::lock_guard lock(mutex_);
    kept_.push_back(std::move(owner));
  }

  void OnWriteDone(bool ok) override {
    std::unique_lock lock(mutex_);
    writing_ = false;
    queued_bytes_ -= current_bytes_;
    current_parked_ = core::WorkMemoryBudget::Reservation();
    ++written_;
    if (!ok) cancelled_ = true;  // the client went away
    progress_.notify_all();
    if (!cancelled_ && !queue_.empty()) {
      StartNext(lock);
      return;
    }
    if (!producing_done_) return;
    lock.unlock();
    Done(cancelled_ && final_status_.ok() ? absl::CancelledError("the call was cancelled while its answer was written")
                                          : final_status_);
  }
  void OnCancel() override {
    std::lock_guard lock(mutex_);
    cancelled_ = true;
    progress_.notify_all();
  }
  void OnDone() override {
    calls_.Remove(&cancelled_);
    stall_.reset();
    delete this;
  }

 private:
  struct Queued {
    Response message;
    uint64_t bytes;
    core::WorkMemoryBudget::Reservation parked;  // empty within the queue limit
  };

  // With the lock held and the queue not empty: starts the next write, with
  // the lock released (a reaction never runs under it).
  void StartNext(std::unique_lock<std::mutex>& lock) {
    current_ = std::move(queue_.front().message);
    current_bytes_ = queue_.front().bytes;
    current_parked_ = std::move(queue_.front().parked);
    queue_.pop_front();
    writing_ = true;
    stall_->Resume();
    lock.unlock();
    this->StartWrite(&current_);
  }

  void FinishProducing(Status status) {
    std::unique_lock lock(mutex_);
    producing_done_ = true;
    if (cancelled_ && status.ok()) status = absl::CancelledError("the call was cancelled while its answer was written");
    final_status_ = status;
    if (!status.ok()) {
      for (const Queued& q : queue_) queued_bytes_ -= q.bytes;
      queue_.clear();
    }
    if (writing_) return;  // OnWriteDone finishes the call
    lock.unlock();
    Done(status);
  }

  void Done(const Status& given) {
    stall_->Stop();
    {
      std::lock_guard lock(mutex_);
      kept_.clear();  // the answer's memory goes before the call ends
    }
    const Status status = calls_.Final(given);
    log_.Done(status);
    this->Finish(ToGrpcStatus(status));
  }

  grpc::CallbackServerContext* context_;
  CallRegistry& calls_;
  RequestLog log_;
  core::WorkMemoryBudget& budget_;
  const uint64_t queue_limit_;
  std::atomic<bool> cancelled_{false};
  bool stalled_ = false;  // under mutex_: the stall limit ended the call
  std::mutex mutex_;
  std::condition_variable progress_;
  std::deque<Queued> queue_;
  uint64_t queued_bytes_ = 0;  // queued and being written
  uint64_t written_ = 0;
  bool writing_ = false;
  bool producing_done_ = false;
  Status final_status_;
  std::vector<std::shared_ptr<const void>> kept_;
  Response current_;
  uint64_t current_bytes_ = 0;
  core::WorkMemoryBudget::Reservation current_parked_;
  double write_ms_ = 0.0;  // producer thread only
  double stall_seconds_;
  std::unique_ptr<UploadLimits::Watch> stall_;  // --stream-stall-seconds, while a write waits for the client
};

}  // namespace visq::service
