// visq.v1.VisibilityService over the core Engine: converts messages,
// validates what protobuf cannot, and hands blocking work to the executor so
// gRPC's callback threads never wait on the disk or the GPU.
#pragma once

#include <chrono>

#include "core/engine.h"
#include "service/auth.h"
#include "service/call_registry.h"
#include "service/executor.h"
#include "service/metrics.h"
#include "service/stats.h"
#include "service/upload_limits.h"
#include "visq/v1/visq.grpc.pb.h"

namespace visq::service {

// What every handler needs; owned by the Server.
struct ServiceContext {
  core::Engine& engine;
  Executor& executor;           // calls that compute
  Executor& metadata_executor;  // calls that compute nothing: never queued behind those that do
  Metrics& metrics;
  const Authorizer& authorizer;
  CallRegistry& calls;          // in flight, for the end of the drain
  UploadLimits& uploads;        // uploads in flight and their idle limit
  std::string server_id;
  std::chrono::steady_clock::time_point started = std::chrono::steady_clock::now();
};

// LoadScene is the raw method (bytes in, bytes out): the reactor parses its
// messages itself, so one that does not parse is an error, not an end.
class VisibilityServiceImpl final
    : public v1::VisibilityService::WithRawCallbackMethod_LoadScene<v1::VisibilityService::CallbackService> {
 public:
  explicit VisibilityServiceImpl(ServiceContext context) : ctx_(std::move(context)) {}
  // Before the server starts serving only.
  void set_server_id(std::string id) { ctx_.server_id = std::move(id); }
  // What GetStats reports, for the other transports (/metrics).
  ServerFigures Figures() const { return CollectServerFigures(ctx_); }

  grpc::ServerReadReactor<grpc::ByteBuffer>* LoadScene(grpc::CallbackServerContext* context,
                                                       grpc::ByteBuffer* response) override;
  grpc::ServerUnaryReactor* ListScenes(grpc::CallbackServerContext* context, const v1::ListScenesRequest* request,
                                       v1::ListScenesResponse* response) override;
  grpc::ServerUnaryReactor* GetScene(grpc::CallbackServerContext* context, const v1::GetSceneRequest* request,
                                     v1::SceneInfo* response) override;
  grpc::ServerUnaryReactor* UnloadScene(grpc::CallbackServerContext* context,
                                        const v1::UnloadSceneRequest* request,
                                        v1::UnloadSceneResponse* response) override;
  grpc::ServerWriteReactor<v1::HiddenSampleMapResponse>* HiddenSampleMap(
      grpc::CallbackServerContext* context, const v1::HiddenSampleMapRequest* request) override;
  grpc::ServerUnaryReactor* PatchVisibility(grpc::CallbackServerContext* context,
                                            const v1::PatchVisibilityRequest* request,
                                            v1::PatchVisibilityResponse* response) override;
  grpc::ServerWriteReactor<v1::VoxelizeResponse>* Voxelize(grpc::CallbackServerContext* context,
                                                           const v1::VoxelizeRequest* request) override;
  grpc::ServerUnaryReactor* Transmittance(grpc::CallbackServerContext* context,
                                          const v1::TransmittanceRequest* request,
                                          v1::TransmittanceResponse* response) override;
  grpc::ServerWriteReactor<v1::VolumetricShadowResponse>* VolumetricShadow(
      grpc::CallbackServerContext* context, const v1::VolumetricShadowRequest* request) override;
  grpc::ServerUnaryReactor* LightVisibility(grpc::CallbackServerContext* context,
                                            const v1::LightVisibilityRequest* request,
                                            v1::LightVisibilityResponse* response) override;
  grpc::ServerBidiReactor<v1::LightVisibilityRequest, v1::LightVisibilityResponse>* LightVisibilityStream(
      grpc::CallbackServerContext* context) override;
  // Obscurances: server/service/obscurance_service.cpp.
  grpc::ServerWriteReactor<v1::ComputeObscurancesResponse>* ComputeObscurances(
      grpc::CallbackServerContext* context, const v1::ComputeObscurancesRequest* request) override;
  grpc::ServerUnaryReactor* SetNodeTransform(grpc::CallbackServerContext* context,
                                             const v1::SetNodeTransformRequest* request,
                                             v1::SceneInfo* response) override;
  grpc::ServerUnaryReactor* UpdateObscurances(grpc::CallbackServerContext* context,
                                              const v1::UpdateObscurancesRequest* request,
                                              v1::UpdateObscurancesResponse* response) override;
  grpc::ServerWriteReactor<v1::ObscurancePreviewResponse>* RenderObscurancePreview(
      grpc::CallbackServerContext* context, const v1::ObscurancePreviewRequest* request) override;
  grpc::ServerWriteReactor<v1::ExportObscurancesResponse>* ExportObscurances(
      grpc::CallbackServerContext* context, const v1::ExportObscurancesRequest* request) override;
  grpc::ServerUnaryReactor* GetStats(grpc::CallbackServerContext* context, const v1::GetStatsRequest* request,
                                     v1::ServerStats* response) override;

 private:
  ServiceContext ctx_;
};

// Core summary -> wire message (shared by the scene RPCs).
void ToProto(const core::SceneSummary& summary, v1::SceneInfo* out);

}  // namespace visq::service
