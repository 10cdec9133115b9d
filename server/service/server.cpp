#include "service/server.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <algorithm>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <mutex>
#include <sstream>
#include <thread>

#include <grpc/grpc.h>
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/impl/server_builder_option.h>
#include <grpcpp/impl/server_builder_plugin.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

namespace visq::service {

namespace {

// Removes the reflection plugin that grpc++_reflection registers for every
// builder at static initialisation: with a token set, reflection would list
// the API to callers that carry none.
class WithoutReflection final : public grpc::ServerBuilderOption {
 public:
  void UpdateArguments(grpc::ChannelArguments*) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override {
    plugins->erase(std::remove_if(plugins->begin(), plugins->end(),
                                  [](const auto& plugin) { return plugin->name() == "proto_server_reflection"; }),
                   plugins->end());
  }
};

}  // namespace

bool IsLoopbackAddress(const std::string& address) {
  if (address.rfind("unix:", 0) == 0 || address.rfind("unix-abstract:", 0) == 0) return true;  // no network
  std::string host = address;
  for (const char* scheme : {"ipv4:", "ipv6:", "dns:"})
    if (host.rfind(scheme, 0) == 0) host = host.substr(std::strlen(scheme));
  const size_t colon = host.rfind(':');
  if (colon == std::string::npos) return false;
  host = host.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  if (host.empty()) return false;  // ":port" listens on every interface
  // Decided on what the name resolves to, not on how it is spelt: every
  // address it resolves to must be loopback.
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* found = nullptr;
  if (::getaddrinfo(host.c_str(), nullptr, &hints, &found) != 0 || found == nullptr) return false;
  bool all_loopback = true;
  for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
    if (a->ai_family == AF_INET) {
      const auto* in = reinterpret_cast<const sockaddr_in*>(a->ai_addr);
      all_loopback &= (ntohl(in->sin_addr.s_addr) >> 24) == 127;
    } else if (a->ai_family == AF_INET6) {
      const auto* in6 = reinterpret_cast<const sockaddr_in6*>(a->ai_addr);
      all_loopback &= IN6_IS_ADDR_LOOPBACK(&in6->sin6_addr) != 0;
    } else {
      all_loopback = false;
    }
  }
  ::freeaddrinfo(found);
  return all_loopback;
}

namespace {

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
  const bool loopback = IsLoopbackAddress(options.address);
  if (!loopback && !tls && options.auth_token.empty() && !options.allow_insecure_remote)
    return absl::FailedPreconditionError(absl::StrCat(
        "refusing to listen on ", options.address,
        " without TLS or a bearer token; set --tls-cert/--tls-key, --auth-token-file, or --allow-insecure-remote"));
  if (!options.metrics_address.empty()) VISQ_RETURN_IF_ERROR(ValidateMetricsAddress(options.metrics_address));
  if (!options.metrics_address.empty() && !options.allow_remote_metrics && !IsLoopbackAddress(options.metrics_address))
    return absl::FailedPreconditionError(absl::StrCat(
        "refusing to serve /metrics on ", options.metrics_address,
        " (not loopback, and plain HTTP without authentication); set --metrics-allow-remote to mean it"));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<grpc::ServerCredentials> credentials, Credentials(options.tls));

  std::unique_ptr<Server> server(new Server());
  server->options_ = options;
  VISQ_ASSIGN_OR_RETURN(server->engine_, core::Engine::Create(options.engine));
  if (core::IdleExplorer* explorer = server->engine_->idle_explorer())
    server->calls_->SetActivityListener([explorer](bool began) { began ? explorer->CallBegan() : explorer->CallEnded(); });
  server->executor_ = std::make_unique<Executor>(options.worker_threads);
  server->metadata_executor_ = std::make_unique<Executor>(2);
  server->metrics_ = std::make_unique<Metrics>();
  server->authorizer_ = std::make_unique<Authorizer>(options.auth_token);
  server->uploads_ = std::make_unique<UploadLimits>(options.uploads);

  grpc::EnableDefaultHealthCheckService(true);
  // Reflection lists the API to anyone who asks: only without a token
  // (v1alpha from gRPC's plugin, v1 from ReflectionV1Service below).
  if (options.auth_token.empty()) grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  if (!options.auth_token.empty()) builder.SetOption(std::make_unique<WithoutReflection>());
  builder.AddListeningPort(options.address, credentials, &server->port_);
  builder.SetMaxReceiveMessageSize(options.max_receive_message_bytes);
  // A port in use is an error, not a port silently shared with another
  // server (gRPC sets SO_REUSEPORT by default).
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  // No client holds what others need: a dead peer's connection is found by
  // keepalive pings, a connection with no call is closed after a while
  // (GOAWAY; clients reconnect), and one connection carries a bounded number
  // of streams at once. Clients may ping as often as every 10 s without
  // being told off, which is what gRPC clients' keepalive allows.
  const auto ms = [](int seconds) { return static_cast<int>(std::min<int64_t>(int64_t{seconds} * 1000, INT32_MAX)); };
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, ms(options.keepalive_seconds));
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, ms(options.keepalive_timeout_seconds));
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 10000);
  if (options.max_connection_idle_seconds > 0)
    builder.AddChannelArgument(GRPC_ARG_MAX_CONNECTION_IDLE_MS, ms(options.max_connection_idle_seconds));
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS, options.max_streams_per_connection);
  // The service is registered before the port is known; its id is fixed up
  // below when it defaults to host:port.
  std::string server_id = options.server_id;
  auto service_context = [&] {
    return ServiceContext{*server->engine_, *server->executor_, *server->metadata_executor_, *server->metrics_,
                          *server->authorizer_, *server->calls_, *server->uploads_, server_id};
  };
  server->service_ = std::make_unique<VisibilityServiceImpl>(service_context());
  builder.RegisterService(server->service_.get());
  if (options.auth_token.empty()) {
    server->reflection_v1_ = std::make_unique<ReflectionV1Service>(std::vector<std::string>{
        v1::VisibilityService::service_full_name(), "grpc.health.v1.Health",
        "grpc.reflection.v1alpha.ServerReflection", grpc::reflection::v1::ServerReflection::service_full_name()});
    builder.RegisterService(server->reflection_v1_.get());
  }
  server->grpc_server_ = builder.BuildAndStart();
  if (!server->grpc_server_ || server->port_ == 0)
    return absl::UnavailableError(absl::StrCat("cannot listen on ", options.address));
  if (server_id.empty()) {
    server_id = options.address.substr(0, options.address.rfind(':')) + ":" + std::to_string(server->port_);
    server->service_->set_server_id(server_id);
  }
  server->SetServing(false);
  if (!options.metrics_address.empty()) {
    VisibilityServiceImpl* service = server->service_.get();
    auto metrics = MetricsHttpServer::Start(options.metrics_address, [service] { return service->Figures(); },
                                            options.metrics_limits);
    if (!metrics.ok()) return metrics.status();
    server->metrics_http_ = *std::move(metrics);
  }
  spdlog::info("listening on {} (port {}, {}{}), health NOT_SERVING until scenes are loaded", options.address,
               server->port_, tls ? (options.tls.client_ca_file.empty() ? "TLS" : "mutual TLS") : "plaintext",
               options.auth_token.empty() ? "" : ", bearer token required");
  if (loopback) spdlog::info("loopback only: other machines cannot reach this server");
  else if (!tls && options.auth_token.empty())
    spdlog::warn("listening beyond loopback without TLS or a token (--allow-insecure-remote)");
  return server;
}

Server::~Server() { GracefulStop(std::chrono::seconds(5)); }

void Server::SetServing(bool serving) {
  if (!grpc_server_) return;
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
  if (!grpc_server_) return;  // never listened: nothing to drain
  // Order: refuse new work (health), drain gRPC, drain the executor, then
  // the engine (and its GL thread) goes with this object.
  SetServing(false);
  spdlog::info("shutting down: health NOT_SERVING, draining requests for up to {} ms", drain.count());
  // The calls still running shortly before the drain's end are told to stop
  // (their work polls the flag between GL jobs, ray batches and points) and
  // answer UNAVAILABLE, so the process exits with the drain, not with the
  // longest job: a pod's grace period holds.
  const auto drain_end = std::chrono::steady_clock::now() + drain;
  const auto stop_at = drain_end - std::min<std::chrono::steady_clock::duration>(drain / 2, std::chrono::seconds(1));
  std::mutex ender_mutex;
  std::condition_variable ender_wake;
  bool drained = false;
  std::thread ender([&] {
    std::unique_lock lock(ender_mutex);
    if (ender_wake.wait_until(lock, stop_at, [&] { return drained; })) return;
    const size_t told = calls_->EndDrain();
    if (told > 0) spdlog::warn("drain period ending: {} call(s) still running told to stop (UNAVAILABLE)", told);
  });
  grpc_server_->Shutdown(std::chrono::system_clock::now() + drain);
  {
    std::lock_guard lock(ender_mutex);
    drained = true;
  }
  ender_wake.notify_all();
  ender.join();
  calls_->EndDrain();  // anything gRPC left running stops now
  grpc_server_->Wait();
  // Scrapes read the executors and the engine: stopped before either goes.
  if (metrics_http_) metrics_http_->Stop();
  executor_.reset();
  metadata_executor_.reset();
  spdlog::info("shut down");
}

// gRPC 1.51's teardown (the last grpc_shutdown, run by ~grpc::Server) joins
// its executor threads, and one of them may be inside a TCP backup poller's
// poll with a 10 s deadline after a connection wrote while the call was
// being cancelled (grpc/grpc#41050): a server whose drain ended in 1.3 s
// exited 10.9 s after SIGTERM in 1 of 4 runs here, waiting in that join. So
// one more library reference is taken before this server goes, the last
// grpc_shutdown never runs, and the process ends with _Exit: gRPC's threads
// are left to the kernel, with nothing of visq's still using them.
void Server::StopAndExit(std::unique_ptr<Server> server, std::chrono::milliseconds drain, int exit_code) {
  if (server) {
    server->GracefulStop(drain);
    grpc_init();
    server.reset();
  }
  spdlog::shutdown();
  std::fflush(nullptr);
  std::_Exit(exit_code);
}

}  // namespace visq::service
