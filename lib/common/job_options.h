// What every queued job carries, whichever thread runs it (the GL thread's
// jobs are the ones that use it today): its priority and its call's stop
// token (common/stop_token.h). The vocabulary the core and the transport
// compute deadlines in, below gpu/ (issue 48 §1).
#pragma once

#include "common/stop_token.h"

namespace visq {

// JobOptions::priority of a query someone waits on, and of long batch work.
inline constexpr int kInteractive = 0;
inline constexpr int kBatch = 10;

struct JobOptions {
  // Lower runs first; equal priorities run in arrival order. Small queries
  // use kInteractive so that long bakes (kBatch, split into steps) do not
  // starve them; nor do they starve a bake: after 8 jobs have overtaken
  // waiting work, the oldest waiting job runs.
  int priority = 0;
  // Asked before the job starts, and by long jobs between steps.
  StopToken stop;
};

}  // namespace visq
