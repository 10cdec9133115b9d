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

void Metrics::Record(const std::string& method, double ms, bool ok) {
  std::lock_guard lock(mutex_);
  Histogram& h = methods_[method];
  ++h.calls;
  if (!ok) ++h.errors;
  h.total_ms += ms;
  h.max_ms = std::max(h.max_ms, ms);
  ++h.buckets[Bucket(ms)];
}

std::vector<MethodSummary> Metrics::Summaries() const {
  std::lock_guard lock(mutex_);
  std::vector<MethodSummary> out;
  for (const auto& [method, h] : methods_) {
    out.push_back({method, h.calls, h.errors, h.calls ? h.total_ms / h.calls : 0.0, Percentile(h, 0.5),
                   Percentile(h, 0.99), h.max_ms});
  }
  return out;
}

}  // namespace visq::service
