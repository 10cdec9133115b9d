#include "service/stats.h"

#include <chrono>

#include "common/version.h"
#include "service/visibility_service.h"

namespace visq::service {

ServerFigures CollectServerFigures(const ServiceContext& ctx) {
  ServerFigures f;
  f.server_id = ctx.server_id;
  f.version = kVersion;
  f.build_commit = kBuildCommit;
  f.uptime_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - ctx.started).count();
  f.device = ctx.engine.device();
  f.gpu_queue_depth = ctx.engine.gpu().queue_depth();
  f.gpu_contexts_lost = ctx.engine.gpu().contexts_lost();
  f.worker_queue_depth = ctx.executor.queued();
  f.metadata_queue_depth = ctx.metadata_executor.queued();
  const auto scenes = ctx.engine.ListScenes();
  f.scenes_resident = scenes.size();
  for (const auto& scene : scenes) {
    f.scene_cpu_bytes += scene.cpu_bytes;
    f.scene_gpu_bytes += scene.gpu_bytes;
  }
  core::WorkMemoryBudget& budget = ctx.engine.work_budget();
  f.work_bytes_in_use = budget.in_use();
  f.work_bytes_peak = budget.peak();
  f.work_bytes_capacity = budget.capacity();
  const core::Engine::LightCacheStats light = ctx.engine.light_cache_stats();
  f.caches.push_back(
      {"light_visibility", light.entries, light.bytes, light.capacity_bytes, light.hits, light.misses, light.evictions});
  f.methods = ctx.metrics.Summaries();
  f.structure_builds = ctx.engine.build_times().Snapshot();
  if (const core::IdleExplorer* explorer = ctx.engine.idle_explorer()) f.idle_exploration = explorer->figures();
  f.process = ReadProcessFigures();
  return f;
}

}  // namespace visq::service
