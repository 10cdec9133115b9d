// /metrics over HTTP on a port of its own, for Prometheus: GET /metrics
// answers the text format; every other path or method is 404. The server
// has a small fixed pool, short timeouts and a tiny request bound, so a
// scraper (or anyone else who reaches the port) cannot hold it.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "common/status.h"
#include "service/stats.h"

namespace httplib {
class Server;
}

namespace visq::service {

// Whether `address` is HOST:PORT or [V6]:PORT with a port in 0..65535.
[[nodiscard]] Status ValidateMetricsAddress(const std::string& address);

class MetricsHttpServer {
 public:
  // Binds `address` (HOST:PORT, [V6]:PORT; port 0 picks a free one) and
  // serves from a thread of its own. A bad address or a port in use is an
  // error here, not later.
  [[nodiscard]] static StatusOr<std::unique_ptr<MetricsHttpServer>> Start(const std::string& address,
                                                                          std::function<ServerFigures()> collect);
  ~MetricsHttpServer();
  MetricsHttpServer(const MetricsHttpServer&) = delete;
  MetricsHttpServer& operator=(const MetricsHttpServer&) = delete;

  int port() const { return port_; }
  // Closes the port and waits for answers in progress (bounded by the write
  // timeout). Idempotent.
  void Stop();

 private:
  MetricsHttpServer() = default;
  std::unique_ptr<httplib::Server> http_;
  std::thread thread_;
  int port_ = 0;
};

}  // namespace visq::service
