#include "core/absorber_rays_cache.h"

#include <algorithm>
#include <utility>

namespace visq::core {

StatusOr<std::shared_ptr<const voxel_reference::AbsorberRays>> AbsorberRaysCache::Get(const Scene& scene,
                                                                                      std::vector<uint32_t> nodes,
                                                                                      const StopToken& stop) {
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  {
    std::lock_guard lock(mutex_);
    for (auto it = kept_.begin(); it != kept_.end(); ++it) {
      if ((*it)->nodes != nodes) continue;
      kept_.splice(kept_.begin(), kept_, it);
      return kept_.front();
    }
  }
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const voxel_reference::AbsorberRays> built,
                        voxel_reference::BuildAbsorberRays(scene, std::move(nodes), stop));
  std::lock_guard lock(mutex_);
  for (const auto& kept : kept_)
    if (kept->nodes == built->nodes) return kept;
  kept_.push_front(built);
  if (kept_.size() > kKept) kept_.pop_back();
  return built;
}

size_t AbsorberRaysCache::MemoryBytes() const {
  std::lock_guard lock(mutex_);
  size_t bytes = 0;
  for (const auto& kept : kept_) bytes += kept->MemoryBytes();
  return bytes;
}

}  // namespace visq::core
