// The process_* figures from a scratch /proc laid out as the kernel's (a
// command name with spaces and parentheses, an unlimited descriptor limit,
// missing and garbage files), and from this process's own /proc.
#include "service/process_figures.h"

#include <fcntl.h>
#include <unistd.h>

#include <ctime>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "test_support.h"

namespace visq::service {
namespace {

namespace fs = std::filesystem;

void Write(const fs::path& path, const std::string& text) {
  fs::create_directories(path.parent_path());
  std::ofstream(path, std::ios::binary) << text;
}

// Fields 1..52 of /proc/PID/stat with the ones read here set: utime (14)
// 250 ticks, stime (15) 150, starttime (22) 5000, vsize (23), rss (24) pages.
std::string StatLine(const std::string& command) {
  std::string line = "4242 (" + command + ") S";
  for (int field = 4; field <= 52; ++field) {
    std::string value = "0";
    if (field == 14) value = "250";
    if (field == 15) value = "150";
    if (field == 22) value = "5000";
    if (field == 23) value = "987654321";
    if (field == 24) value = "1000";
    line += " " + value;
  }
  return line + "\n";
}

TEST(ProcessFigures, ReadsTheStandardFiguresFromProc) {
  testing::ScratchDir proc;
  Write(proc.path() / "self" / "stat", StatLine("visq server) (x"));  // ')' inside the name
  Write(proc.path() / "stat", "cpu  1 2 3\ncpu0 1 2 3\nintr 1 2 3\nbtime 1764900000\nprocesses 9\n");
  Write(proc.path() / "self" / "limits",
        "Limit                     Soft Limit           Hard Limit           Units     \n"
        "Max cpu time              unlimited            unlimited            seconds   \n"
        "Max open files            1024                 524288               files     \n");
  for (int fd = 0; fd < 5; ++fd) Write(proc.path() / "self" / "fd" / std::to_string(fd), "");

  const ProcessFigures f = ReadProcessFigures(proc.path(), /*ticks_per_second=*/100, /*page_bytes=*/4096);
  ASSERT_TRUE(f.cpu_seconds);
  EXPECT_DOUBLE_EQ(*f.cpu_seconds, 4.0);  // (250 + 150) / 100
  ASSERT_TRUE(f.start_time_seconds);
  EXPECT_DOUBLE_EQ(*f.start_time_seconds, 1764900050.0);  // btime + 5000 / 100
  EXPECT_EQ(f.virtual_bytes, 987654321u);
  EXPECT_EQ(f.resident_bytes, 1000u * 4096);
  EXPECT_EQ(f.open_fds, 5u);
  EXPECT_EQ(f.max_fds, 1024u);  // the soft limit, the one that refuses an open
}

TEST(ProcessFigures, MissingAndGarbageFilesLeaveFiguresOutAndNeverCrash) {
  {
    testing::ScratchDir proc;  // nothing at all
    const ProcessFigures f = ReadProcessFigures(proc.path(), 100, 4096);
    EXPECT_FALSE(f.cpu_seconds || f.resident_bytes || f.virtual_bytes || f.open_fds || f.max_fds ||
                 f.start_time_seconds);
  }
  for (const std::string& stat : {std::string(""), std::string("garbage"), std::string("1 (x"), std::string("1 (x) S"),
                                  std::string("1 (x) S 1 2 3 4 5 6 7 8 9 10 -5 abc"), std::string(200000, ')')}) {
    testing::ScratchDir proc;
    Write(proc.path() / "self" / "stat", stat);
    Write(proc.path() / "stat", "btime not-a-number\n");
    Write(proc.path() / "self" / "limits", "Max open files            unlimited            unlimited            files\n");
    const ProcessFigures f = ReadProcessFigures(proc.path(), 100, 4096);
    EXPECT_FALSE(f.cpu_seconds || f.resident_bytes || f.virtual_bytes || f.start_time_seconds) << stat.substr(0, 40);
    EXPECT_FALSE(f.max_fds) << "unlimited has no number";
    EXPECT_FALSE(f.open_fds) << "no self/fd folder";
  }
  // A good stat line without /proc/stat's btime: no start time, the rest.
  testing::ScratchDir proc;
  Write(proc.path() / "self" / "stat", StatLine("visq-server"));
  const ProcessFigures f = ReadProcessFigures(proc.path(), 100, 4096);
  EXPECT_TRUE(f.cpu_seconds);
  EXPECT_FALSE(f.start_time_seconds);
  // Units the machine could not give: no figure in them.
  const ProcessFigures unitless = ReadProcessFigures(proc.path(), -1, -1);
  EXPECT_FALSE(unitless.cpu_seconds || unitless.resident_bytes);
  EXPECT_TRUE(unitless.virtual_bytes) << "bytes already";
}

TEST(ProcessFigures, ThisProcessFiguresAreSane) {
  // Burn a little CPU, open a descriptor: both show.
  volatile double sink = 0;
  for (int i = 0; i < 20000000; ++i) sink = sink + i * 1e-9;
  const ProcessFigures before = ReadProcessFigures();
  const int fd = ::open("/proc/self/stat", O_RDONLY | O_CLOEXEC);
  ASSERT_GE(fd, 0);
  const ProcessFigures after = ReadProcessFigures();
  ::close(fd);

  ASSERT_TRUE(before.cpu_seconds && before.resident_bytes && before.virtual_bytes && before.open_fds &&
              before.start_time_seconds);
  EXPECT_GT(*before.cpu_seconds, 0.0);
  EXPECT_GT(*before.resident_bytes, uint64_t{1} << 20);
  EXPECT_GE(*before.virtual_bytes, *before.resident_bytes);
  EXPECT_EQ(*after.open_fds, *before.open_fds + 1);
  if (before.max_fds) {
    EXPECT_GE(*before.max_fds, *before.open_fds);
  }
  // Started within the last day, not in the future (a second's slack for
  // the clock tick rounding).
  const double now = static_cast<double>(std::time(nullptr));
  EXPECT_LE(*before.start_time_seconds, now + 1);
  EXPECT_GT(*before.start_time_seconds, now - 86400);
}

}  // namespace
}  // namespace visq::service
