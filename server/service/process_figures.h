// The process's own figures as Prometheus' standard process_* family
// reports them (client_golang's process collector): CPU time, resident and
// virtual memory, open and allowed file descriptors, start time. Read from
// /proc at each scrape, so that dashboards and alerts written for any
// Prometheus-instrumented server work on visq unchanged.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>

namespace visq::service {

struct ProcessFigures {
  // Each is absent when its file cannot be read or does not parse: a
  // scrape leaves the sample out rather than report a made-up 0.
  std::optional<double> cpu_seconds;          // user + system
  std::optional<uint64_t> resident_bytes;
  std::optional<uint64_t> virtual_bytes;
  std::optional<uint64_t> open_fds;
  std::optional<uint64_t> max_fds;            // the soft limit ("unlimited": absent)
  std::optional<double> start_time_seconds;   // since the Unix epoch
};

// `proc` is /proc; a test points it at a scratch folder holding self/stat,
// self/limits, self/fd/ and stat. `ticks_per_second` and `page_bytes` are
// the kernel's units there (sysconf's _SC_CLK_TCK and _SC_PAGE_SIZE).
ProcessFigures ReadProcessFigures(const std::filesystem::path& proc, long ticks_per_second, long page_bytes);
// This process's, from /proc with this machine's units.
ProcessFigures ReadProcessFigures();

}  // namespace visq::service
