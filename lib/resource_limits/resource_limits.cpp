#include "resource_limits/resource_limits.h"

#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <climits>
#include <fstream>
#include <optional>
#include <string_view>
#include <thread>
#include <vector>

namespace visq::resource_limits {
namespace {

namespace fs = std::filesystem;

// Every file read here is a line or a few; more than this is not one of
// the kernel's, and is read no further.
constexpr size_t kMaxFileBytes = 64 << 10;
// v1 writes "no limit" as the largest page-aligned signed 64-bit number
// (9223372036854771712); any figure this large is none.
constexpr uint64_t kNoLimitAbove = uint64_t{1} << 62;
// A cgroup path deeper than this is not a real one; stop climbing.
constexpr int kMaxDepth = 64;

std::optional<std::string> ReadSmallFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::string text(kMaxFileBytes, '\0');
  in.read(text.data(), static_cast<std::streamsize>(text.size()));
  text.resize(static_cast<size_t>(in.gcount()));
  return text;
}

std::string_view Trim(std::string_view text) {
  const auto space = [](char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; };
  while (!text.empty() && space(text.front())) text.remove_prefix(1);
  while (!text.empty() && space(text.back())) text.remove_suffix(1);
  return text;
}

// The whole of `text` as a decimal number; nullopt for anything else
// (signs, spaces inside, trailing text, overflow).
template <typename Integer>
std::optional<Integer> ParseWhole(std::string_view text) {
  Integer value{};
  const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || error != std::errc() || end != text.data() + text.size()) return std::nullopt;
  return value;
}

// One hierarchy the process sits in: where its controllers' files are
// (the v2 mount, or v1's folder for a controller) and the process's path
// inside it.
struct Hierarchy {
  bool v2 = false;
  std::vector<fs::path> folders;  // v1: the controller's folder under several names
  fs::path cgroup;                // "/kubepods/pod1/abc", absolute
};

// The hierarchies of /proc/self/cgroup that hold `controller` (v1), and
// the v2 one. Lines that do not read as "ID:CONTROLLERS:PATH" are skipped.
std::vector<Hierarchy> HierarchiesOf(const CgroupRoots& roots, std::string_view controller) {
  std::vector<Hierarchy> out;
  const std::optional<std::string> text = ReadSmallFile(roots.proc_self_cgroup);
  if (!text) return out;
  std::string_view rest = *text;
  while (!rest.empty()) {
    const size_t newline = rest.find('\n');
    const std::string_view line = rest.substr(0, newline);
    rest = newline == std::string_view::npos ? std::string_view() : rest.substr(newline + 1);
    // The path is everything after the second colon: it may hold colons.
    const size_t first = line.find(':');
    const size_t second = first == std::string_view::npos ? first : line.find(':', first + 1);
    if (second == std::string_view::npos) continue;
    const std::string_view id = line.substr(0, first), controllers = line.substr(first + 1, second - first - 1);
    const std::string_view path = line.substr(second + 1);
    if (path.empty() || path.front() != '/' || path.find('\0') != std::string_view::npos) continue;
    Hierarchy h;
    // Lexically normal and absolute: ".." cannot climb above the mount.
    h.cgroup = fs::path(path).lexically_normal();
    if (id == "0" && controllers.empty()) {
      h.v2 = true;
      h.folders = {roots.cgroup_mount};
    } else {
      bool holds = false;
      for (size_t begin = 0; begin <= controllers.size();) {
        const size_t comma = std::min(controllers.find(',', begin), controllers.size());
        holds |= controllers.substr(begin, comma - begin) == controller;
        begin = comma + 1;
      }
      // A folder name is one component: a list with a slash is not one.
      if (!holds || controllers.find('/') != std::string_view::npos || controllers == "." || controllers == "..")
        continue;
      // Mounted under the list's name ("cpu,cpuacct"), with a link named
      // for each controller ("cpu") on most systems.
      h.folders = {roots.cgroup_mount / std::string(controllers)};
      if (controllers != controller) h.folders.push_back(roots.cgroup_mount / std::string(controller));
    }
    out.push_back(std::move(h));
  }
  return out;
}

// `path` without "." and "..", nor a trailing separator (which would make
// "a/b/" and "a/b" two folders).
fs::path Normal(const fs::path& path) {
  fs::path normal = path.lexically_normal();
  if (normal.filename().empty() && normal.has_relative_path()) normal = normal.parent_path();
  return normal;
}

// `file` in the process's cgroup and in each one above it, up to the
// mount: without a cgroup namespace the path names a folder the container
// does not see, and the limit is in the mount's own folder.
template <typename Visit>
void ForEachLevel(const Hierarchy& h, const std::string& file, Visit&& visit) {
  for (const fs::path& folder : h.folders) {
    fs::path level = Normal(folder / h.cgroup.relative_path());
    const fs::path top = Normal(folder);
    for (int depth = 0; depth < kMaxDepth; ++depth) {
      if (std::optional<std::string> text = ReadSmallFile(level / file)) visit(level / file, Trim(*text));
      if (level == top || !level.has_relative_path() || level.parent_path() == level) break;
      level = level.parent_path();
    }
  }
}

// A v2 cpu.max "QUOTA PERIOD" ("max PERIOD": none) as whole CPUs, rounded
// up; nullopt for none or garbage.
std::optional<uint64_t> CpusOfQuota(uint64_t quota, uint64_t period) {
  if (quota == 0 || period == 0) return std::nullopt;
  return quota / period + (quota % period != 0 ? 1 : 0);
}

}  // namespace

MemoryLimit ReadMemoryLimit(const CgroupRoots& roots, uint64_t physical_bytes) {
  MemoryLimit best{physical_bytes, "physical memory"};
  // 0 (nothing known) loses to any limit.
  const auto consider = [&](uint64_t bytes, const fs::path& file, const char* kind) {
    if (bytes == 0 || bytes >= kNoLimitAbove) return;
    if (best.bytes == 0 || bytes < best.bytes) best = {bytes, std::string(kind) + " " + file.string()};
  };
  for (const Hierarchy& h : HierarchiesOf(roots, "memory")) {
    if (h.v2) {
      ForEachLevel(h, "memory.max", [&](const fs::path& file, std::string_view text) {
        if (const auto bytes = ParseWhole<uint64_t>(text)) consider(*bytes, file, "cgroup v2 memory.max");
      });
    } else {
      ForEachLevel(h, "memory.limit_in_bytes", [&](const fs::path& file, std::string_view text) {
        if (const auto bytes = ParseWhole<uint64_t>(text)) consider(*bytes, file, "cgroup v1 memory.limit_in_bytes");
      });
    }
  }
  return best;
}

CpuLimit ReadCpuLimit(const CgroupRoots& roots, unsigned affinity_cpus) {
  CpuLimit best{std::max(affinity_cpus, 1u), "affinity mask"};
  const auto consider = [&](uint64_t quota, uint64_t period, const fs::path& file, const char* kind) {
    const std::optional<uint64_t> cpus = CpusOfQuota(quota, period);
    if (!cpus || *cpus >= best.cpus) return;
    best = {static_cast<unsigned>(std::max<uint64_t>(*cpus, 1)),
            std::string(kind) + " " + file.string() + " (" + std::to_string(quota) + " " + std::to_string(period) +
                ")"};
  };
  for (const Hierarchy& h : HierarchiesOf(roots, "cpu")) {
    if (h.v2) {
      ForEachLevel(h, "cpu.max", [&](const fs::path& file, std::string_view text) {
        // "QUOTA PERIOD"; the kernel always writes both, an older one may
        // write the quota alone (its period is 100 ms).
        const size_t space = text.find(' ');
        const std::optional<uint64_t> quota = ParseWhole<uint64_t>(text.substr(0, space));
        const std::optional<uint64_t> period =
            space == std::string_view::npos ? std::optional<uint64_t>(100000) : ParseWhole<uint64_t>(text.substr(space + 1));
        if (quota && period) consider(*quota, *period, file, "cgroup v2 cpu.max");
      });
    } else {
      ForEachLevel(h, "cpu.cfs_quota_us", [&](const fs::path& file, std::string_view text) {
        const std::optional<int64_t> quota = ParseWhole<int64_t>(text);  // -1: none
        const std::optional<std::string> period_text = ReadSmallFile(file.parent_path() / "cpu.cfs_period_us");
        const std::optional<int64_t> period =
            period_text ? ParseWhole<int64_t>(Trim(*period_text)) : std::optional<int64_t>();
        if (quota && period && *quota > 0 && *period > 0)
          consider(static_cast<uint64_t>(*quota), static_cast<uint64_t>(*period), file, "cgroup v1 cpu.cfs_quota_us");
      });
    }
  }
  return best;
}

uint64_t PhysicalMemoryBytes() {
  const long pages = ::sysconf(_SC_PHYS_PAGES), page = ::sysconf(_SC_PAGE_SIZE);
  if (pages <= 0 || page <= 0) return 0;
  if (uint64_t(pages) > UINT64_MAX / uint64_t(page)) return UINT64_MAX;
  return uint64_t(pages) * uint64_t(page);
}

unsigned AffinityCpus() {
  // The set's size must cover the kernel's CPU count, which may exceed
  // CPU_SETSIZE: grow it while the kernel says it is too small.
  for (int cpus = CPU_SETSIZE; cpus <= (1 << 20); cpus *= 2) {
    cpu_set_t* set = CPU_ALLOC(cpus);
    if (set == nullptr) break;
    const size_t size = CPU_ALLOC_SIZE(cpus);
    CPU_ZERO_S(size, set);
    const int result = ::sched_getaffinity(0, size, set);
    const int error = errno;
    const int count = result == 0 ? CPU_COUNT_S(size, set) : 0;
    CPU_FREE(set);
    if (count > 0) return static_cast<unsigned>(count);
    if (result != 0 && error == EINVAL) continue;
    break;
  }
  return std::max(1u, std::thread::hardware_concurrency());
}

const MemoryLimit& ProcessMemoryLimit() {
  static const MemoryLimit limit = ReadMemoryLimit(CgroupRoots{}, PhysicalMemoryBytes());
  return limit;
}

const CpuLimit& ProcessCpuLimit() {
  static const CpuLimit limit = ReadCpuLimit(CgroupRoots{}, AffinityCpus());
  return limit;
}

}  // namespace visq::resource_limits
