// Hidden-sample maps and patch-to-patch visibility on the GPU (Eisemann &
// Décoret 2007, "Visibility Sampling on GPU and Applications"). The
// algorithm lives in gpu/hidden_sample_map/ with its shaders; this header is
// its public face and holds no GL or protobuf type. The model it answers in
// (patches, requests, results, bounds) is lib/sampling.
#pragma once

#include <memory>

#include "common/status.h"
#include "sampling/visibility_sampling.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

// Owns the programs and a small cache of Hough tables (keyed by the sample
// pattern and resolution) on the GL thread. Thread-safe: every GL step runs
// as a job on the worker.
class HiddenSampleMapper {
 public:
  [[nodiscard]] static StatusOr<std::unique_ptr<HiddenSampleMapper>> Create(GpuWorker& worker);
  ~HiddenSampleMapper();  // releases GL objects on the GL thread
  HiddenSampleMapper(const HiddenSampleMapper&) = delete;
  HiddenSampleMapper& operator=(const HiddenSampleMapper&) = delete;

  [[nodiscard]] StatusOr<sampling::HiddenSampleMapResult> Compute(const GpuScene& scene, const sampling::HiddenSampleMapRequest& request,
                                                        const JobOptions& job = {});
  [[nodiscard]] StatusOr<sampling::PatchVisibilityResult> PatchVisibility(const GpuScene& scene,
                                                                const sampling::PatchVisibilityRequest& request,
                                                                const JobOptions& job = {});

  struct State;  // GL-thread state, defined in gpu/hidden_sample_map/

 private:
  explicit HiddenSampleMapper(GpuWorker& worker);
  GpuWorker* worker_;
  std::shared_ptr<State> state_;
};

}  // namespace visq::gpu
