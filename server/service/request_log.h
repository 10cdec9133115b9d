// Every log line of a request carries its id and method; the closing line
// carries its status and time.
#pragma once

#include <atomic>
#include <chrono>
#include <string>

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include "common/status.h"
#include "service/log_format.h"
#include "service/metrics.h"

namespace visq::service {

class RequestLog {
 public:
  // Uses the client's x-request-id metadata when it sends one.
  RequestLog(grpc::CallbackServerContext* context, const char* method, Metrics* metrics);
  // A call that never reached Done (its reactor went first) leaves the
  // in-flight count.
  ~RequestLog();
  RequestLog(const RequestLog&) = delete;
  RequestLog& operator=(const RequestLog&) = delete;

  // In the JSON format the line also carries request_id and method as
  // fields of their own.
  template <typename... Args>
  void Info(fmt::format_string<Args...> format, Args&&... args) const {
    const ScopedLogFields fields(Fields());
    spdlog::info("[{} {}] {}", id_, method_, fmt::format(format, std::forward<Args>(args)...));
  }
  // Logs the outcome with the total time and records it in the metrics
  // (the first call only); returns the time in milliseconds. In the JSON
  // format the line carries request_id, method, status (the code's name,
  // "OK" included) and duration_ms as fields of their own.
  double Done(const Status& status) const;
  double ElapsedMs() const;
  const std::string& id() const { return id_; }
  // "[id method]", as every line of the request starts.
  std::string Tag() const { return fmt::format("[{} {}]", id_, method_); }

 private:
  // request_id and method, as every JSON line of the request carries them.
  std::vector<LogField> Fields() const;

  std::string id_;
  const char* method_;
  Metrics* metrics_;
  std::chrono::steady_clock::time_point start_;
  mutable std::atomic<bool> done_{false};
};

}  // namespace visq::service
