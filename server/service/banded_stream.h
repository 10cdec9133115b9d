// One handler for every RPC whose answer the core makes in bands
// (common/band.h) and the transport streams as they are made: a hidden-sample
// map, a volumetric image, a voxel grid. Per RPC there is only conversion
// (convert.h: FromProto, FirstMessage, WriteBand, LastMessage,
// DescribeAnswer) and the core function that makes the answer.
//
// The stream: a first message with the figures known before any band, each
// band's messages (one array chunk each) as soon as the band is made, and a
// last message with what needs every band: its accuracy and timing.
#pragma once

#include <memory>
#include <string>
#include <utility>

#include <grpcpp/server_context.h>

#include "core/work_timing.h"
#include "service/convert.h"
#include "service/reactors.h"
#include "service/visibility_service.h"

namespace visq::service {

// `run(engine, query, sink)` is the core's function for the query: it hands
// each band to the sink in order and returns the answer (figures only).
template <typename Response, typename Request, typename Run>
grpc::ServerWriteReactor<Response>* ServeBandedStream(const ServiceContext& ctx, grpc::CallbackServerContext* context,
                                                      const char* method, const Request* request, Run run) {
  using Reactor = ProducedStreamReactor<Response>;
  return new Reactor(
      context, ctx, method,
      [ctx = &ctx, context, request, run = std::move(run)](const std::atomic<bool>& cancelled, const RequestLog& log,
                                                           Reactor& out) -> StatusOr<Response> {
        const double queue_ms = log.ElapsedMs();
        auto query_or = FromProto(*request);
        VISQ_RETURN_IF_ERROR(query_or.status());
        auto query = *std::move(query_or);
        query.call = CallOptionsFor(context, &cancelled, log);
        const std::function<Status(Response)> write = [&out](Response message) { return out.Write(std::move(message)); };
        auto sink = [&](const auto& figures, const auto& band) -> Status {
          if (band.opens_answer()) VISQ_RETURN_IF_ERROR(write(FirstMessage(figures)));
          return WriteBand(query, figures, band, write);
        };
        auto answer_or = run(ctx->engine, query, sink);
        VISQ_RETURN_IF_ERROR(answer_or.status());
        const auto& answer = *answer_or;
        log.Info("{}", DescribeAnswer(query, answer));
        // An answer's memory reservation lasts until its last message is sent.
        if constexpr (requires { answer.memory; })
          if (answer.memory) out.Keep(answer.memory);
        // The timing goes last: the transfer is the time the work waited for
        // its writes (the reader's pace).
        Response last = LastMessage(answer);
        const core::WorkTiming work = core::WorkTimingOf(answer);
        v1::Timing* timing = last.mutable_timing();
        timing->set_queue_ms(queue_ms + work.queue_ms);
        timing->set_compute_ms(work.compute_ms);
        timing->set_build_ms(query.call.BuildMs());
        timing->set_transfer_ms(out.write_ms());
        timing->set_total_ms(log.ElapsedMs());
        return last;
      });
}

}  // namespace visq::service
