// What every handler shares: the unary-call pattern (authorize, run on the
// executor, log and finish), the prepared server-streaming pattern, and the
// call's deadline for GPU jobs.
#pragma once

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <type_traits>
#include <vector>

#include <grpcpp/server_context.h>

#include "core/call_options.h"
#include "service/chunked_responses.h"
#include "service/request_log.h"
#include "service/status_conversion.h"
#include "service/visibility_service.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::service {

// Which pool a unary call runs on: metadata calls (list, get, unload,
// stats) have threads of their own, so they answer in milliseconds while
// every compute thread is busy.
enum class Lane { kCompute, kMetadata };

// A unary reactor that remembers a cancellation (the client's, or the
// server's at shutdown), so work in progress can stop.
class CancellableUnaryReactor final : public grpc::ServerUnaryReactor {
 public:
  void OnCancel() override { cancelled_ = true; }
  void OnDone() override { delete this; }
  const std::atomic<bool>& cancelled() const { return cancelled_; }

 private:
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
  auto* reactor = new CancellableUnaryReactor();
  auto log = std::make_shared<RequestLog>(context, method, &ctx.metrics);
  if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
    log->Done(authorized);
    reactor->Finish(ToGrpcStatus(authorized));
    return reactor;
  }
  Executor& executor = lane == Lane::kMetadata ? ctx.metadata_executor : ctx.executor;
  executor.Post([reactor, log, work = std::move(work)]() mutable {
    Status status;
    if constexpr (std::is_invocable_v<Work&, RequestLog&, const std::atomic<bool>&>)
      status = work(*log, reactor->cancelled());
    else
      status = work(*log);
    log->Done(status);
    reactor->Finish(ToGrpcStatus(status));
  });
  return reactor;
}

// The call's deadline on the steady clock, which GPU jobs are queued with:
// a job whose client gave up never reaches the GPU.
inline gpu::SteadyTime SteadyDeadline(const grpc::CallbackServerContext* context) {
  const auto deadline = context->deadline();
  if (deadline == std::chrono::system_clock::time_point::max()) return gpu::SteadyTime::max();
  const auto left = deadline - std::chrono::system_clock::now();
  return std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(left);
}

// The call's deadline and cancellation for the core, so a request whose
// client gave up stops (the core chooses the GPU priority).
inline CallOptions CallOptionsFor(grpc::CallbackServerContext* context, const std::atomic<bool>* cancelled) {
  return {SteadyDeadline(context), cancelled};
}

// The figures' timing for a streamed answer; transfer_ms and total_ms are as
// of the first message (the chunks after it are built as they are written).
inline void SetStreamTiming(double queue_ms, double compute_ms, double before_transfer_ms, const RequestLog& log,
                            v1::Timing* timing) {
  timing->set_queue_ms(queue_ms);
  timing->set_compute_ms(compute_ms);
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
      : log_(context, method, &ctx.metrics) {
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Done(authorized);
      return;
    }
    ctx.executor.Post([this, compute = std::move(compute)] {
      StatusOr<ChunkedResponses<Response>> messages = compute(cancelled_, log_);
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
  void OnDone() override { delete this; }

 private:
  void WriteNext() {
    if (cancelled_ || !messages_->Next(current_)) {
      messages_.reset();  // the answer's memory goes before the call ends
      Done(cancelled_ ? absl::CancelledError("the call was cancelled while its answer was written")
                      : absl::OkStatus());
      return;
    }
    this->StartWrite(&current_);
  }

  void Done(const Status& status) {
    log_.Done(status);
    this->Finish(ToGrpcStatus(status));
  }

  RequestLog log_;
  std::atomic<bool> cancelled_{false};
  std::optional<ChunkedResponses<Response>> messages_;
  Response current_;
};

}  // namespace visq::service
