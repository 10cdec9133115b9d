#include "service/prometheus_text.h"

#include <cmath>
#include <utility>
#include <vector>

#include <fmt/format.h>

namespace visq::service {
namespace {

using Labels = std::vector<std::pair<std::string, std::string>>;

// Shortest text that reads back as the same double; Prometheus spells the
// non-finite ones +Inf, -Inf and NaN.
std::string Number(double value) {
  if (std::isnan(value)) return "NaN";
  if (std::isinf(value)) return value > 0 ? "+Inf" : "-Inf";
  return fmt::format("{}", value);
}

std::string LabelText(const Labels& labels) {
  if (labels.empty()) return "";
  std::string out = "{";
  for (size_t i = 0; i < labels.size(); ++i) {
    if (i > 0) out += ',';
    out += labels[i].first;
    out += "=\"";
    out += EscapePrometheusLabelValue(labels[i].second);
    out += '"';
  }
  return out + "}";
}

class Writer {
 public:
  // Starts a family: its HELP and TYPE lines, once.
  void Family(const std::string& name, const char* type, std::string_view help) {
    out_ += fmt::format("# HELP {} {}\n# TYPE {} {}\n", name, EscapePrometheusHelp(help), name, type);
  }
  void Sample(const std::string& name, const Labels& labels, double value) {
    out_ += name;
    out_ += LabelText(labels);
    out_ += ' ';
    out_ += Number(value);
    out_ += '\n';
  }
  // A one-sample family.
  void Single(const std::string& name, const char* type, std::string_view help, double value,
              const Labels& labels = {}) {
    Family(name, type, help);
    Sample(name, labels, value);
  }
  std::string Take() { return std::move(out_); }

 private:
  std::string out_;
};

}  // namespace

std::string EscapePrometheusLabelValue(std::string_view value) {
  std::string out;
  out.reserve(value.size());
  for (char c : value) {
    if (c == '\\') out += "\\\\";
    else if (c == '"') out += "\\\"";
    else if (c == '\n') out += "\\n";
    else out += c;
  }
  return out;
}

std::string EscapePrometheusHelp(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    if (c == '\\') out += "\\\\";
    else if (c == '\n') out += "\\n";
    else out += c;
  }
  return out;
}

std::string RenderPrometheusText(const ServerFigures& f) {
  Writer w;
  w.Single("visq_build_info", "gauge", "The server's version and the commit it was built from.", 1,
           {{"version", f.version}, {"commit", f.build_commit}});
  w.Single("visq_gpu_info", "gauge", "The GL device the server renders on (software: llvmpipe or another CPU rasterizer).",
           1, {{"renderer", f.device.gl_renderer}, {"egl_device", f.device.egl_device},
               {"software", f.device.software ? "true" : "false"}});
  w.Single("visq_uptime_seconds", "gauge", "Seconds since the server started.", f.uptime_s);

  // Per-RPC outcomes, calls in flight, latencies.
  w.Family("visq_rpc_handled_total", "counter", "Finished visq.v1 calls by method and gRPC status code.");
  for (const auto& m : f.methods)
    for (const auto& [code, count] : m.codes)
      w.Sample("visq_rpc_handled_total", {{"method", m.method}, {"code", code}}, static_cast<double>(count));
  w.Family("visq_rpc_errors_total", "counter", "Finished visq.v1 calls whose status was not OK, by method.");
  for (const auto& m : f.methods)
    w.Sample("visq_rpc_errors_total", {{"method", m.method}}, static_cast<double>(m.errors));
  w.Family("visq_rpc_in_flight", "gauge", "visq.v1 calls begun and not yet finished, by method.");
  uint64_t in_flight = 0;
  for (const auto& m : f.methods) {
    w.Sample("visq_rpc_in_flight", {{"method", m.method}}, static_cast<double>(m.in_flight));
    in_flight += m.in_flight;
  }
  w.Single("visq_requests_in_flight", "gauge", "visq.v1 calls begun and not yet finished.",
           static_cast<double>(in_flight));
  w.Family("visq_rpc_duration_seconds", "histogram", "Time from a visq.v1 call's arrival to its status, by method.");
  for (const auto& m : f.methods) {
    for (size_t i = 0; i < Metrics::kPrometheusBucketsSeconds.size() && i < m.cumulative_buckets.size(); ++i)
      w.Sample("visq_rpc_duration_seconds_bucket",
               {{"method", m.method}, {"le", Number(Metrics::kPrometheusBucketsSeconds[i])}},
               static_cast<double>(m.cumulative_buckets[i]));
    w.Sample("visq_rpc_duration_seconds_bucket", {{"method", m.method}, {"le", "+Inf"}}, static_cast<double>(m.calls));
    w.Sample("visq_rpc_duration_seconds_sum", {{"method", m.method}}, m.total_seconds);
    w.Sample("visq_rpc_duration_seconds_count", {{"method", m.method}}, static_cast<double>(m.calls));
  }

  // Queues.
  w.Family("visq_queue_depth", "gauge",
           "Work waiting: GPU jobs for the GL thread, compute calls for the workers, metadata calls.");
  w.Sample("visq_queue_depth", {{"queue", "gpu"}}, static_cast<double>(f.gpu_queue_depth));
  w.Sample("visq_queue_depth", {{"queue", "worker"}}, static_cast<double>(f.worker_queue_depth));
  w.Sample("visq_queue_depth", {{"queue", "metadata"}}, static_cast<double>(f.metadata_queue_depth));

  // Memory by kind, and the bounds that apply.
  w.Family("visq_memory_bytes", "gauge",
           "Memory held, by kind: resident scene geometry (CPU), its GPU buffers, cached light trees, and the "
           "work budget held by answers in progress.");
  w.Sample("visq_memory_bytes", {{"kind", "scene_cpu"}}, static_cast<double>(f.scene_cpu_bytes));
  w.Sample("visq_memory_bytes", {{"kind", "scene_gpu"}}, static_cast<double>(f.scene_gpu_bytes));
  uint64_t cache_bytes = 0;
  for (const auto& c : f.caches) cache_bytes += c.bytes;
  w.Sample("visq_memory_bytes", {{"kind", "caches"}}, static_cast<double>(cache_bytes));
  w.Sample("visq_memory_bytes", {{"kind", "work_in_flight"}}, static_cast<double>(f.work_bytes_in_use));
  w.Single("visq_work_memory_capacity_bytes", "gauge", "The work budget (--max-work-bytes).",
           static_cast<double>(f.work_bytes_capacity));
  w.Single("visq_work_memory_peak_bytes", "gauge", "The most of the work budget held at once since start.",
           static_cast<double>(f.work_bytes_peak));

  // Caches.
  w.Family("visq_cache_entries", "gauge", "Entries held, by cache.");
  for (const auto& c : f.caches) w.Sample("visq_cache_entries", {{"cache", c.name}}, static_cast<double>(c.entries));
  w.Family("visq_cache_bytes", "gauge", "Bytes held, by cache.");
  for (const auto& c : f.caches) w.Sample("visq_cache_bytes", {{"cache", c.name}}, static_cast<double>(c.bytes));
  w.Family("visq_cache_capacity_bytes", "gauge", "The bound on a cache's bytes.");
  for (const auto& c : f.caches)
    w.Sample("visq_cache_capacity_bytes", {{"cache", c.name}}, static_cast<double>(c.capacity_bytes));
  w.Family("visq_cache_hits_total", "counter", "Lookups that found their entry, by cache.");
  for (const auto& c : f.caches) w.Sample("visq_cache_hits_total", {{"cache", c.name}}, static_cast<double>(c.hits));
  w.Family("visq_cache_misses_total", "counter", "Lookups that built their entry, by cache.");
  for (const auto& c : f.caches)
    w.Sample("visq_cache_misses_total", {{"cache", c.name}}, static_cast<double>(c.misses));
  w.Family("visq_cache_evictions_total", "counter", "Entries dropped to stay within the bound, by cache.");
  for (const auto& c : f.caches)
    w.Sample("visq_cache_evictions_total", {{"cache", c.name}}, static_cast<double>(c.evictions));
  w.Family("visq_cache_hit_ratio", "gauge", "hits / (hits + misses) since start, by cache (0 before any lookup).");
  for (const auto& c : f.caches) {
    const uint64_t lookups = c.hits + c.misses;
    w.Sample("visq_cache_hit_ratio", {{"cache", c.name}},
             lookups ? static_cast<double>(c.hits) / static_cast<double>(lookups) : 0.0);
  }

  // Structures built on first use.
  w.Family("visq_structure_build_seconds", "summary",
           "Time spent building per-scene structures, by kind: scene_load (parse and flatten), gpu_upload, "
           "embree_bvh, triangle_index.");
  for (const auto& [kind, b] : f.structure_builds) {
    w.Sample("visq_structure_build_seconds_sum", {{"structure", kind}}, b.total_ms / 1e3);
    w.Sample("visq_structure_build_seconds_count", {{"structure", kind}}, static_cast<double>(b.count));
  }
  w.Family("visq_structure_builds_in_progress", "gauge", "Per-scene structures being built now, by kind.");
  for (const auto& [kind, b] : f.structure_builds)
    w.Sample("visq_structure_builds_in_progress", {{"structure", kind}}, static_cast<double>(b.in_progress));
  w.Family("visq_structure_build_failures_total", "counter",
           "Per-scene structure builds that failed (built again by the next call that needs them), by kind.");
  for (const auto& [kind, b] : f.structure_builds)
    w.Sample("visq_structure_build_failures_total", {{"structure", kind}}, static_cast<double>(b.failures));

  if (f.idle_exploration) {
    const core::IdleExplorer::Figures& idle = *f.idle_exploration;
    w.Single("visq_idle_probes_total", "counter",
             "Probes of the server's choice of method run while no call was in flight (measured or cut).",
             static_cast<double>(idle.probes_run));
    w.Single("visq_idle_probes_preempted_total", "counter",
             "Idle-time probes stopped by a call arriving; each waits for the next quiet spell.",
             static_cast<double>(idle.probes_preempted));
    w.Single("visq_idle_probes_pending", "gauge", "Idle-time probes waiting for a quiet spell.",
             static_cast<double>(idle.pending));
    w.Single("visq_idle_probe_seconds_total", "counter", "Time spent on idle-time probes.", idle.total_ms / 1e3);
  }

  w.Single("visq_gpu_contexts_lost_total", "counter",
           "GPU contexts lost (GPU resets) since start; each failed the job that was running.",
           static_cast<double>(f.gpu_contexts_lost));
  w.Single("visq_scenes_resident", "gauge", "Scenes resident in memory.", static_cast<double>(f.scenes_resident));

  // The standard process_* family, named and described as client_golang's
  // process collector does, so that dashboards written for it work here; a
  // figure /proc did not give is left out.
  const ProcessFigures& p = f.process;
  if (p.cpu_seconds)
    w.Single("process_cpu_seconds_total", "counter", "Total user and system CPU time spent in seconds.", *p.cpu_seconds);
  if (p.open_fds)
    w.Single("process_open_fds", "gauge", "Number of open file descriptors.", static_cast<double>(*p.open_fds));
  if (p.max_fds)
    w.Single("process_max_fds", "gauge", "Maximum number of open file descriptors.", static_cast<double>(*p.max_fds));
  if (p.virtual_bytes)
    w.Single("process_virtual_memory_bytes", "gauge", "Virtual memory size in bytes.",
             static_cast<double>(*p.virtual_bytes));
  if (p.resident_bytes)
    w.Single("process_resident_memory_bytes", "gauge", "Resident memory size in bytes.",
             static_cast<double>(*p.resident_bytes));
  if (p.start_time_seconds)
    w.Single("process_start_time_seconds", "gauge", "Start time of the process since unix epoch in seconds.",
             *p.start_time_seconds);
  return w.Take();
}

}  // namespace visq::service
