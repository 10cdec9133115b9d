#include "service/server.h"

#include <fstream>
#include <sstream>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

namespace visq::service {

namespace {

bool IsLoopback(const std::string& address) {
  return address.rfind("127.", 0) == 0 || address.rfind("localhost:", 0) == 0 || address.rfind("[::1]:", 0) == 0;
}

StatusOr<std::string> ReadFile(const std::string& path, const char* what) {
  std::ifstream in(path);
  if (!in) return absl::InvalidArgumentError(absl::StrCat(what, " ", path, ": cannot read"));
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

StatusOr<std::shared_ptr<grpc::ServerCredentials>> Credentials(const TlsOptions& tls) {
  if (tls.cert_file.empty() && tls.key_file.empty()) {
    if (!tls.client_ca_file.empty()) return absl::InvalidArgumentError("--tls-client-ca needs --tls-cert and --tls-key");
    return grpc::InsecureServerCredentials();
  }
  if (tls.cert_file.empty() || tls.key_file.empty())
    return absl::InvalidArgumentError("TLS needs both --tls-cert and --tls-key");
  grpc::SslServerCredentialsOptions ssl(tls.client_ca_file.empty()
                                            ? GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE
                                            : GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  VISQ_ASSIGN_OR_RETURN(std::string cert, ReadFile(tls.cert_file, "--tls-cert"));
  VISQ_ASSIGN_OR_RETURN(std::string key, ReadFile(tls.key_file, "--tls-key"));
  ssl.pem_key_cert_pairs.push_back({key, cert});
  if (!tls.client_ca_file.empty()) {
    VISQ_ASSIGN_OR_RETURN(ssl.pem_root_certs, ReadFile(tls.client_ca_file, "--tls-client-ca"));
  }
  return grpc::SslServerCredentials(ssl);
}

}  // namespace

StatusOr<std::unique_ptr<Server>> Server::Create(const ServerOptions& options) {
  const bool tls = !options.tls.cert_file.empty();
  if (!IsLoopback(options.address) && !tls && options.auth_token.empty() && !options.allow_insecure_remote)
    return absl::FailedPreconditionError(absl::StrCat(
        "refusing to listen on ", options.address,
        " without TLS or a bearer token; set --tls-cert/--tls-key, --auth-token-file, or --allow-insecure-remote"));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<grpc::ServerCredentials> credentials, Credentials(options.tls));

  std::unique_ptr<Server> server(new Server());
  server->options_ = options;
  VISQ_ASSIGN_OR_RETURN(server->engine_, Engine::Create(options.engine));
  server->executor_ = std::make_unique<Executor>(options.worker_threads);
  server->metrics_ = std::make_unique<Metrics>();
  server->authorizer_ = std::make_unique<Authorizer>(options.auth_token);

  grpc::EnableDefaultHealthCheckService(true);
  // Reflection lists the API to anyone who asks: only without a token.
  if (options.auth_token.empty()) grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(options.address, credentials, &server->port_);
  builder.SetMaxReceiveMessageSize(options.max_receive_message_bytes);
  // The service is registered before the port is known; its id is fixed up
  // below when it defaults to host:port.
  std::string server_id = options.server_id;
  auto service_context = [&] {
    return ServiceContext{*server->engine_, *server->executor_, *server->metrics_, *server->authorizer_, server_id};
  };
  server->service_ = std::make_unique<VisibilityServiceImpl>(service_context());
  builder.RegisterService(server->service_.get());
  server->grpc_server_ = builder.BuildAndStart();
  if (!server->grpc_server_ || server->port_ == 0)
    return absl::UnavailableError(absl::StrCat("cannot listen on ", options.address));
  if (server_id.empty()) {
    server_id = options.address.substr(0, options.address.rfind(':')) + ":" + std::to_string(server->port_);
    server->service_->set_server_id(server_id);
  }
  server->SetServing(false);
  spdlog::info("listening on {} (port {}, {}{}), health NOT_SERVING until scenes are loaded", options.address,
               server->port_, tls ? (options.tls.client_ca_file.empty() ? "TLS" : "mutual TLS") : "plaintext",
               options.auth_token.empty() ? "" : ", bearer token required");
  if (IsLoopback(options.address)) spdlog::info("loopback only: other machines cannot reach this server");
  else if (!tls && options.auth_token.empty())
    spdlog::warn("listening beyond loopback without TLS or a token (--allow-insecure-remote)");
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
