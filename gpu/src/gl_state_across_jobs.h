// GL objects that outlive one GL job: a long request (a voxelization, a
// volumetric rendering) is split into jobs so that other queries get the GL
// thread between them, and its targets live from its first job to its last.
// They die on the GL thread however the request ends, and a job that finds
// the context lost since they were made fails instead of using dead names.
#pragma once

#include <memory>
#include <string_view>
#include <utility>

#include "common/status.h"
#include "gl_object.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

template <typename T>
class GlStateAcrossJobs {
 public:
  explicit GlStateAcrossJobs(GpuWorker& worker) : worker_(&worker) {}
  ~GlStateAcrossJobs() {
    if (state_) worker_->Post([state = std::move(state_)]() mutable { state.reset(); });
  }
  GlStateAcrossJobs(const GlStateAcrossJobs&) = delete;
  GlStateAcrossJobs& operator=(const GlStateAcrossJobs&) = delete;

  // GL thread, in the request's first job.
  void Set(std::shared_ptr<T> state) {
    state_ = std::move(state);
    generation_ = CurrentContextGeneration();
  }

  // GL thread, in the jobs after it: the state, or INTERNAL naming `what`
  // when the context it was made in has been lost since.
  [[nodiscard]] StatusOr<T*> Get(std::string_view what) const {
    if (!state_) return absl::InternalError(absl::StrCat(AbslView(what), ": used before its first job made it"));
    if (generation_ != CurrentContextGeneration())
      return absl::InternalError(absl::StrCat(AbslView(what), ": the GPU context was lost between its jobs; retry"));
    return state_.get();
  }

 private:
  GpuWorker* worker_;
  std::shared_ptr<T> state_;
  uint64_t generation_ = 0;
};

}  // namespace visq::gpu
