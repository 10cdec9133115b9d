#include "service/visibility_service.h"

#include <functional>
#include <memory>
#include <optional>

#include <absl/strings/str_format.h>
#include <grpcpp/support/proto_buffer_reader.h>

#include "common/version.h"
#include "core/light_visibility_query.h"
#include "core/volumetric_query.h"
#include "core/voxel_query.h"
#include "service/banded_stream.h"
#include "service/convert.h"
#include "service/exception_boundary.h"
#include "service/parse_failure.h"
#include "service/reactors.h"
#include "service/stats.h"
#include "service/request_log.h"
#include "service/status_conversion.h"

namespace visq::service {
namespace {

// LoadSceneHeader.warm as the core takes it; INVALID_ARGUMENT naming the
// entry for a value this server does not know.
StatusOr<std::vector<core::StructureKind>> WarmFromProto(const v1::LoadSceneHeader& header) {
  std::vector<core::StructureKind> kinds;
  for (int i = 0; i < header.warm_size(); ++i) {
    switch (header.warm(i)) {
      case v1::GPU_BUFFERS: kinds.push_back(core::StructureKind::kGpuBuffers); break;
      case v1::EMBREE_BVH: kinds.push_back(core::StructureKind::kEmbreeBvh); break;
      case v1::TRIANGLE_INDEX: kinds.push_back(core::StructureKind::kTriangleIndex); break;
      default:
        return absl::InvalidArgumentError(absl::StrCat("header.warm[", i, "]: unknown structure ", header.warm(i),
                                                       " (GPU_BUFFERS, EMBREE_BVH or TRIANGLE_INDEX)"));
    }
  }
  return kinds;
}

// Client-streamed scene load: a header, then (for uploads) file chunks.
// The messages arrive as bytes and are parsed here: gRPC's generated reader
// reports a message it cannot parse as the end of the stream, which would
// commit an upload the client is still sending.
class LoadSceneReactor final : public grpc::ServerReadReactor<grpc::ByteBuffer> {
 public:
  LoadSceneReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx, grpc::ByteBuffer* response)
      : context_(context),
        log_(context, "LoadScene", &ctx.metrics),
        engine_(ctx.engine),
        executor_(ctx.executor),
        uploads_(ctx.uploads),
        response_(response),
        calls_(ctx.calls) {
    calls_.WorkBegan();
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    // Refuse before a single chunk is stored.
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Fail(authorized);
      return;
    }
    // A stream that sends nothing for the idle limit is cancelled: its read
    // ends, and the upload with its staging goes (EndOfStream).
    watch_ = uploads_.StartWatch([this] {
      idle_ = true;
      context_->TryCancel();
    });
    StartRead(&received_);
  }

  void OnReadDone(bool ok) override {
    // A failed read is a half-close, a cancellation or a broken stream (an
    // oversize message): only the first may commit. A message that does not
    // parse arrives as bytes (ok), so it never looks like the end.
    if (!ok) {
      EndOfStream();
      return;
    }
    watch_->Touch();
    ++messages_read_;
    Status status = CatchExceptions(log_.id(), "LoadScene", [&] { return Parse(); });
    if (status.ok()) status = CatchExceptions(log_.id(), "LoadScene", [&] { return Consume(); });
    if (!status.ok()) {
      Fail(status);
      return;
    }
    StartRead(&received_);
  }

  void OnDone() override {
    calls_.WorkEnded();
    delete this;
  }
  void OnCancel() override { cancelled_ = true; }

 private:
  bool Cancelled() const { return cancelled_ || context_->IsCancelled(); }

  // received_ -> request_; INVALID_ARGUMENT naming the field (or saying
  // the message is cut short) for bytes that are not a LoadSceneRequest.
  Status Parse() {
    request_.Clear();
    grpc::ProtoBufferReader reader(&received_);
    const bool parsed = request_.ParseFromZeroCopyStream(&reader);
    if (parsed) {
      received_.Clear();
      return absl::OkStatus();
    }
    std::string bytes;
    std::vector<grpc::Slice> slices;
    if (received_.Dump(&slices).ok())
      for (const grpc::Slice& slice : slices) bytes.append(reinterpret_cast<const char*>(slice.begin()), slice.size());
    received_.Clear();
    return absl::InvalidArgumentError(absl::StrCat(DescribeParseFailure(*v1::LoadSceneRequest::descriptor(), bytes),
                                                   " (LoadScene message ", messages_read_, "): nothing stored"));
  }

  Status Consume() {
    if (!header_seen_) {
      if (!request_.has_header()) return absl::InvalidArgumentError("the first LoadScene message must be a header");
      header_seen_ = true;
      const v1::LoadSceneHeader& header = request_.header();
      name_ = header.name();
      replace_ = header.replace();
      VISQ_ASSIGN_OR_RETURN(warm_, WarmFromProto(header));
      switch (header.source_case()) {
        case v1::LoadSceneHeader::kFromRepository:
          from_repository_ = true;
          log_.Info("'{}' from the repository", name_);
          return absl::OkStatus();
        case v1::LoadSceneHeader::kUploadMainFile: {
          log_.Info("'{}' upload of {} ({} bytes announced)", name_, header.upload_main_file(),
                    header.expected_bytes());
          VISQ_ASSIGN_OR_RETURN(slot_, uploads_.Acquire(UploadLimits::ClientOfPeer(context_->peer())));
          VISQ_ASSIGN_OR_RETURN(upload_, engine_.BeginUpload(name_, header.upload_main_file(), header.replace(),
                                                             header.expected_bytes()));
          return absl::OkStatus();
        }
        default:
          return absl::InvalidArgumentError("header: set from_repository or upload_main_file");
      }
    }
    if (!request_.has_chunk()) return absl::InvalidArgumentError("only the first LoadScene message may be a header");
    if (from_repository_) return absl::InvalidArgumentError("a load from the repository takes no file chunks");
    return upload_->Append(request_.chunk().file(), request_.chunk().data());
  }

  void EndOfStream() {
    if (watch_) watch_->Stop();
    if (idle_) {
      const double seconds = uploads_.options().idle.count() / 1000.0;
      Fail(absl::DeadlineExceededError(
          absl::StrCat("LoadScene sent nothing for ", seconds, " s (--upload-idle-seconds): aborted, nothing stored")));
      return;
    }
    if (!header_seen_) {
      Fail(absl::InvalidArgumentError("LoadScene stream ended without a header"));
      return;
    }
    if (Cancelled()) {
      Fail(absl::CancelledError("LoadScene was cancelled or cut off before it completed: nothing stored"));
      return;
    }
    // Parsing and storing block: off the callback thread.
    executor_.Post([this] {
      StatusOr<core::SceneSummary> summary = CatchExceptions(log_.id(), "LoadScene", [&] {
        return from_repository_ ? engine_.LoadFromRepository(name_, replace_)
                                : engine_.FinishUpload(std::move(upload_), StopToken{&cancelled_, SteadyDeadline(context_)});
      });
      slot_.reset();  // stored or not, the upload is no longer in flight
      // The structures build in the background; the answer does not wait.
      if (summary.ok() && !warm_.empty()) {
        if (Status warming = engine_.Warm(summary->name, summary->version, warm_); !warming.ok())
          log_.Info("not warmed: {}", warming.message());
      }
      if (!summary.ok()) {
        Fail(summary.status());
        return;
      }
      v1::SceneInfo info;
      ToProto(*summary, &info);
      bool own_buffer = false;
      if (grpc::Status serialized = grpc::SerializationTraits<v1::SceneInfo>::Serialize(info, response_, &own_buffer);
          !serialized.ok()) {
        Fail(absl::InternalError(absl::StrCat("the answer did not serialize: ", serialized.error_message())));
        return;
      }
      log_.Done(absl::OkStatus());
      Finish(grpc::Status::OK);
    });
  }

  void Fail(const Status& status) {
    slot_.reset();
    upload_.reset();  // removes the staged files
    log_.Done(status);
    Finish(ToGrpcStatus(status));
  }

  grpc::CallbackServerContext* context_;
  RequestLog log_;
  core::Engine& engine_;
  Executor& executor_;
  UploadLimits& uploads_;
  grpc::ByteBuffer* response_;
  CallRegistry& calls_;
  grpc::ByteBuffer received_;
  uint64_t messages_read_ = 0;
  v1::LoadSceneRequest request_;
  std::atomic<bool> cancelled_{false};
  bool header_seen_ = false;
  bool from_repository_ = false;
  bool replace_ = false;
  std::string name_;
  std::vector<core::StructureKind> warm_;
  std::unique_ptr<UploadLimits::Slot> slot_;  // while an upload is in flight
  std::unique_ptr<core::SceneUpload> upload_;
  std::atomic<bool> idle_{false};
  // Last: it goes first, and waits for an idle cancellation in progress.
  std::unique_ptr<UploadLimits::Watch> watch_;
};

}  // namespace

void ToProto(const core::SceneSummary& s, v1::SceneInfo* out) {
  out->set_name(s.name);
  out->set_version(s.version);
  out->set_triangle_count(s.triangles);
  out->set_vertex_count(s.vertices);
  ToProto(s.bounds.min, out->mutable_bounds_min());
  ToProto(s.bounds.max, out->mutable_bounds_max());
  out->set_content_hash(s.content_hash);
  out->mutable_memory()->set_cpu_bytes(s.cpu_bytes);
  out->mutable_memory()->set_gpu_bytes(s.gpu_bytes);
  out->mutable_estimated_memory()->set_cpu_bytes(s.estimate.cpu_bytes());
  out->mutable_estimated_memory()->set_gpu_bytes(s.estimate.gpu_bytes);
  out->set_unique_triangle_count(s.estimate.unique_triangles);
  out->set_instance_count(s.estimate.instances);
  out->set_material_count(s.materials);
  out->set_emissive_triangle_count(s.emissive_triangles);
  out->set_has_lightmap_uvs(s.has_lightmap_uvs);
  for (const auto& d : s.dropped) out->add_dropped(d);
  out->set_load_ms(s.load_ms);
  out->set_persisted(s.persisted);
  for (const auto& n : s.nodes) {
    auto* node = out->add_nodes();
    node->set_name(n.name);
    node->set_gltf_index(n.gltf_index);
    node->set_parent(n.parent);
    node->set_triangle_count(n.triangle_count);
  }
}

grpc::ServerReadReactor<grpc::ByteBuffer>* VisibilityServiceImpl::LoadScene(grpc::CallbackServerContext* context,
                                                                           grpc::ByteBuffer* response) {
  return new LoadSceneReactor(context, ctx_, response);
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::ListScenes(grpc::CallbackServerContext* context,
                                                            const v1::ListScenesRequest*,
                                                            v1::ListScenesResponse* response) {
  return RunUnaryCall(ctx_, context, "ListScenes", [this, response](RequestLog&) {
    for (const auto& summary : ctx_.engine.ListScenes()) ToProto(summary, response->add_scenes());
    return absl::OkStatus();
  }, Lane::kMetadata);
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::GetScene(grpc::CallbackServerContext* context,
                                                          const v1::GetSceneRequest* request,
                                                          v1::SceneInfo* response) {
  return RunUnaryCall(ctx_, context, "GetScene", [this, request, response](RequestLog& log) -> Status {
    log.Info("'{}'", request->name());
    VISQ_ASSIGN_OR_RETURN(core::SceneSummary summary,
                          ctx_.engine.GetScene(request->name(), request->include_nodes(), request->load_if_stored()));
    ToProto(summary, response);
    return absl::OkStatus();
  }, Lane::kMetadata);
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::UnloadScene(grpc::CallbackServerContext* context,
                                                             const v1::UnloadSceneRequest* request,
                                                             v1::UnloadSceneResponse* response) {
  return RunUnaryCall(ctx_, context, "UnloadScene", [this, request, response](RequestLog& log) -> Status {
    log.Info("'{}'{}", request->name(), request->delete_from_repository() ? " (and delete)" : "");
    VISQ_ASSIGN_OR_RETURN(bool deleted, ctx_.engine.UnloadScene(request->name(), request->delete_from_repository()));
    response->set_deleted_from_repository(deleted);
    return absl::OkStatus();
  }, Lane::kMetadata);
}

}  // namespace visq::service

namespace visq::service {

grpc::ServerUnaryReactor* VisibilityServiceImpl::GetStats(grpc::CallbackServerContext* context,
                                                          const v1::GetStatsRequest*, v1::ServerStats* response) {
  return RunUnaryCall(ctx_, context, "GetStats", [this, response](RequestLog&) {
    const ServerFigures f = CollectServerFigures(ctx_);
    response->set_server_id(f.server_id);
    response->set_server_version(f.version);
    response->set_build_commit(f.build_commit);
    response->set_uptime_s(f.uptime_s);
    response->set_gpu_vendor(f.device.gl_vendor);
    response->set_gpu_renderer(f.device.gl_renderer);
    response->set_gl_version(f.device.gl_version);
    response->set_egl_device(f.device.egl_device);
    response->set_gpu_software(f.device.software);
    response->set_gpu_queue_depth(static_cast<uint32_t>(f.gpu_queue_depth));
    response->set_gpu_contexts_lost(f.gpu_contexts_lost);
    response->set_worker_queue_depth(static_cast<uint32_t>(f.worker_queue_depth));
    response->set_scenes_resident(static_cast<uint32_t>(f.scenes_resident));
    response->mutable_scene_memory()->set_cpu_bytes(f.scene_cpu_bytes);
    response->mutable_scene_memory()->set_gpu_bytes(f.scene_gpu_bytes);
    for (const CacheFigures& c : f.caches) {
      auto* cache = response->add_caches();
      cache->set_name(c.name);
      cache->set_entries(c.entries);
      cache->set_bytes(c.bytes);
      cache->set_capacity_bytes(c.capacity_bytes);
      cache->set_hits(c.hits);
      cache->set_misses(c.misses);
      cache->set_evictions(c.evictions);
    }
    for (const auto& [kind, b] : f.structure_builds) {
      auto* out = response->add_structure_builds();
      out->set_structure(kind);
      out->set_builds(b.count);
      out->set_failures(b.failures);
      out->set_in_progress(b.in_progress);
      out->set_total_ms(b.total_ms);
      out->set_max_ms(b.max_ms);
    }
    if (f.idle_exploration) {
      auto* idle = response->mutable_idle_exploration();
      idle->set_probes_run(f.idle_exploration->probes_run);
      idle->set_probes_preempted(f.idle_exploration->probes_preempted);
      idle->set_probes_dropped(f.idle_exploration->probes_dropped);
      idle->set_pending(f.idle_exploration->pending);
      idle->set_total_ms(f.idle_exploration->total_ms);
    }
    for (const auto& m : f.methods) {
      auto* out = response->add_methods();
      out->set_method(m.method);
      out->set_calls(m.calls);
      out->set_errors(m.errors);
      out->set_mean_ms(m.mean_ms);
      out->set_p50_ms(m.p50_ms);
      out->set_p99_ms(m.p99_ms);
      out->set_max_ms(m.max_ms);
    }
    return absl::OkStatus();
  }, Lane::kMetadata);
}

}  // namespace visq::service

namespace visq::service {
namespace {

// One light-visibility batch: convert, run, convert back, with the timing
// breakdown measured from the request's arrival.
Status AnswerLightVisibility(core::Engine& engine, const core::LightVisibilityQuery& query, const RequestLog& log,
                             double queue_ms, v1::LightVisibilityResponse* response) {
  VISQ_ASSIGN_OR_RETURN(core::LightVisibilityAnswer answer, core::RunLightVisibility(engine, query));
  const double before_transfer = log.ElapsedMs();
  ToProto(answer, response);
  auto* cache = response->mutable_cache();
  cache->set_name("light_visibility");
  const core::Engine::LightCacheStats light = engine.light_cache_stats();
  cache->set_entries(light.entries);
  cache->set_bytes(light.bytes);
  cache->set_capacity_bytes(light.capacity_bytes);
  cache->set_hits(light.hits);
  cache->set_misses(light.misses);
  cache->set_evictions(light.evictions);
  auto* timing = response->mutable_timing();
  timing->set_queue_ms(queue_ms + core::WorkTimingOf(answer).queue_ms);
  timing->set_compute_ms(core::WorkTimingOf(answer).compute_ms);
  timing->set_build_ms(query.call.BuildMs());
  timing->set_transfer_ms(log.ElapsedMs() - before_transfer);
  timing->set_total_ms(log.ElapsedMs());
  log.Info("{} point(s), {} tree(s), {} built ({} nodes, {} refinements), {:.2f} ms", query.points.size(),
           answer.trees, answer.trees_created, answer.tree.nodes, answer.tree.refinements, answer.compute_ms);
  return absl::OkStatus();
}

// Batches in, answers out, one at a time and in order.
class LightVisibilityStreamReactor final
    : public grpc::ServerBidiReactor<v1::LightVisibilityRequest, v1::LightVisibilityResponse> {
 public:
  LightVisibilityStreamReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx)
      : log_(context, "LightVisibilityStream", &ctx.metrics), ctx_(ctx), deadline_(SteadyDeadline(context)) {
    // In the registry, so that the drain's end stops the batch at its next
    // point and the call answers UNAVAILABLE (as the unary call does).
    ctx_.calls.Add(&cancelled_);
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Done(authorized);
      return;
    }
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      Done(absl::OkStatus());
      return;
    }
    const double arrived_ms = log_.ElapsedMs();
    ctx_.executor.Post([this, arrived_ms] {
      StatusOr<core::LightVisibilityQuery> query;
      const Status status = CatchExceptions(log_.id(), "LightVisibilityStream", [&]() -> Status {
        query = FromProto(request_, previous_ ? &*previous_ : nullptr);
        response_.Clear();
        VISQ_RETURN_IF_ERROR(query.status());
        query->call = {StopToken{&cancelled_, deadline_}, std::make_shared<core::BuildClock>()};
        return AnswerLightVisibility(ctx_.engine, *query, log_, log_.ElapsedMs() - arrived_ms, &response_);
      });
      if (!status.ok()) {
        Done(status);
        return;
      }
      query->points.clear();
      previous_ = std::move(*query);
      StartWrite(&response_);
    });
  }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      Done(absl::CancelledError("client went away"));
      return;
    }
    StartRead(&request_);
  }

  void OnDone() override {
    ctx_.calls.Remove(&cancelled_);
    delete this;
  }
  void OnCancel() override { cancelled_ = true; }

 private:
  void Done(const Status& given) {
    const Status status = ctx_.calls.Final(given);
    log_.Done(status);
    Finish(ToGrpcStatus(status));
  }

  RequestLog log_;
  const ServiceContext& ctx_;
  v1::LightVisibilityRequest request_;
  v1::LightVisibilityResponse response_;
  std::optional<core::LightVisibilityQuery> previous_;
  std::chrono::steady_clock::time_point deadline_;  // the whole stream's
  std::atomic<bool> cancelled_{false};
};

}  // namespace

grpc::ServerUnaryReactor* VisibilityServiceImpl::LightVisibility(grpc::CallbackServerContext* context,
                                                                 const v1::LightVisibilityRequest* request,
                                                                 v1::LightVisibilityResponse* response) {
  return RunUnaryCall(ctx_, context, "LightVisibility", [this, context, request, response](
                                                             RequestLog& log, const std::atomic<bool>& cancelled) -> Status {
    const double queue_ms = log.ElapsedMs();
    VISQ_ASSIGN_OR_RETURN(core::LightVisibilityQuery query, FromProto(*request));
    query.call = CallOptionsFor(context, &cancelled, log);
    return AnswerLightVisibility(ctx_.engine, query, log, queue_ms, response);
  });
}

grpc::ServerBidiReactor<v1::LightVisibilityRequest, v1::LightVisibilityResponse>*
VisibilityServiceImpl::LightVisibilityStream(grpc::CallbackServerContext* context) {
  return new LightVisibilityStreamReactor(context, ctx_);
}

}  // namespace visq::service

namespace visq::service {

// The streamed answers: each its conversion (convert.h) and its core
// function, over one handler (banded_stream.h).
grpc::ServerWriteReactor<v1::HiddenSampleMapResponse>* VisibilityServiceImpl::HiddenSampleMap(
    grpc::CallbackServerContext* context, const v1::HiddenSampleMapRequest* request) {
  return ServeBandedStream<v1::HiddenSampleMapResponse>(
      ctx_, context, "HiddenSampleMap", request,
      [](core::Engine& engine, const core::HiddenSampleMapQuery& query, const auto& sink) {
        return core::RunHiddenSampleMap(engine, query, sink);
      });
}

grpc::ServerWriteReactor<v1::VolumetricShadowResponse>* VisibilityServiceImpl::VolumetricShadow(
    grpc::CallbackServerContext* context, const v1::VolumetricShadowRequest* request) {
  return ServeBandedStream<v1::VolumetricShadowResponse>(
      ctx_, context, "VolumetricShadow", request,
      [](core::Engine& engine, const core::VolumetricQuery& query, const auto& sink) {
        return core::RunVolumetricShadow(engine, query, sink);
      });
}

grpc::ServerWriteReactor<v1::VoxelizeResponse>* VisibilityServiceImpl::Voxelize(grpc::CallbackServerContext* context,
                                                                                const v1::VoxelizeRequest* request) {
  return ServeBandedStream<v1::VoxelizeResponse>(
      ctx_, context, "Voxelize", request,
      [](core::Engine& engine, const core::VoxelizeQuery& query, const auto& sink) {
        return core::RunVoxelize(engine, query, sink);
      });
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::Transmittance(grpc::CallbackServerContext* context,
                                                               const v1::TransmittanceRequest* request,
                                                               v1::TransmittanceResponse* response) {
  return RunUnaryCall(ctx_, context, "Transmittance", [this, context, request, response](
                                                           RequestLog& log, const std::atomic<bool>& cancelled) -> Status {
    const double queue_ms = log.ElapsedMs();
    VISQ_ASSIGN_OR_RETURN(core::TransmittanceQuery query, FromProto(*request));
    query.call = CallOptionsFor(context, &cancelled, log);
    core::WorkMemoryBudget::Reservation memory;  // until the response is made
    VISQ_ASSIGN_OR_RETURN(core::TransmittanceAnswer answer, core::RunTransmittance(ctx_.engine, query, &memory));
    const double before_transfer = log.ElapsedMs();
    ToProto(answer, response);
    auto* timing = response->mutable_timing();
    const core::WorkTiming work = core::WorkTimingOf(answer);
    timing->set_queue_ms(queue_ms + work.queue_ms);
    timing->set_compute_ms(work.compute_ms);
    timing->set_build_ms(query.call.BuildMs());
    timing->set_transfer_ms(log.ElapsedMs() - before_transfer);
    timing->set_total_ms(log.ElapsedMs());
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::PatchVisibility(grpc::CallbackServerContext* context,
                                                                 const v1::PatchVisibilityRequest* request,
                                                                 v1::PatchVisibilityResponse* response) {
  return RunUnaryCall(ctx_, context, "PatchVisibility", [this, context, request, response](
                                                             RequestLog& log, const std::atomic<bool>& cancelled) -> Status {
    const double queue_ms = log.ElapsedMs();
    VISQ_ASSIGN_OR_RETURN(core::PatchVisibilityQuery query, FromProto(*request));
    query.call = CallOptionsFor(context, &cancelled, log);
    VISQ_ASSIGN_OR_RETURN(core::PatchVisibilityAnswer answer, core::RunPatchVisibility(ctx_.engine, query));
    const sampling::PatchVisibilityResult& result = answer.result;
    const double before_transfer = log.ElapsedMs();
    ToProto(answer, response);
    auto* timing = response->mutable_timing();
    const core::WorkTiming work = core::WorkTimingOf(answer);
    timing->set_queue_ms(queue_ms + work.queue_ms);
    timing->set_compute_ms(work.compute_ms);
    timing->set_build_ms(query.call.BuildMs());
    timing->set_transfer_ms(log.ElapsedMs() - before_transfer);
    timing->set_total_ms(log.ElapsedMs());
    log.Info("{} {} source samples by {}x{} receiver samples: mutual visible fraction {:.4f}",
             core::VisibilityMethodName(answer.method, query.request.lookup), result.source_visible.size(),
             query.request.receiver_columns, query.request.receiver_rows, result.mutual_visible_fraction);
    return absl::OkStatus();
  });
}

}  // namespace visq::service
