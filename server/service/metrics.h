// Per-RPC call counts, outcomes by status code, calls in flight and latency
// histograms: GetStats reads percentiles from them, /metrics the Prometheus
// buckets.
#pragma once

#include <array>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include <absl/status/status.h>

namespace visq::service {

struct MethodSummary {
  std::string method;
  uint64_t calls = 0;
  uint64_t errors = 0;
  double mean_ms = 0;
  double p50_ms = 0;
  double p99_ms = 0;
  double max_ms = 0;
  uint64_t in_flight = 0;
  // Finished calls by status code name ("OK", "NOT_FOUND"); sums to calls.
  std::map<std::string, uint64_t> codes;
  double total_seconds = 0;
  // Calls that took at most kPrometheusBucketsSeconds[i], cumulative; the
  // +Inf bucket is `calls`.
  std::vector<uint64_t> cumulative_buckets;
};

class Metrics {
 public:
  // Upper bounds of the exported latency buckets: fixed, so that a
  // dashboard's histogram_quantile sees the same `le` labels on every replica.
  // They reach 4 hours: a bake runs for hours, and beyond the last bucket
  // histogram_quantile can only answer that bucket's bound.
  static constexpr std::array<double, 22> kPrometheusBucketsSeconds = {
      0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1,
      2.5,    5,     10,     30,    120,  300,   600,  1800, 3600, 7200, 14400};

  // A call began (counted in flight until Record).
  void Begin(const std::string& method);
  // A call that Begin counted finished with `code` after `ms`.
  void Record(const std::string& method, double ms, absl::StatusCode code);
  // A call that Begin counted ended without an outcome.
  void Abandon(const std::string& method);
  std::vector<MethodSummary> Summaries() const;

 private:
  // Log-spaced buckets, 10 % apart, from 1 microsecond to about 60
  // hours (bakes run for hours): percentiles are exact to within one bucket.
  static constexpr int kBuckets = 275;
  static constexpr double kFirstBucketMs = 1e-3;
  static constexpr double kGrowth = 1.1;
  struct Histogram {
    uint64_t calls = 0;
    uint64_t errors = 0;
    uint64_t in_flight = 0;
    double total_ms = 0;
    double max_ms = 0;
    std::array<uint64_t, kBuckets> buckets{};
    std::array<uint64_t, kPrometheusBucketsSeconds.size()> prometheus_buckets{};  // not cumulative
    std::map<absl::StatusCode, uint64_t> codes;
  };
  static int Bucket(double ms);
  static double BucketUpperMs(int bucket);
  static double Percentile(const Histogram& h, double fraction);

  mutable std::mutex mutex_;
  std::map<std::string, Histogram> methods_;
};

}  // namespace visq::service
