// The obscurance RPCs (Méndez-Feliu, Sbert et al.): ComputeObscurances
// streams progress while the GPU bakes, then the result in chunks;
// SetNodeTransform and UpdateObscurances are unary; RenderObscurancePreview
// streams the picture like VolumetricShadow, and ExportObscurances the
// atlas UVs and the baked glTF. The work is in
// core/obscurance_query.h and the messages' conversions in convert.cpp;
// this file runs the calls.
#include <algorithm>
#include <cmath>
#include <mutex>
#include <optional>

#include <absl/strings/str_format.h>

#include "core/obscurance_query.h"
#include "core/scene_edit_query.h"
#include "service/convert.h"
#include "service/reactors.h"
#include "service/request_log.h"
#include "service/status_conversion.h"
#include "service/visibility_service.h"

namespace visq::service {
namespace {

// Writes progress while the bake runs on the executor, then the result.
// The executor pushes messages into a small queue; one write is in flight
// at a time (OnWriteDone starts the next); a progress message replaces one
// still waiting. Finish comes only after the bake returned, so the executor
// never touches a reactor that gRPC has deleted.
class ComputeObscurancesReactor final : public grpc::ServerWriteReactor<v1::ComputeObscurancesResponse> {
 public:
  ComputeObscurancesReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx,
                            const v1::ComputeObscurancesRequest* request)
      : calls_(ctx.calls), log_(context, "ComputeObscurances", &ctx.metrics),
        stall_(ctx.uploads.StartStallWatch([this, context] {
          cancelled_ = true;  // the bake stops at its next step
          context->TryCancel();
        })) {
    // In the registry, so that the drain's end tells the bake to stop (it
    // polls the flag between steps) and the call answers UNAVAILABLE: left
    // out, a bake ran on until gRPC's own shutdown deadline cut it, answered
    // CANCELLED, a full drain late.
    calls_.Add(&cancelled_);
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      log_.Done(authorized);
      Finish(ToGrpcStatus(authorized));
      return;
    }
    const SteadyTime deadline = SteadyDeadline(context);
    ctx.executor.Post([this, &ctx, request, deadline] {
      const double queue_ms = log_.ElapsedMs();
      StatusOr<ChunkedResponses<v1::ComputeObscurancesResponse>> messages = CatchExceptions(
          log_.id(), "ComputeObscurances", [&] { return Compute(ctx.engine, *request, deadline, queue_ms); });
      Complete(std::move(messages));
    });
  }

  void OnWriteDone(bool ok) override {
    std::unique_lock lock(mutex_);
    writing_ = false;
    if (!ok) {
      broken_ = true;  // the client went away: stop the bake, finish once it has
      cancelled_ = true;
    }
    Next(lock);
  }
  void OnCancel() override { cancelled_ = true; }
  void OnDone() override {
    calls_.Remove(&cancelled_);
    stall_.reset();
    delete this;
  }

 private:
  StatusOr<ChunkedResponses<v1::ComputeObscurancesResponse>> Compute(core::Engine& engine,
                                                                     const v1::ComputeObscurancesRequest& request,
                                                                     SteadyTime deadline, double queue_ms) {
    VISQ_ASSIGN_OR_RETURN(core::ObscuranceQuery query, FromProto(request));
    query.call = {StopToken{&cancelled_, deadline}, std::make_shared<core::BuildClock>()};
    const std::shared_ptr<core::BuildClock> build_clock = query.call.build_clock;
    // At most ~10 progress messages a second (and the first and last).
    auto last_sent = std::make_shared<double>(-1e9);
    query.progress = [this, last_sent](const obscurance::ObscuranceProgress& p) {
      if (p.directions_done != 1 && p.directions_done != p.directions_total &&
          p.elapsed_seconds - *last_sent < 0.1)
        return;
      *last_sent = p.elapsed_seconds;
      v1::ComputeObscurancesResponse m;
      auto* progress = m.mutable_progress();
      progress->set_directions_done(p.directions_done);
      progress->set_directions_total(p.directions_total);
      progress->set_elapsed_s(p.elapsed_seconds);
      progress->set_estimated_s_left(p.estimated_seconds_left);
      Progress(std::move(m));
    };
    log_.Info("'{}' {}^2 atlas, directions [{}, {}) of {}, d_max {}{}{}", query.scene, query.resolution,
              query.params.first_direction, query.params.first_direction + query.params.direction_count,
              query.total_directions, query.params.d_max, query.params.color_bleeding ? ", color bleeding" : "",
              query.partial_only ? ", partial" : "");
    const bool want_averages = query.want_averages, want_errors = query.want_errors;
    VISQ_ASSIGN_OR_RETURN(core::ObscuranceAnswer answer, core::RunComputeObscurances(engine, std::move(query)));
    const double before_transfer = log_.ElapsedMs();
    const double compute_ms = core::WorkTimingOf(answer).compute_ms;
    log_.Info("{}x{} texels, {} layers, bake {:.1f} ms", answer.width, answer.height, answer.stats.layers,
              answer.bake_ms);
    ChunkedResponses<v1::ComputeObscurancesResponse> messages = ToProtoStream(std::move(answer), want_averages, want_errors);
    SetStreamTiming(queue_ms, compute_ms, build_clock->ms(), before_transfer, log_,
                    messages.first().mutable_figures()->mutable_timing());
    return messages;
  }

  void Progress(v1::ComputeObscurancesResponse message) {
    std::unique_lock lock(mutex_);
    progress_ = std::move(message);
    Next(lock);
  }

  void Complete(StatusOr<ChunkedResponses<v1::ComputeObscurancesResponse>> messages) {
    std::unique_lock lock(mutex_);
    final_ = messages.status();
    if (messages.ok()) results_.emplace(*std::move(messages));
    progress_.reset();  // stale once the result is here
    Next(lock);
  }

  // Starts the next write, or finishes; called with the lock held, and
  // releases it before Finish (after which OnDone may delete this).
  void Next(std::unique_lock<std::mutex>& lock) {
    if (writing_ || finished_) return;
    if (!broken_ && (!final_ || final_->ok())) {
      if (progress_) {
        current_ = std::move(*progress_);
        progress_.reset();
        writing_ = true;
        stall_->Resume();
        StartWrite(&current_);
        return;
      }
      if (final_ && results_ && !cancelled_ && results_->Next(current_)) {
        writing_ = true;
        stall_->Resume();
        StartWrite(&current_);
        return;
      }
    }
    stall_->Stop();  // nothing waits for the client while the bake runs
    if (!final_) return;
    finished_ = true;
    results_.reset();  // the answer's memory goes before the call ends
    // A call stopped while its answer was written has not had all of it: not
    // OK (the drain's end stops the writes of a call whose client is there).
    const Status status = calls_.Final(
        !final_->ok()  ? *final_
        : broken_      ? absl::CancelledError("client went away")
        : cancelled_   ? absl::CancelledError("the call was cancelled while its answer was written")
                       : *final_);
    lock.unlock();
    log_.Done(status);
    Finish(ToGrpcStatus(status));
  }

  CallRegistry& calls_;
  RequestLog log_;
  std::atomic<bool> cancelled_{false};
  std::unique_ptr<UploadLimits::Watch> stall_;  // --stream-stall-seconds, while a write waits for the client
  std::mutex mutex_;
  bool writing_ = false;
  bool broken_ = false;
  bool finished_ = false;
  std::optional<v1::ComputeObscurancesResponse> progress_;
  std::optional<ChunkedResponses<v1::ComputeObscurancesResponse>> results_;
  std::optional<Status> final_;
  v1::ComputeObscurancesResponse current_;
};


}  // namespace

grpc::ServerWriteReactor<v1::ComputeObscurancesResponse>* VisibilityServiceImpl::ComputeObscurances(
    grpc::CallbackServerContext* context, const v1::ComputeObscurancesRequest* request) {
  return new ComputeObscurancesReactor(context, ctx_, request);
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::SetNodeTransform(grpc::CallbackServerContext* context,
                                                                  const v1::SetNodeTransformRequest* request,
                                                                  v1::SceneInfo* response) {
  return RunUnaryCall(ctx_, context, "SetNodeTransform", [this, context, request, response](
                                                              RequestLog& log, const std::atomic<bool>& cancelled) -> Status {
    core::NodeTransformQuery query = FromProto(*request);
    query.call = CallOptionsFor(context, &cancelled, log);
    // A call whose client gave up while it queued does not move the node.
    VISQ_RETURN_IF_ERROR(query.call.stop.Check("SetNodeTransform: before the move"));
    log.Info("'{}' node {}", query.scene,
             query.node_name ? "'" + *query.node_name + "'" : query.node_index ? std::to_string(*query.node_index) : "?");
    VISQ_ASSIGN_OR_RETURN(core::SceneSummary summary, core::RunSetNodeTransform(ctx_.engine, query));
    ToProto(summary, response);
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::UpdateObscurances(grpc::CallbackServerContext* context,
                                                                   const v1::UpdateObscurancesRequest* request,
                                                                   v1::UpdateObscurancesResponse* response) {
  return RunUnaryCall(ctx_, context, "UpdateObscurances", [this, context, request, response](
                                                               RequestLog& log, const std::atomic<bool>& cancelled) -> Status {
    const double queue_ms = log.ElapsedMs();
    core::ObscuranceUpdateQuery query = FromProto(*request);
    query.call = CallOptionsFor(context, &cancelled, log);
    VISQ_ASSIGN_OR_RETURN(core::ObscuranceUpdateAnswer answer, core::RunUpdateObscurances(ctx_.engine, query));
    const double before_transfer = log.ElapsedMs();
    ToProto(answer, response);
    auto* timing = response->mutable_timing();
    timing->set_queue_ms(queue_ms + core::WorkTimingOf(answer).queue_ms);
    timing->set_compute_ms(core::WorkTimingOf(answer).compute_ms);
    timing->set_transfer_ms(log.ElapsedMs() - before_transfer);
    timing->set_total_ms(log.ElapsedMs());
    log.Info("v{} -> v{}: {} move(s), {} texels changed, {} rays, {:.1f} ms", answer.from_version,
             answer.scene_version, answer.moves_applied, answer.update.texels.size(), answer.update.rays,
             answer.compute_ms);
    return absl::OkStatus();
  });
}

grpc::ServerWriteReactor<v1::ObscurancePreviewResponse>* VisibilityServiceImpl::RenderObscurancePreview(
    grpc::CallbackServerContext* context, const v1::ObscurancePreviewRequest* request) {
  return new PreparedStreamReactor<v1::ObscurancePreviewResponse>(
      context, ctx_, "RenderObscurancePreview",
      [this, context, request](const std::atomic<bool>& cancelled,
                               const RequestLog& log) -> StatusOr<ChunkedResponses<v1::ObscurancePreviewResponse>> {
        const double queue_ms = log.ElapsedMs();
        VISQ_ASSIGN_OR_RETURN(core::ObscurancePreviewQuery query, FromProto(*request));
        query.call = CallOptionsFor(context, &cancelled, log);
        VISQ_ASSIGN_OR_RETURN(core::ObscurancePreviewAnswer answer,
                              core::RunRenderObscurancePreview(ctx_.engine, query));
        const double before_transfer = log.ElapsedMs();
        log.Info("v{} {}x{} {}, render {:.1f} ms", answer.solution_version, answer.image.width, answer.image.height,
                 request->quantity() == v1::ObscurancePreviewRequest::INTENSITY ? "intensity" : "W",
                 answer.image.render_ms);
        const core::WorkTiming work = core::WorkTimingOf(answer);
        ChunkedResponses<v1::ObscurancePreviewResponse> messages = ToProtoStream(std::move(answer));
        SetStreamTiming(queue_ms + work.queue_ms, work.compute_ms, query.call.BuildMs(), before_transfer, log,
                        messages.first().mutable_timing());
        return messages;
      });
}

grpc::ServerWriteReactor<v1::ExportObscurancesResponse>* VisibilityServiceImpl::ExportObscurances(
    grpc::CallbackServerContext* context, const v1::ExportObscurancesRequest* request) {
  return new PreparedStreamReactor<v1::ExportObscurancesResponse>(
      context, ctx_, "ExportObscurances",
      [this, context, request](const std::atomic<bool>& cancelled,
                               const RequestLog& log) -> StatusOr<ChunkedResponses<v1::ExportObscurancesResponse>> {
        const double queue_ms = log.ElapsedMs();
        VISQ_ASSIGN_OR_RETURN(core::ObscuranceExportQuery query, FromProto(*request));
        query.call = CallOptionsFor(context, &cancelled, log);
        VISQ_ASSIGN_OR_RETURN(core::ObscuranceExportAnswer answer, core::RunExportObscurances(ctx_.engine, query));
        const double before_transfer = log.ElapsedMs();
        log.Info("v{} {}x{}, {} triangles, {} UV floats, {} glTF bytes, export {:.1f} ms", answer.solution_version,
                 answer.width, answer.height, answer.triangles, answer.atlas_uv.size(), answer.glb.size(),
                 answer.export_ms);
        const core::WorkTiming work = core::WorkTimingOf(answer);
        ChunkedResponses<v1::ExportObscurancesResponse> messages = ToProtoStream(std::move(answer));
        SetStreamTiming(queue_ms + work.queue_ms, work.compute_ms, query.call.BuildMs(), before_transfer, log,
                        messages.first().mutable_timing());
        return messages;
      });
}

}  // namespace visq::service
