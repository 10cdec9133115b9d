// The server's figures at one moment, gathered in one place: GetStats
// converts them to its message, /metrics to the Prometheus text format.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "core/engine.h"
#include "service/metrics.h"
#include "service/process_figures.h"

namespace visq::service {

struct ServiceContext;

struct CacheFigures {
  std::string name;
  uint64_t entries = 0;
  uint64_t bytes = 0;
  uint64_t capacity_bytes = 0;
  uint64_t hits = 0;
  uint64_t misses = 0;
  uint64_t evictions = 0;
};

struct ServerFigures {
  std::string server_id;
  std::string version;
  std::string build_commit;
  double uptime_s = 0;
  GpuDeviceInfo device;
  uint64_t gpu_queue_depth = 0;
  uint64_t worker_queue_depth = 0;
  uint64_t metadata_queue_depth = 0;
  uint64_t gpu_contexts_lost = 0;
  uint64_t scenes_resident = 0;
  uint64_t scene_cpu_bytes = 0;
  uint64_t scene_gpu_bytes = 0;
  uint64_t work_bytes_in_use = 0;
  uint64_t work_bytes_peak = 0;
  uint64_t work_bytes_capacity = 0;
  std::vector<CacheFigures> caches;
  std::vector<MethodSummary> methods;
  std::map<std::string, core::BuildTimes::Figures> structure_builds;
  std::optional<core::IdleExplorer::Figures> idle_exploration;  // none: the server does not explore when idle
  ProcessFigures process;
};

ServerFigures CollectServerFigures(const ServiceContext& ctx);

}  // namespace visq::service
