#include "service/server.h"

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

namespace visq::service {

StatusOr<std::unique_ptr<Server>> Server::Create(const ServerOptions& options) {
  std::unique_ptr<Server> server(new Server());
  server->options_ = options;
  VISQ_ASSIGN_OR_RETURN(server->engine_, Engine::Create(options.engine));
  server->executor_ = std::make_unique<Executor>(options.worker_threads);
  server->service_ = std::make_unique<VisibilityServiceImpl>(*server->engine_, *server->executor_);

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(options.address, grpc::InsecureServerCredentials(), &server->port_);
  builder.SetMaxReceiveMessageSize(options.max_receive_message_bytes);
  builder.RegisterService(server->service_.get());
  server->grpc_server_ = builder.BuildAndStart();
  if (!server->grpc_server_ || server->port_ == 0)
    return absl::UnavailableError(absl::StrCat("cannot listen on ", options.address));
  server->SetServing(false);
  spdlog::info("listening on {} (port {}), health NOT_SERVING until scenes are loaded", options.address,
               server->port_);
  if (options.address.rfind("127.", 0) != 0 && options.address.rfind("localhost", 0) != 0 &&
      options.address.rfind("[::1]", 0) != 0)
    spdlog::warn("listening beyond loopback without TLS or authentication");
  return server;
}

Server::~Server() { GracefulStop(std::chrono::seconds(5)); }

void Server::SetServing(bool serving) {
  auto* health = grpc_server_->GetHealthCheckService();
  if (health == nullptr) return;
  health->SetServingStatus(serving);  // every service, including ""
  health->SetServingStatus(v1::VisibilityService::service_full_name(), serving);
}

void Server::Ready() {
  engine_->LoadRepositoryScenes();
  SetServing(true);
  spdlog::info("ready: {} scene(s) resident, health SERVING", engine_->ListScenes().size());
}

void Server::GracefulStop(std::chrono::milliseconds drain) {
  if (stopped_) return;
  stopped_ = true;
  // Order: refuse new work (health), drain gRPC, drain the executor, then
  // the engine (and its GL thread) goes with this object.
  SetServing(false);
  spdlog::info("shutting down: health NOT_SERVING, draining requests for up to {} ms", drain.count());
  grpc_server_->Shutdown(std::chrono::system_clock::now() + drain);
  grpc_server_->Wait();
  executor_.reset();
  spdlog::info("shut down");
}

}  // namespace visq::service
