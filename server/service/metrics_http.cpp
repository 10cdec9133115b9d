#include "service/metrics_http.h"

#include <sys/socket.h>

#include <charconv>
#include <chrono>

#include <httplib.h>
#include <spdlog/spdlog.h>

#include "service/prometheus_text.h"

namespace visq::service {
namespace {

struct HostPort {
  std::string host;
  int port = 0;
};

StatusOr<HostPort> ParseHostPort(const std::string& address) {
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0)
    return absl::InvalidArgumentError(absl::StrCat("--metrics-address '", address, "': expected HOST:PORT"));
  HostPort out;
  out.host = address.substr(0, colon);
  if (out.host.size() >= 2 && out.host.front() == '[' && out.host.back() == ']')
    out.host = out.host.substr(1, out.host.size() - 2);
  else if (out.host.find(':') != std::string::npos)
    return absl::InvalidArgumentError(
        absl::StrCat("--metrics-address '", address, "': write an IPv6 address in brackets, [::1]:PORT"));
  const std::string port = address.substr(colon + 1);
  const auto [end, error] = std::from_chars(port.data(), port.data() + port.size(), out.port);
  if (out.host.empty() || port.empty() || error != std::errc() || end != port.data() + port.size() ||
      out.port < 0 || out.port > 65535)
    return absl::InvalidArgumentError(absl::StrCat("--metrics-address '", address, "': expected HOST:PORT"));
  return out;
}

}  // namespace

Status ValidateMetricsAddress(const std::string& address) { return ParseHostPort(address).status(); }

StatusOr<std::unique_ptr<MetricsHttpServer>> MetricsHttpServer::Start(const std::string& address,
                                                                     std::function<ServerFigures()> collect) {
  VISQ_ASSIGN_OR_RETURN(HostPort where, ParseHostPort(address));
  std::unique_ptr<MetricsHttpServer> server(new MetricsHttpServer());
  server->http_ = std::make_unique<httplib::Server>();
  httplib::Server& http = *server->http_;
  // Two threads are plenty for a scraper; short timeouts and a tiny payload
  // bound keep a slow or hostile peer from holding them.
  http.new_task_queue = [] { return new httplib::ThreadPool(2); };
  http.set_read_timeout(std::chrono::seconds(5));
  http.set_write_timeout(std::chrono::seconds(5));
  http.set_keep_alive_max_count(16);
  http.set_keep_alive_timeout(5);
  http.set_payload_max_length(4096);
  // SO_REUSEADDR only: a restart binds despite TIME_WAIT, but a second
  // server cannot share the port (httplib's default adds SO_REUSEPORT).
  http.set_socket_options([](int sock) {
    int yes = 1;
    ::setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
  });
  http.Get("/metrics", [collect = std::move(collect)](const httplib::Request&, httplib::Response& response) {
    response.set_content(RenderPrometheusText(collect()), kPrometheusContentType);
  });
  // Every other path or method (POST /metrics, an unknown verb) is 404,
  // with a body that names what is served.
  http.set_error_handler([](const httplib::Request&, httplib::Response& response) {
    if (response.status == 400 || response.status == 404 || response.status == 405) {
      response.status = 404;
      response.set_content("only GET /metrics is served here\n", "text/plain");
    }
  });
  if (where.port == 0) {
    server->port_ = http.bind_to_any_port(where.host);
    if (server->port_ < 0) server->port_ = 0;
  } else if (http.bind_to_port(where.host, where.port)) {
    server->port_ = where.port;
  }
  if (server->port_ == 0)
    return absl::UnavailableError(absl::StrCat("--metrics-address ", address,
                                               ": cannot listen there (address not local, or port in use)"));
  server->thread_ = std::thread([&http] { http.listen_after_bind(); });
  // Stop() only stops a server that is running: wait until it is.
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (!http.is_running() && std::chrono::steady_clock::now() < give_up)
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  spdlog::info("metrics: GET http://{}:{}/metrics", address.substr(0, address.rfind(':')), server->port_);
  return server;
}

void MetricsHttpServer::Stop() {
  if (!thread_.joinable()) return;
  http_->stop();
  thread_.join();
}

MetricsHttpServer::~MetricsHttpServer() { Stop(); }

}  // namespace visq::service
