// Per-RPC call counts and latency histograms for GetStats.
#pragma once

#include <array>
#include <map>
#include <mutex>
#include <string>
#include <vector>

namespace visq::service {

struct MethodSummary {
  std::string method;
  uint64_t calls = 0;
  uint64_t errors = 0;
  double mean_ms = 0;
  double p50_ms = 0;
  double p99_ms = 0;
  double max_ms = 0;
};

class Metrics {
 public:
  void Record(const std::string& method, double ms, bool ok);
  std::vector<MethodSummary> Summaries() const;

 private:
  // Log-spaced buckets, 10 % apart, from 1 microsecond to about 3 hours:
  // percentiles are exact to within one bucket.
  static constexpr int kBuckets = 240;
  static constexpr double kFirstBucketMs = 1e-3;
  static constexpr double kGrowth = 1.1;
  struct Histogram {
    uint64_t calls = 0;
    uint64_t errors = 0;
    double total_ms = 0;
    double max_ms = 0;
    std::array<uint64_t, kBuckets> buckets{};
  };
  static int Bucket(double ms);
  static double BucketUpperMs(int bucket);
  static double Percentile(const Histogram& h, double fraction);

  mutable std::mutex mutex_;
  std::map<std::string, Histogram> methods_;
};

}  // namespace visq::service
