#include "service/request_log.h"

#include "common/job_timing.h"

namespace visq::service {
namespace {
std::atomic<uint64_t> next_request_id{1};
constexpr size_t kMaxClientIdLength = 64;
}  // namespace

RequestLog::RequestLog(grpc::CallbackServerContext* context, const char* method, Metrics* metrics)
    : method_(method), metrics_(metrics), start_(std::chrono::steady_clock::now()) {
  if (metrics_ != nullptr) metrics_->Begin(method_);
  const auto& metadata = context->client_metadata();
  auto it = metadata.find("x-request-id");
  if (it != metadata.end() && !it->second.empty() && it->second.size() <= kMaxClientIdLength) {
    id_.assign(it->second.data(), it->second.size());
    for (char& c : id_)
      if (c < 0x21 || c > 0x7e) c = '?';  // keep log lines one line
  } else {
    id_ = fmt::format("r{}", next_request_id.fetch_add(1));
  }
}

RequestLog::~RequestLog() {
  if (metrics_ != nullptr && !done_.exchange(true)) metrics_->Abandon(method_);
}

double RequestLog::ElapsedMs() const {
  return MillisecondsSince(start_);
}

std::vector<LogField> RequestLog::Fields() const {
  return {LogField::String("request_id", id_), LogField::String("method", method_)};
}

double RequestLog::Done(const Status& status) const {
  const double ms = ElapsedMs();
  if (metrics_ != nullptr && !done_.exchange(true)) metrics_->Record(method_, ms, status.code());
  std::vector<LogField> fields = Fields();
  fields.push_back(LogField::String("status", absl::StatusCodeToString(status.code())));
  fields.push_back(LogField::Number("duration_ms", ms));
  const ScopedLogFields scoped(std::move(fields));
  if (status.ok())
    spdlog::info("[{} {}] OK in {:.2f} ms", id_, method_, ms);
  else
    spdlog::warn("[{} {}] {} in {:.2f} ms: {}", id_, method_, absl::StatusCodeToString(status.code()), ms,
                 status.message());
  return ms;
}

}  // namespace visq::service
