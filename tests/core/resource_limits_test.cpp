// The cgroup readers on files in a scratch folder laid out as the kernel
// lays out /proc/self/cgroup and /sys/fs/cgroup: v2 "max" and numbers, v1,
// a limit on a parent cgroup, missing files, and garbage, which must never
// crash and leave the machine's own figure standing.
#include "resource_limits/resource_limits.h"

#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "common/parallel.h"
#include "core/work_budget.h"
#include "test_support.h"

namespace visq::resource_limits {
namespace {

namespace fs = std::filesystem;

constexpr uint64_t kGiB = uint64_t{1} << 30;
constexpr uint64_t kPhysical = 512 * kGiB;

void Write(const fs::path& path, const std::string& text) {
  fs::create_directories(path.parent_path());
  std::ofstream(path, std::ios::binary) << text;
}

// A scratch /proc/self/cgroup and /sys/fs/cgroup.
class CgroupFiles {
 public:
  CgroupFiles() { roots_ = {scratch_.path() / "proc_self_cgroup", scratch_.path() / "sys_fs_cgroup"}; }
  const CgroupRoots& roots() const { return roots_; }
  void ProcSelfCgroup(const std::string& text) { Write(roots_.proc_self_cgroup, text); }
  // `relative` under the mount: "kubepods/pod1/memory.max".
  void Mount(const std::string& relative, const std::string& text) { Write(roots_.cgroup_mount / relative, text); }

 private:
  testing::ScratchDir scratch_;
  CgroupRoots roots_;
};

TEST(MemoryLimit, V2MaxIsNoLimit) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  files.Mount("memory.max", "max\n");
  const MemoryLimit limit = ReadMemoryLimit(files.roots(), kPhysical);
  EXPECT_EQ(limit.bytes, kPhysical);
  EXPECT_EQ(limit.source, "physical memory");
}

TEST(MemoryLimit, V2NumberBelowPhysicalIsTaken) {
  // The pod: 32 GiB on a 512 GiB node, in a cgroup namespace (the
  // container's own cgroup is the mount's root).
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  files.Mount("memory.max", std::to_string(32 * kGiB) + "\n");
  const MemoryLimit limit = ReadMemoryLimit(files.roots(), kPhysical);
  EXPECT_EQ(limit.bytes, 32 * kGiB);
  EXPECT_NE(limit.source.find("cgroup v2 memory.max"), std::string::npos) << limit.source;
  EXPECT_NE(limit.source.find("sys_fs_cgroup"), std::string::npos) << limit.source;
}

TEST(MemoryLimit, V2NumberAbovePhysicalLeavesPhysical) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  files.Mount("memory.max", std::to_string(1024 * kGiB));
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, kPhysical);
}

TEST(MemoryLimit, V2SmallestOfTheCgroupAndItsParents) {
  // A limit on the pod's slice binds a container inside it that has none
  // of its own; the container's own, smaller one binds more.
  CgroupFiles files;
  files.ProcSelfCgroup("0::/kubepods/pod1/container\n");
  files.Mount("kubepods/memory.max", std::to_string(100 * kGiB));
  files.Mount("kubepods/pod1/memory.max", std::to_string(48 * kGiB));
  files.Mount("kubepods/pod1/container/memory.max", "max");
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, 48 * kGiB);
  files.Mount("kubepods/pod1/container/memory.max", std::to_string(20 * kGiB));
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, 20 * kGiB);
}

TEST(MemoryLimit, V2PathTheContainerDoesNotSeeFallsToTheMountsOwnFolder) {
  // Without a cgroup namespace, /proc/self/cgroup names the host's path,
  // and the container's own cgroup is mounted at the root.
  CgroupFiles files;
  files.ProcSelfCgroup("0::/system.slice/docker-abc.scope\n");
  files.Mount("memory.max", std::to_string(8 * kGiB));
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, 8 * kGiB);
}

TEST(MemoryLimit, V1LimitInBytes) {
  CgroupFiles files;
  files.ProcSelfCgroup("12:cpu,cpuacct:/docker/abc\n9:memory:/docker/abc\n0::/\n");
  files.Mount("memory/docker/abc/memory.limit_in_bytes", std::to_string(16 * kGiB) + "\n");
  const MemoryLimit limit = ReadMemoryLimit(files.roots(), kPhysical);
  EXPECT_EQ(limit.bytes, 16 * kGiB);
  EXPECT_NE(limit.source.find("cgroup v1 memory.limit_in_bytes"), std::string::npos) << limit.source;
}

TEST(MemoryLimit, V1UnlimitedIsNoLimit) {
  CgroupFiles files;
  files.ProcSelfCgroup("9:memory:/\n");
  files.Mount("memory/memory.limit_in_bytes", "9223372036854771712\n");
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, kPhysical);
  // Unknown physical memory and no limit: still nothing known.
  EXPECT_EQ(ReadMemoryLimit(files.roots(), 0).bytes, 0u);
}

TEST(MemoryLimit, ALimitStandsWhenPhysicalMemoryIsUnknown) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  files.Mount("memory.max", std::to_string(2 * kGiB));
  EXPECT_EQ(ReadMemoryLimit(files.roots(), 0).bytes, 2 * kGiB);
}

TEST(MemoryLimit, MissingFilesLeavePhysical) {
  CgroupFiles files;  // neither file exists
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, kPhysical);
  files.ProcSelfCgroup("0::/a/b\n9:memory:/a/b\n");  // the cgroup's files do not
  const MemoryLimit limit = ReadMemoryLimit(files.roots(), kPhysical);
  EXPECT_EQ(limit.bytes, kPhysical);
  EXPECT_EQ(limit.source, "physical memory");
}

TEST(MemoryLimit, GarbageNeverCrashesAndLeavesPhysical) {
  const std::string huge_line(100000, '7');
  for (const std::string& proc : {std::string("0::/\n"), std::string("garbage"), std::string(""), std::string(":::"),
                                  std::string("0::\n"), std::string("0::relative/path\n"), std::string("0:/\n"),
                                  std::string("0::/../../../etc\n"), std::string("9:memory/../..:/\n"),
                                  std::string("9:memory:/\0/x\n", 14), huge_line}) {
    for (const std::string& contents :
         {std::string(""), std::string("-1"), std::string("0"), std::string("12abc"), std::string("1 2"),
          std::string("99999999999999999999999999"), std::string("\xff\xfe\x00\x01", 4), std::string("max max"),
          std::string("+5"), huge_line}) {
      CgroupFiles files;
      files.ProcSelfCgroup(proc);
      files.Mount("memory.max", contents);
      files.Mount("memory/memory.limit_in_bytes", contents);
      const MemoryLimit limit = ReadMemoryLimit(files.roots(), kPhysical);
      EXPECT_EQ(limit.bytes, kPhysical) << "/proc/self/cgroup '" << proc.substr(0, 40) << "', limit '"
                                        << contents.substr(0, 40) << "': " << limit.source;
    }
  }
}

TEST(MemoryLimit, AFolderWhereTheFileShouldBeIsNoLimit) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  fs::create_directories(files.roots().cgroup_mount / "memory.max");
  EXPECT_EQ(ReadMemoryLimit(files.roots(), kPhysical).bytes, kPhysical);
}

TEST(CpuLimit, V2QuotaRoundsUp) {
  struct Case {
    const char* cpu_max;
    unsigned cpus;
  };
  for (const Case& c : {Case{"150000 100000", 2}, Case{"100000 100000", 1}, Case{"200000 100000", 2},
                        Case{"50000 100000", 1}, Case{"1000 100000", 1}, Case{"400001 100000", 5},
                        Case{"max 100000", 64}, Case{"6400000 100000", 64}, Case{"9000000 100000", 64}}) {
    CgroupFiles files;
    files.ProcSelfCgroup("0::/\n");
    files.Mount("cpu.max", std::string(c.cpu_max) + "\n");
    const CpuLimit limit = ReadCpuLimit(files.roots(), 64);
    EXPECT_EQ(limit.cpus, c.cpus) << c.cpu_max << ": " << limit.source;
  }
}

TEST(CpuLimit, V2QuotaNamesItsFileAndFigures) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/pod\n");
  files.Mount("pod/cpu.max", "150000 100000\n");
  const CpuLimit limit = ReadCpuLimit(files.roots(), 16);
  EXPECT_EQ(limit.cpus, 2u);
  EXPECT_NE(limit.source.find("cgroup v2 cpu.max"), std::string::npos) << limit.source;
  EXPECT_NE(limit.source.find("(150000 100000)"), std::string::npos) << limit.source;
}

TEST(CpuLimit, AffinityBelowTheQuotaWins) {
  CgroupFiles files;
  files.ProcSelfCgroup("0::/\n");
  files.Mount("cpu.max", "800000 100000");
  const CpuLimit limit = ReadCpuLimit(files.roots(), 3);
  EXPECT_EQ(limit.cpus, 3u);
  EXPECT_EQ(limit.source, "affinity mask");
}

TEST(CpuLimit, V1QuotaOverPeriod) {
  CgroupFiles files;
  files.ProcSelfCgroup("12:cpu,cpuacct:/docker/abc\n9:memory:/docker/abc\n");
  files.Mount("cpu,cpuacct/docker/abc/cpu.cfs_quota_us", "250000\n");
  files.Mount("cpu,cpuacct/docker/abc/cpu.cfs_period_us", "100000\n");
  const CpuLimit limit = ReadCpuLimit(files.roots(), 32);
  EXPECT_EQ(limit.cpus, 3u) << limit.source;
  EXPECT_NE(limit.source.find("cgroup v1 cpu.cfs_quota_us"), std::string::npos) << limit.source;

  files.Mount("cpu,cpuacct/docker/abc/cpu.cfs_quota_us", "-1\n");  // no quota
  EXPECT_EQ(ReadCpuLimit(files.roots(), 32).cpus, 32u);
}

TEST(CpuLimit, MissingFilesAndGarbageLeaveTheAffinityMask) {
  {
    CgroupFiles files;
    EXPECT_EQ(ReadCpuLimit(files.roots(), 8).cpus, 8u);
  }
  for (const std::string& contents :
       {std::string(""), std::string("max"), std::string("0 100000"), std::string("100000 0"), std::string("-1 100000"),
        std::string("abc def"), std::string("150000"), std::string("150000  100000"),
        std::string("99999999999999999999999 1"), std::string(100000, '9')}) {
    CgroupFiles files;
    files.ProcSelfCgroup("0::/\n12:cpu:/\n");
    files.Mount("cpu.max", contents);
    files.Mount("cpu/cpu.cfs_quota_us", contents);
    files.Mount("cpu/cpu.cfs_period_us", "100000");
    const CpuLimit limit = ReadCpuLimit(files.roots(), 8);
    // "150000" alone is a quota: over v2's default period of 100 ms, and
    // over v1's period file, 2.
    EXPECT_EQ(limit.cpus, contents == "150000" ? 2u : 8u) << "'" << contents.substr(0, 40) << "': " << limit.source;
  }
}

TEST(CpuLimit, AtLeastOne) {
  CgroupFiles files;
  EXPECT_EQ(ReadCpuLimit(files.roots(), 0).cpus, 1u);
  files.ProcSelfCgroup("0::/\n");
  files.Mount("cpu.max", "1 1000000");
  EXPECT_EQ(ReadCpuLimit(files.roots(), 4).cpus, 1u);
}

TEST(ProcessLimits, ThePoolFollowsTheCpuLimit) {
  // This machine's own: whatever its cgroup says, the figures are sane and
  // the process's pool is sized by them.
  EXPECT_GE(ProcessCpuLimit().cpus, 1u);
  EXPECT_LE(ProcessCpuLimit().cpus, AffinityCpus());
  EXPECT_EQ(ParallelWorkers(), ProcessCpuLimit().cpus);
  EXPECT_GT(ProcessMemoryLimit().bytes, 0u);
  EXPECT_LE(ProcessMemoryLimit().bytes, PhysicalMemoryBytes());
}

TEST(ProcessLimits, TheWorkBudgetIsHalfOfTheMemoryLimit) {
  const core::WorkMemoryBudget by_default(0);
  EXPECT_EQ(by_default.capacity(), ProcessMemoryLimit().bytes / 2);
  EXPECT_EQ(by_default.capacity_source().rfind("half of " + ProcessMemoryLimit().source, 0), 0u)
      << by_default.capacity_source();
  const core::WorkMemoryBudget given(12345);
  EXPECT_EQ(given.capacity(), 12345u);
  EXPECT_EQ(given.capacity_source(), "as given");
}

// What an answer parks while it waits for its reader leaves a quarter of
// the budget to the calls still to start, and goes back when released.
TEST(ProcessLimits, ParkedAnswersLeaveAQuarterOfTheWorkBudget) {
  core::WorkMemoryBudget budget(1000);
  const JobOptions job;
  auto running = budget.Reserve(500, "a running call", job);
  ASSERT_TRUE(running.ok()) << running.status();
  auto parked = budget.TryReserveSpare(250);
  ASSERT_TRUE(parked.has_value());
  EXPECT_EQ(budget.in_use(), 750u);
  EXPECT_FALSE(budget.TryReserveSpare(1).has_value()) << "parked past three quarters of the budget";
  EXPECT_FALSE(budget.TryReserveSpare(uint64_t{1} << 63).has_value());
  parked.reset();
  EXPECT_EQ(budget.in_use(), 500u);
  EXPECT_TRUE(budget.TryReserveSpare(250).has_value());
  EXPECT_EQ(budget.in_use(), 500u);
}

}  // namespace
}  // namespace visq::resource_limits
