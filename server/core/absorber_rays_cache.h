// The absorbers' BVHs that ray stabbing (Transmittance's RAY_STABBING)
// casts against, kept per resident scene for the queries that follow: the
// build is most of a small request's time (58 of 75 ms behind the bunny),
// and a tool asks the same absorbers again as its light or points move.
#pragma once

#include <cstddef>
#include <cstdint>
#include <list>
#include <memory>
#include <mutex>
#include <vector>

#include "common/status.h"
#include "common/stop_token.h"
#include "scene/scene.h"
#include "voxel_reference/transmittance_by_rays.h"

namespace visq::core {

class AbsorberRaysCache {
 public:
  // Node sets kept, the least recently used out: a few absorber sets a scene.
  static constexpr size_t kKept = 4;

  // The BVH of `nodes` (indices into scene.nodes, any order), built on the
  // first ask (outside the lock: a call that asks while another builds the
  // same set builds its own, and the first to finish is kept).
  [[nodiscard]] StatusOr<std::shared_ptr<const voxel_reference::AbsorberRays>> Get(const Scene& scene,
                                                                                  std::vector<uint32_t> nodes,
                                                                                  const StopToken& stop);
  // What the kept BVHs hold, for the scene's memory.
  size_t MemoryBytes() const;

 private:
  mutable std::mutex mutex_;
  std::list<std::shared_ptr<const voxel_reference::AbsorberRays>> kept_;  // the most recently used first
};

}  // namespace visq::core
