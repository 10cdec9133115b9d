// The obscurance RPCs (Méndez-Feliu, Sbert et al.): ComputeObscurances
// streams progress while the GPU bakes, then the result in chunks;
// SetNodeTransform and UpdateObscurances are unary; RenderObscurancePreview
// streams the picture like VolumetricShadow, and ExportObscurances the
// atlas UVs and the baked glTF. The work is in
// core/obscurance_query.h; this file converts messages and runs the calls.
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

void AddVec3(const glm::vec3& v, google::protobuf::RepeatedField<float>* out) {
  out->Add(v.x);
  out->Add(v.y);
  out->Add(v.z);
}

// Figures, then the arrays in the order the proto gives.
ChunkedResponses<v1::ComputeObscurancesResponse> ToProtoStream(core::ObscuranceAnswer answer, bool want_averages,
                                                               bool want_errors) {
  auto kept = std::make_shared<const core::ObscuranceAnswer>(std::move(answer));
  const core::ObscuranceAnswer& a = *kept;
  v1::ComputeObscurancesResponse figures;
  v1::ObscuranceFigures* f = figures.mutable_figures();
  f->set_scene_version(a.scene_version);
  f->mutable_atlas()->set_width(a.width);
  f->mutable_atlas()->set_height(a.height);
  f->mutable_atlas()->set_from_lightmap_uvs(a.from_lightmap_uvs);
  f->mutable_atlas()->set_chart_count(a.chart_count);
  f->mutable_atlas()->set_texels_per_unit(a.texels_per_unit);
  f->set_channels(a.partial.channels);
  f->set_fingerprint(a.partial.fingerprint);
  for (const obscurance::DirectionRange& r : a.partial.ranges) {
    auto* range = f->add_ranges();
    range->set_first(r.first);
    range->set_count(r.count);
  }
  f->set_total_directions(a.total_directions);
  f->set_partial_only(!a.result.has_value());
  ToProto(a.ambient.ambient_intensity, f->mutable_ambient_intensity());
  ToProto(a.ambient.r_ave, f->mutable_r_ave());
  f->set_ambient_clamped(a.ambient.clamped);
  f->set_layers(a.stats.layers);
  f->set_max_layers(a.stats.max_layers);
  f->set_truncated_directions(a.stats.truncated_directions);
  f->set_bundle_resolution(a.stats.bundle_resolution);
  f->set_update_ready(a.update_ready);
  const core::ObscuranceCoverage coverage = core::CoverageOf(a);
  f->set_estimated_texels(coverage.estimated_texels);
  f->set_mean_samples_per_patch(coverage.mean_samples_per_patch);
  service::ToProto(core::ObscuranceStatement(a), f->mutable_accuracy());
  if (a.plan) ToProto(*a.plan, f->mutable_accuracy());

  // The figures alone, then each array's chunks.
  ChunkedResponses<v1::ComputeObscurancesResponse> stream(std::move(figures), /*first_carries_chunk=*/false);
  stream.Keep(kept);
  using Message = v1::ComputeObscurancesResponse;
  if (!a.result) {
    stream.Add(a.partial.sums.size(), [&a](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(a.partial.sums, b, e, m.mutable_partial_sums());
    });
    stream.Add(a.partial.counts.size(), [&a](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(a.partial.counts, b, e, m.mutable_partial_counts());
    });
    return stream;
  }
  const obscurance::ObscuranceResult& r = *a.result;
  // Per-texel and per-triangle colors go as x, y, z floats (offsets count floats).
  auto add_vec3s = [&stream](const std::vector<glm::vec3>& values, auto field) {
    stream.Add(3 * values.size(), [&values, field](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddFlattenedRange(values, b, e, (m.*field)());
    });
  };
  add_vec3s(r.w, &Message::mutable_w);
  add_vec3s(r.intensity, &Message::mutable_intensity);
  stream.Add(r.estimated.size(), [&r](Message& m, size_t b, size_t e) {
    m.set_offset(b);
    m.set_estimated(std::string(reinterpret_cast<const char*>(r.estimated.data() + b), e - b));
  });
  if (want_averages) {
    add_vec3s(r.triangle_w, &Message::mutable_triangle_w);
    add_vec3s(r.vertex_w, &Message::mutable_vertex_w);
  }
  auto add_floats = [&stream](const std::vector<float>& values, auto field) {
    stream.Add(values.size(), [&values, field](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(values, b, e, (m.*field)());
    });
  };
  if (want_errors) {
    add_floats(a.bounds.texel, &Message::mutable_w_error);
    if (want_averages) {
      add_floats(a.bounds.triangle, &Message::mutable_triangle_w_error);
      add_floats(a.bounds.vertex, &Message::mutable_vertex_w_error);
    }
  }
  return stream;
}

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
    const double compute_ms = answer.atlas_ms + answer.bake_ms + answer.finalize_ms + answer.updater_ms;
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

void ToProto(const core::ObscuranceUpdateAnswer& a, v1::UpdateObscurancesResponse* out) {
  const obscurance::ObscuranceUpdate& u = a.update;
  out->set_from_version(a.from_version);
  out->set_scene_version(a.scene_version);
  out->set_moves_applied(a.moves_applied);
  out->mutable_texels()->Add(u.texels.begin(), u.texels.end());
  for (const glm::vec3& v : u.w) AddVec3(v, out->mutable_w());
  for (const glm::vec3& v : u.intensity) AddVec3(v, out->mutable_intensity());
  out->mutable_triangles()->Add(u.triangles.begin(), u.triangles.end());
  for (const glm::vec3& v : u.triangle_w) AddVec3(v, out->mutable_triangle_w());
  out->mutable_vertices()->Add(u.vertices.begin(), u.vertices.end());
  for (const glm::vec3& v : u.vertex_w) AddVec3(v, out->mutable_vertex_w());
  out->set_influenced_before(u.influenced_before);
  out->set_influenced_after(u.influenced_after);
  out->set_own_patches(u.own_patches);
  out->set_candidates(u.candidates);
  out->set_recomputed(u.recomputed);
  out->set_rays(u.rays);
  out->set_rays_per_patch(a.rays_per_patch);
  out->set_width(a.width);
  out->set_height(a.height);
  for (const glm::vec3& v : a.full_w) AddVec3(v, out->mutable_full_w());
  out->mutable_w_error()->Add(a.bounds.texel.begin(), a.bounds.texel.end());
  out->mutable_triangle_w_error()->Add(a.bounds.triangle.begin(), a.bounds.triangle.end());
  out->mutable_vertex_w_error()->Add(a.bounds.vertex.begin(), a.bounds.vertex.end());
  service::ToProto(core::ObscuranceUpdateStatement(a), out->mutable_accuracy());
}

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
    // A call whose client gave up while it queued does not move the node.
    VISQ_RETURN_IF_ERROR(CallOptionsFor(context, &cancelled, log).stop.Check("SetNodeTransform: before the move"));
    core::NodeTransformQuery query;
    query.scene = request->scene().name();
    query.scene_version = request->scene().version();
    if (request->node_case() == v1::SetNodeTransformRequest::kNodeName) query.node_name = request->node_name();
    if (request->node_case() == v1::SetNodeTransformRequest::kNodeIndex) query.node_index = request->node_index();
    query.world_matrix.assign(request->world_matrix().begin(), request->world_matrix().end());
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
    core::ObscuranceUpdateQuery query;
    query.scene = request->scene().name();
    query.scene_version = request->scene().version();
    query.want_full_w = request->want_full_w();
    query.call = CallOptionsFor(context, &cancelled, log);
    VISQ_ASSIGN_OR_RETURN(core::ObscuranceUpdateAnswer answer, core::RunUpdateObscurances(ctx_.engine, query));
    const double before_transfer = log.ElapsedMs();
    ToProto(answer, response);
    auto* timing = response->mutable_timing();
    timing->set_queue_ms(queue_ms);
    timing->set_compute_ms(answer.compute_ms);
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
        const double image_queue_ms = answer.image.queue_ms;
        const double compute_ms = answer.copy_ms + answer.image.total_ms - answer.image.queue_ms;
        ChunkedResponses<v1::ObscurancePreviewResponse> messages = ToProtoStream(std::move(answer));
        SetStreamTiming(queue_ms + image_queue_ms, compute_ms, query.call.BuildMs(), before_transfer, log,
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
        const double compute_ms = answer.copy_ms + answer.export_ms;
        ChunkedResponses<v1::ExportObscurancesResponse> messages = ToProtoStream(std::move(answer));
        SetStreamTiming(queue_ms, compute_ms, query.call.BuildMs(), before_transfer, log, messages.first().mutable_timing());
        return messages;
      });
}

}  // namespace visq::service
