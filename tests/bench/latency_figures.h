// Percentiles of call latencies, as the RPC benches print them.
#pragma once

#include <algorithm>
#include <cstdio>
#include <vector>

namespace visq::bench {

struct LatencyFigures {
  size_t n = 0;
  double p50 = 0, p90 = 0, p99 = 0, max = 0;  // ms
};

// Nearest-rank percentiles of `ms` (none: all zero).
inline LatencyFigures Figures(std::vector<double> ms) {
  LatencyFigures f;
  if (ms.empty()) return f;
  std::sort(ms.begin(), ms.end());
  auto at = [&](double q) { return ms[std::min(ms.size() - 1, static_cast<size_t>(q * ms.size()))]; };
  f.n = ms.size();
  f.p50 = at(0.5);
  f.p90 = at(0.9);
  f.p99 = at(0.99);
  f.max = ms.back();
  return f;
}

inline void Report(const char* what, const std::vector<double>& ms) {
  const LatencyFigures f = Figures(ms);
  std::printf("%-40s n=%zu  p50 %.3f ms  p90 %.3f ms  p99 %.3f ms  max %.3f ms\n", what, f.n, f.p50, f.p90, f.p99,
              f.max);
}

}  // namespace visq::bench
