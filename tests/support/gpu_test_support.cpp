#include "gpu_test_support.h"

#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>

namespace visq::testing {

gpu::GpuWorker& SharedGpuWorker() {
  static std::unique_ptr<gpu::GpuWorker> worker = [] {
    gpu::GpuOptions options;
    options.debug = true;
    auto started = gpu::GpuWorker::Start(options);
    if (!started.ok()) {
      std::fprintf(stderr, "no GL context for the GPU tests: %s\n", std::string(started.status().message()).c_str());
      std::abort();
    }
    return std::move(*started);
  }();
  return *worker;
}

}  // namespace visq::testing
