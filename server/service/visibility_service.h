// visq.v1.VisibilityService over the core Engine: converts messages,
// validates what protobuf cannot, and hands blocking work to the executor so
// gRPC's callback threads never wait on the disk or the GPU.
#pragma once

#include "core/engine.h"
#include "service/executor.h"
#include "visq/v1/visq.grpc.pb.h"

namespace visq::service {

class VisibilityServiceImpl final : public v1::VisibilityService::CallbackService {
 public:
  VisibilityServiceImpl(Engine& engine, Executor& executor) : engine_(engine), executor_(executor) {}

  grpc::ServerReadReactor<v1::LoadSceneRequest>* LoadScene(grpc::CallbackServerContext* context,
                                                           v1::SceneInfo* response) override;
  grpc::ServerUnaryReactor* ListScenes(grpc::CallbackServerContext* context, const v1::ListScenesRequest* request,
                                       v1::ListScenesResponse* response) override;
  grpc::ServerUnaryReactor* GetScene(grpc::CallbackServerContext* context, const v1::GetSceneRequest* request,
                                     v1::SceneInfo* response) override;
  grpc::ServerUnaryReactor* UnloadScene(grpc::CallbackServerContext* context,
                                        const v1::UnloadSceneRequest* request,
                                        v1::UnloadSceneResponse* response) override;

 private:
  Engine& engine_;
  Executor& executor_;
};

// Core summary -> wire message (shared by the scene RPCs).
void ToProto(const SceneSummary& summary, v1::SceneInfo* out);

}  // namespace visq::service
