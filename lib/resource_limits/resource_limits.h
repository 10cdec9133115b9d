// What this process may use of the machine: the memory and the CPUs its
// container (cgroup v2 or v1) and its affinity mask allow, not the whole
// machine's. A pod limited to 32 GiB on a 512 GiB node sees 512 GiB through
// sysconf(_SC_PHYS_PAGES), and one with a quota of 2 CPUs on a 64-core node
// sees 64 through hardware_concurrency(): sizing by those gets the pod
// OOM-killed by the kubelet, or throttled, instead of visq refusing work.
//
// The readers take the file system's roots as parameters, so a test points
// them at files in a scratch folder. Whatever the files hold (missing,
// unreadable, garbage, a path that climbs out of the mount) they never
// fail: a limit that cannot be read is no limit, and the machine's own
// figure stands.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

namespace visq::resource_limits {

// Where the kernel shows this process's cgroups; a test points these at a
// scratch folder.
struct CgroupRoots {
  // Lines "ID:CONTROLLERS:PATH": "0::PATH" for cgroup v2, "4:memory:PATH"
  // and "3:cpu,cpuacct:PATH" for v1.
  std::filesystem::path proc_self_cgroup = "/proc/self/cgroup";
  // The v2 hierarchy itself, or the folder holding v1's one per
  // controller (memory/, cpu,cpuacct/).
  std::filesystem::path cgroup_mount = "/sys/fs/cgroup";
};

struct MemoryLimit {
  uint64_t bytes = 0;  // 0: unknown (no physical figure and no limit)
  // For the start-up log: "physical memory", or the limit's file and kind,
  // "cgroup v2 memory.max /sys/fs/cgroup/memory.max".
  std::string source;
};

struct CpuLimit {
  unsigned cpus = 1;  // at least 1
  // "affinity mask", or the quota's file and its figures,
  // "cgroup v2 cpu.max /sys/fs/cgroup/cpu.max (150000 100000)".
  std::string source;
};

// The smaller of `physical_bytes` and the memory limits of the process's
// cgroup and of every cgroup above it (a limit set on a parent, a pod's
// slice, binds too): v2 memory.max ("max" is none), v1
// memory.limit_in_bytes (its "unlimited" is a huge number, also none).
MemoryLimit ReadMemoryLimit(const CgroupRoots& roots, uint64_t physical_bytes);

// The smaller of `affinity_cpus` and the CPU quota of the process's cgroup
// and those above it, in whole CPUs rounded up (a quota of 1.5 CPUs keeps
// 2 workers busy half the time each rather than leave half a CPU unused):
// v2 cpu.max "QUOTA PERIOD" ("max" is none), v1 cpu.cfs_quota_us (-1 is
// none) over cpu.cfs_period_us. At least 1.
CpuLimit ReadCpuLimit(const CgroupRoots& roots, unsigned affinity_cpus);

// The machine's memory (sysconf); 0 when it cannot say.
uint64_t PhysicalMemoryBytes();
// The CPUs this process may run on (sched_getaffinity; taskset, a
// cpuset-pinned container), else hardware_concurrency(); at least 1.
unsigned AffinityCpus();

// This process's limits, read once at first use from /proc and /sys.
const MemoryLimit& ProcessMemoryLimit();
const CpuLimit& ProcessCpuLimit();

}  // namespace visq::resource_limits
