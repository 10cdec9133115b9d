// What every handler shares: the unary-call pattern (authorize, run on the
// executor, log and finish) and the call's deadline for GPU jobs.
#pragma once

#include <chrono>
#include <memory>

#include <grpcpp/server_context.h>

#include "service/request_log.h"
#include "service/status_conversion.h"
#include "service/visibility_service.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::service {

// A unary call: tags the response with the server id, authorizes, runs
// `work(RequestLog&)` on the executor, and finishes with its status.
template <typename Work>
grpc::ServerUnaryReactor* RunUnaryCall(const ServiceContext& ctx, grpc::CallbackServerContext* context,
                                       const char* method, Work work) {
  context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
  auto* reactor = context->DefaultReactor();
  auto log = std::make_shared<RequestLog>(context, method, &ctx.metrics);
  if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
    log->Done(authorized);
    reactor->Finish(ToGrpcStatus(authorized));
    return reactor;
  }
  ctx.executor.Post([reactor, log, work = std::move(work)]() mutable {
    const Status status = work(*log);
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

}  // namespace visq::service
