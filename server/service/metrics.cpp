#include "service/metrics.h"

#include <algorithm>
#include <cmath>

namespace visq::service {

int Metrics::Bucket(double ms) {
  if (!(ms > kFirstBucketMs)) return 0;
  const int b = static_cast<int>(std::ceil(std::log(ms / kFirstBucketMs) / std::log(kGrowth)));
  return std::clamp(b, 0, kBuckets - 1);
}

double Metrics::BucketUpperMs(int bucket) { return kFirstBucketMs * std::pow(kGrowth, bucket); }

double Metrics::Percentile(const Histogram& h, double fraction) {
  if (h.calls == 0) return 0;
  const uint64_t rank = static_cast<uint64_t>(std::ceil(fraction * static_cast<double>(h.calls)));
  uint64_t seen = 0;
  for (int b = 0; b < kBuckets; ++b) {
    seen += h.buckets[b];
    if (seen >= rank) return std::min(BucketUpperMs(b), h.max_ms);
  }
  return h.max_ms;
}

void Metrics::Begin(const std::string& method) {
  std::lock_guard lock(mutex_);
  ++methods_[method].in_flight;
}

void Metrics::Abandon(const std::string& method) {
  std::lock_guard lock(mutex_);
  Histogram& h = methods_[method];
  if (h.in_flight > 0) --h.in_flight;
}

void Metrics::Record(const std::string& method, double ms, absl::StatusCode code) {
  std::lock_guard lock(mutex_);
  Histogram& h = methods_[method];
  if (h.in_flight > 0) --h.in_flight;
  ++h.calls;
  if (code != absl::StatusCode::kOk) ++h.errors;
  ++h.codes[code];
  h.total_ms += ms;
  h.max_ms = std::max(h.max_ms, ms);
  ++h.buckets[Bucket(ms)];
  const double seconds = ms / 1e3;
  for (size_t i = 0; i < kPrometheusBucketsSeconds.size(); ++i) {
    if (seconds <= kPrometheusBucketsSeconds[i]) {
      ++h.prometheus_buckets[i];
      break;
    }
  }
}

std::vector<MethodSummary> Metrics::Summaries() const {
  std::lock_guard lock(mutex_);
  std::vector<MethodSummary> out;
  for (const auto& [method, h] : methods_) {
    MethodSummary s{method, h.calls, h.errors, h.calls ? h.total_ms / h.calls : 0.0, Percentile(h, 0.5),
                    Percentile(h, 0.99), h.max_ms};
    s.in_flight = h.in_flight;
    for (const auto& [code, count] : h.codes) s.codes[absl::StatusCodeToString(code)] = count;
    s.total_seconds = h.total_ms / 1e3;
    uint64_t cumulative = 0;
    for (uint64_t count : h.prometheus_buckets) s.cumulative_buckets.push_back(cumulative += count);
    out.push_back(std::move(s));
  }
  return out;
}

}  // namespace visq::service
