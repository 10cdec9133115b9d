#include "service/process_figures.h"

#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <fstream>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

namespace visq::service {
namespace {

namespace fs = std::filesystem;

// /proc/self/stat and /proc/self/limits are a line or a few; /proc/stat
// grows with the CPUs (a line each) but its btime line comes early enough.
constexpr std::streamsize kMaxFileBytes = 1 << 20;

std::optional<std::string> ReadSmallFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::string text;
  char buffer[4096];
  while (static_cast<std::streamsize>(text.size()) < kMaxFileBytes && in.read(buffer, sizeof(buffer)).gcount() > 0)
    text.append(buffer, static_cast<size_t>(in.gcount()));
  return text;
}

std::optional<uint64_t> ParseWhole(std::string_view text) {
  uint64_t value = 0;
  const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || error != std::errc() || end != text.data() + text.size()) return std::nullopt;
  return value;
}

std::vector<std::string_view> Words(std::string_view text) {
  std::vector<std::string_view> words;
  size_t begin = 0;
  while (begin < text.size()) {
    while (begin < text.size() && (text[begin] == ' ' || text[begin] == '\t' || text[begin] == '\n')) ++begin;
    size_t end = begin;
    while (end < text.size() && text[end] != ' ' && text[end] != '\t' && text[end] != '\n') ++end;
    if (end > begin) words.push_back(text.substr(begin, end - begin));
    begin = end;
  }
  return words;
}

// The line of `text` that starts with `prefix`, without it.
std::optional<std::string_view> LineAfter(std::string_view text, std::string_view prefix) {
  for (size_t begin = 0; begin < text.size();) {
    const size_t end = std::min(text.find('\n', begin), text.size());
    const std::string_view line = text.substr(begin, end - begin);
    if (line.substr(0, prefix.size()) == prefix) return line.substr(prefix.size());
    begin = end + 1;
  }
  return std::nullopt;
}

}  // namespace

ProcessFigures ReadProcessFigures(const fs::path& proc, long ticks_per_second, long page_bytes) {
  ProcessFigures f;
  const double ticks = ticks_per_second > 0 ? static_cast<double>(ticks_per_second) : 0.0;

  // self/stat: "PID (COMM) STATE PPID ...". COMM may hold spaces and
  // parentheses, so the fields are counted from the last ')'; the one after
  // it is field 3 (man 5 proc).
  if (const std::optional<std::string> stat = ReadSmallFile(proc / "self" / "stat")) {
    const size_t close = stat->rfind(')');
    if (close != std::string::npos) {
      const std::vector<std::string_view> fields = Words(std::string_view(*stat).substr(close + 1));
      const auto field = [&](size_t number) -> std::optional<uint64_t> {
        return number - 3 < fields.size() ? ParseWhole(fields[number - 3]) : std::nullopt;
      };
      const std::optional<uint64_t> utime = field(14), stime = field(15);
      if (utime && stime && ticks > 0) f.cpu_seconds = static_cast<double>(*utime + *stime) / ticks;
      f.virtual_bytes = field(23);
      if (const std::optional<uint64_t> rss_pages = field(24); rss_pages && page_bytes > 0)
        f.resident_bytes = *rss_pages * static_cast<uint64_t>(page_bytes);
      // Start time: ticks after boot, plus the boot time (/proc/stat btime).
      const std::optional<uint64_t> start_ticks = field(22);
      const std::optional<std::string> system_stat = ReadSmallFile(proc / "stat");
      const std::optional<std::string_view> btime =
          system_stat ? LineAfter(*system_stat, "btime ") : std::nullopt;
      const std::optional<uint64_t> boot_seconds = btime ? ParseWhole(*btime) : std::nullopt;
      if (start_ticks && boot_seconds && ticks > 0)
        f.start_time_seconds = static_cast<double>(*boot_seconds) + static_cast<double>(*start_ticks) / ticks;
    }
  }

  // self/fd: one entry per descriptor (the one this listing holds among
  // them, as client_golang counts too).
  std::error_code error;
  uint64_t open = 0;
  for (fs::directory_iterator it(proc / "self" / "fd", error), end; !error && it != end; it.increment(error)) ++open;
  if (!error) f.open_fds = open;

  // self/limits: "Max open files  SOFT  HARD  files".
  if (const std::optional<std::string> limits = ReadSmallFile(proc / "self" / "limits"))
    if (const std::optional<std::string_view> line = LineAfter(*limits, "Max open files"))
      if (const std::vector<std::string_view> words = Words(*line); !words.empty())
        f.max_fds = ParseWhole(words[0]);  // "unlimited" does not parse: absent
  return f;
}

ProcessFigures ReadProcessFigures() {
  return ReadProcessFigures("/proc", ::sysconf(_SC_CLK_TCK), ::sysconf(_SC_PAGE_SIZE));
}

}  // namespace visq::service
