#include "service/visibility_service.h"

#include <memory>

#include "service/request_log.h"
#include "service/status_conversion.h"

namespace visq::service {
namespace {

void ToProtoVec(const glm::dvec3& v, v1::Vec3* out) {
  out->set_x(v.x);
  out->set_y(v.y);
  out->set_z(v.z);
}

// Client-streamed scene load: a header, then (for uploads) file chunks.
class LoadSceneReactor final : public grpc::ServerReadReactor<v1::LoadSceneRequest> {
 public:
  LoadSceneReactor(grpc::CallbackServerContext* context, const ServiceContext& ctx, v1::SceneInfo* response)
      : log_(context, "LoadScene", &ctx.metrics), engine_(ctx.engine), executor_(ctx.executor), response_(response) {
    context->AddInitialMetadata("x-visq-server-id", ctx.server_id);
    // Refuse before a single chunk is stored.
    if (Status authorized = ctx.authorizer.Check(*context); !authorized.ok()) {
      Fail(authorized);
      return;
    }
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {  // the client finished sending
      EndOfStream();
      return;
    }
    Status status = Consume();
    if (!status.ok()) {
      Fail(status);
      return;
    }
    StartRead(&request_);
  }

  void OnDone() override { delete this; }

 private:
  Status Consume() {
    if (!header_seen_) {
      if (!request_.has_header()) return absl::InvalidArgumentError("the first LoadScene message must be a header");
      header_seen_ = true;
      const v1::LoadSceneHeader& header = request_.header();
      name_ = header.name();
      replace_ = header.replace();
      switch (header.source_case()) {
        case v1::LoadSceneHeader::kFromRepository:
          from_repository_ = true;
          log_.Info("'{}' from the repository", name_);
          return absl::OkStatus();
        case v1::LoadSceneHeader::kUploadMainFile: {
          log_.Info("'{}' upload of {} ({} bytes announced)", name_, header.upload_main_file(),
                    header.expected_bytes());
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
    if (!header_seen_) {
      Fail(absl::InvalidArgumentError("LoadScene stream ended without a header"));
      return;
    }
    // Parsing and storing block: off the callback thread.
    executor_.Post([this] {
      StatusOr<SceneSummary> summary = from_repository_ ? engine_.LoadFromRepository(name_, replace_)
                                                        : engine_.FinishUpload(std::move(upload_));
      if (summary.ok()) ToProto(*summary, response_);
      if (!summary.ok()) Fail(summary.status());
      else {
        log_.Done(absl::OkStatus());
        Finish(grpc::Status::OK);
      }
    });
  }

  void Fail(const Status& status) {
    upload_.reset();  // removes the staged files
    log_.Done(status);
    Finish(ToGrpcStatus(status));
  }

  RequestLog log_;
  Engine& engine_;
  Executor& executor_;
  v1::SceneInfo* response_;
  v1::LoadSceneRequest request_;
  bool header_seen_ = false;
  bool from_repository_ = false;
  bool replace_ = false;
  std::string name_;
  std::unique_ptr<SceneUpload> upload_;
};

}  // namespace

template <typename Work>
grpc::ServerUnaryReactor* VisibilityServiceImpl::RunUnary(grpc::CallbackServerContext* context, const char* method,
                                                          Work work) {
  context->AddInitialMetadata("x-visq-server-id", ctx_.server_id);
  auto* reactor = context->DefaultReactor();
  auto log = std::make_shared<RequestLog>(context, method, &ctx_.metrics);
  if (Status authorized = ctx_.authorizer.Check(*context); !authorized.ok()) {
    log->Done(authorized);
    reactor->Finish(ToGrpcStatus(authorized));
    return reactor;
  }
  ctx_.executor.Post([reactor, log, work = std::move(work)]() mutable {
    const Status status = work(*log);
    log->Done(status);
    reactor->Finish(ToGrpcStatus(status));
  });
  return reactor;
}

void ToProto(const SceneSummary& s, v1::SceneInfo* out) {
  out->set_name(s.name);
  out->set_version(s.version);
  out->set_triangle_count(s.triangles);
  out->set_vertex_count(s.vertices);
  ToProtoVec(s.bounds.min, out->mutable_bounds_min());
  ToProtoVec(s.bounds.max, out->mutable_bounds_max());
  out->set_content_hash(s.content_hash);
  out->mutable_memory()->set_cpu_bytes(s.cpu_bytes);
  out->mutable_memory()->set_gpu_bytes(s.gpu_bytes);
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

grpc::ServerReadReactor<v1::LoadSceneRequest>* VisibilityServiceImpl::LoadScene(grpc::CallbackServerContext* context,
                                                                                v1::SceneInfo* response) {
  return new LoadSceneReactor(context, ctx_, response);
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::ListScenes(grpc::CallbackServerContext* context,
                                                            const v1::ListScenesRequest*,
                                                            v1::ListScenesResponse* response) {
  return RunUnary(context, "ListScenes", [this, response](RequestLog&) {
    for (const auto& summary : ctx_.engine.ListScenes()) ToProto(summary, response->add_scenes());
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::GetScene(grpc::CallbackServerContext* context,
                                                          const v1::GetSceneRequest* request,
                                                          v1::SceneInfo* response) {
  return RunUnary(context, "GetScene", [this, request, response](RequestLog& log) -> Status {
    log.Info("'{}'", request->name());
    VISQ_ASSIGN_OR_RETURN(SceneSummary summary, ctx_.engine.GetScene(request->name(), request->include_nodes(), request->load_if_stored()));
    ToProto(summary, response);
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* VisibilityServiceImpl::UnloadScene(grpc::CallbackServerContext* context,
                                                             const v1::UnloadSceneRequest* request,
                                                             v1::UnloadSceneResponse* response) {
  return RunUnary(context, "UnloadScene", [this, request, response](RequestLog& log) -> Status {
    log.Info("'{}'{}", request->name(), request->delete_from_repository() ? " (and delete)" : "");
    VISQ_ASSIGN_OR_RETURN(bool deleted, ctx_.engine.UnloadScene(request->name(), request->delete_from_repository()));
    response->set_deleted_from_repository(deleted);
    return absl::OkStatus();
  });
}

}  // namespace visq::service

namespace visq::service {

grpc::ServerUnaryReactor* VisibilityServiceImpl::GetStats(grpc::CallbackServerContext* context,
                                                          const v1::GetStatsRequest*, v1::ServerStats* response) {
  return RunUnary(context, "GetStats", [this, response](RequestLog&) {
    response->set_server_id(ctx_.server_id);
    response->set_uptime_s(
        std::chrono::duration<double>(std::chrono::steady_clock::now() - ctx_.started).count());
    const gpu::DeviceInfo& device = ctx_.engine.device();
    response->set_gpu_vendor(device.gl_vendor);
    response->set_gpu_renderer(device.gl_renderer);
    response->set_gl_version(device.gl_version);
    response->set_egl_device(device.egl_device);
    response->set_gpu_software(device.software);
    response->set_gpu_queue_depth(static_cast<uint32_t>(ctx_.engine.gpu().queue_depth()));
    response->set_worker_queue_depth(static_cast<uint32_t>(ctx_.executor.queued()));
    uint64_t cpu = 0, gpu_bytes = 0;
    const auto scenes = ctx_.engine.ListScenes();
    for (const auto& scene : scenes) {
      cpu += scene.cpu_bytes;
      gpu_bytes += scene.gpu_bytes;
    }
    response->set_scenes_resident(static_cast<uint32_t>(scenes.size()));
    response->mutable_scene_memory()->set_cpu_bytes(cpu);
    response->mutable_scene_memory()->set_gpu_bytes(gpu_bytes);
    for (const auto& m : ctx_.metrics.Summaries()) {
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
  });
}

}  // namespace visq::service
