// The visq server's lifecycle: Create() starts the engine (GL thread, scene
// repository) and the gRPC listener with health NOT_SERVING; Ready() loads
// the repository's scenes and turns health to SERVING; GracefulStop() turns
// it back to NOT_SERVING, drains requests, and shuts down in order.
#pragma once

#include <memory>
#include <string>

#include <grpcpp/server.h>

#include "core/engine.h"
#include "service/executor.h"
#include "service/metrics_http.h"
#include "service/reflection_v1.h"
#include "service/upload_limits.h"
#include "service/visibility_service.h"

namespace visq::service {

struct TlsOptions {
  std::string cert_file;       // PEM server certificate chain; TLS on when set
  std::string key_file;        // PEM private key
  std::string client_ca_file;  // PEM CA: when set, clients must present a certificate it signed (mutual TLS)
};

struct ServerOptions {
  std::string address = "127.0.0.1:50051";
  int max_receive_message_bytes = 16 << 20;  // chunked uploads keep messages small
  int worker_threads = 4;
  std::string server_id;         // reported by GetStats; default host:port
  std::string auth_token;        // bearer token required on every visq.v1 call when set
  TlsOptions tls;
  bool allow_insecure_remote = false;  // listen beyond loopback without TLS and token
  // HOST:PORT for Prometheus's GET /metrics (plain HTTP); empty: no endpoint.
  std::string metrics_address;
  bool allow_remote_metrics = false;  // metrics_address may be beyond loopback
  MetricsHttpLimits metrics_limits;
  // What one client may hold: connections are pinged when quiet and closed
  // when dead or idle, streams per connection are capped, and uploads are
  // capped and aborted when they send nothing (UploadLimits).
  int keepalive_seconds = 60;             // --keepalive-seconds: ping a quiet connection this often
  int keepalive_timeout_seconds = 20;     // --keepalive-timeout-seconds: close it when the ping goes unanswered
  int max_connection_idle_seconds = 300;  // --max-connection-idle-seconds: close a connection with no call
  int max_streams_per_connection = 128;   // --max-streams-per-connection
  UploadLimits::Options uploads;
  core::EngineOptions engine;
};

// Whether HOST:PORT (or a unix: address) can only be reached from this
// machine: every address the host resolves to is loopback.
bool IsLoopbackAddress(const std::string& address);

class Server {
 public:
  [[nodiscard]] static StatusOr<std::unique_ptr<Server>> Create(const ServerOptions& options);
  ~Server();

  // Loads the repository's scenes, then reports SERVING.
  void Ready();
  // The port actually bound (useful with port 0).
  int port() const { return port_; }
  // The /metrics port bound, 0 without one.
  int metrics_port() const { return metrics_http_ ? metrics_http_->port() : 0; }
  void GracefulStop(std::chrono::milliseconds drain);
  core::Engine& engine() { return *engine_; }

  // The process's end: GracefulStop, then this server's own state released
  // (the engine, its GL context, the catalog), then the process exits with
  // `exit_code` without gRPC's library teardown, which can wait seconds for
  // nothing this server needs (server.cpp says why).
  [[noreturn]] static void StopAndExit(std::unique_ptr<Server> server, std::chrono::milliseconds drain,
                                       int exit_code);

 private:
  Server() = default;
  void SetServing(bool serving);

  ServerOptions options_;
  std::unique_ptr<core::Engine> engine_;
  std::unique_ptr<Executor> executor_;
  std::unique_ptr<Executor> metadata_executor_;
  std::unique_ptr<Metrics> metrics_;
  std::unique_ptr<Authorizer> authorizer_;
  std::unique_ptr<CallRegistry> calls_ = std::make_unique<CallRegistry>();
  std::unique_ptr<UploadLimits> uploads_;
  std::unique_ptr<VisibilityServiceImpl> service_;
  std::unique_ptr<ReflectionV1Service> reflection_v1_;
  std::unique_ptr<grpc::Server> grpc_server_;
  std::unique_ptr<MetricsHttpServer> metrics_http_;
  int port_ = 0;
  bool stopped_ = false;
};

}  // namespace visq::service
