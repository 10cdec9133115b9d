// Where a job's time went: waiting for its thread, and running there.
#pragma once

#include <chrono>

namespace visq {

// Milliseconds on the steady clock, for every timing field visq reports.
inline double MillisecondsBetween(std::chrono::steady_clock::time_point a, std::chrono::steady_clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}
inline double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return MillisecondsBetween(start, std::chrono::steady_clock::now());
}

struct JobTiming {
  double queue_ms = 0;  // from submission to start (on the GL thread, for GPU jobs)
  double run_ms = 0;    // running, GPU work finished (glFinish) for GPU jobs
};

}  // namespace visq
