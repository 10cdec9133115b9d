// What a query's work took, as the core counts it: the time its GL jobs
// waited for the GL thread, and the time the work itself ran (GL jobs and
// the CPU around them, structures built on first use excluded: those are
// the call's build clock). The transport adds its own queueing before the
// work and its writes after it; every RPC's Timing is made from these two.
#pragma once

namespace visq::core {

struct WorkTiming {
  double queue_ms = 0.0;    // the work's GL jobs waiting for the GL thread
  double compute_ms = 0.0;  // the work running
};

}  // namespace visq::core
