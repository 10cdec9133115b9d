// /metrics over HTTP on a port of its own, for Prometheus: GET /metrics
// answers the text format; every other path or method is 404. One thread
// serves every connection (poll), each request within a total deadline and
// a small size bound, and at most a fixed number of connections at once: a
// peer that sends its request a byte at a time (slowloris), or opens many
// connections, cannot keep a scraper from its answer.
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "common/status.h"
#include "service/stats.h"

namespace visq::service {

// Whether `address` is HOST:PORT or [V6]:PORT with a port in 0..65535.
[[nodiscard]] Status ValidateMetricsAddress(const std::string& address);

struct MetricsHttpLimits {
  int max_connections = 16;  // --metrics-max-connections: more are closed as they arrive
  // --metrics-read-seconds: the whole request must arrive within it, and the
  // answer be taken within it again; else the connection is closed.
  std::chrono::milliseconds request_timeout{std::chrono::seconds(5)};
};

class MetricsHttpServer {
 public:
  // Binds `address` (HOST:PORT, [V6]:PORT; port 0 picks a free one) and
  // serves from a thread of its own. A bad address or a port in use is an
  // error here, not later.
  [[nodiscard]] static StatusOr<std::unique_ptr<MetricsHttpServer>> Start(const std::string& address,
                                                                          std::function<ServerFigures()> collect,
                                                                          MetricsHttpLimits limits = {});
  ~MetricsHttpServer();
  MetricsHttpServer(const MetricsHttpServer&) = delete;
  MetricsHttpServer& operator=(const MetricsHttpServer&) = delete;

  int port() const { return port_; }
  // Closes the port and every connection. Idempotent.
  void Stop();

 private:
  MetricsHttpServer() = default;
  void Serve();

  std::function<ServerFigures()> collect_;
  MetricsHttpLimits limits_;
  int listen_fd_ = -1;
  int wake_fd_ = -1;  // an eventfd: Stop() wakes the poll
  std::thread thread_;
  int port_ = 0;
};

}  // namespace visq::service
