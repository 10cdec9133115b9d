// A GPU worker for the GL tests of one executable.
#pragma once

#include "visq/gpu/gpu_worker.h"

namespace visq::testing {

// One GPU worker (llvmpipe here) shared by every test of an executable, with
// GL error checks on. Fails the test if no context can be made.
gpu::GpuWorker& SharedGpuWorker();

}  // namespace visq::testing
