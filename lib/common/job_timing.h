// Where a job's time went: waiting for its thread, and running there.
#pragma once

namespace visq {

struct JobTiming {
  double queue_ms = 0;  // from submission to start (on the GL thread, for GPU jobs)
  double run_ms = 0;    // running, GPU work finished (glFinish) for GPU jobs
};

}  // namespace visq
