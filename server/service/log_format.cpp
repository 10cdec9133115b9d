#include "service/log_format.h"

#include <chrono>
#include <cmath>
#include <ctime>
#include <memory>

#include <absl/strings/str_cat.h>
#include <absl/strings/str_format.h>
#include <google/protobuf/stubs/logging.h>
#include <grpc/support/log.h>
#include <spdlog/pattern_formatter.h>
#include <spdlog/spdlog.h>

namespace visq::service {
namespace {

// The fields of the innermost ScopedLogFields alive on this thread.
thread_local const std::vector<LogField>* current_fields = nullptr;

bool NeedsEscape(unsigned char c) { return c < 0x20 || c == 0x7f || c == '\\'; }

class EscapingFormatter final : public spdlog::formatter {
 public:
  explicit EscapingFormatter(std::string pattern)
      : pattern_(std::move(pattern)), inner_(std::make_unique<spdlog::pattern_formatter>(pattern_)) {}

  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    const std::string_view payload(msg.payload.data(), msg.payload.size());
    bool clean = true;
    for (char c : payload) clean &= !NeedsEscape(static_cast<unsigned char>(c));
    if (clean) {
      inner_->format(msg, dest);
      return;
    }
    const std::string escaped = EscapeForLog(payload);
    spdlog::details::log_msg copy = msg;
    copy.payload = spdlog::string_view_t(escaped.data(), escaped.size());
    inner_->format(copy, dest);
  }

  std::unique_ptr<spdlog::formatter> clone() const override { return std::make_unique<EscapingFormatter>(pattern_); }

 private:
  std::string pattern_;
  std::unique_ptr<spdlog::pattern_formatter> inner_;
};

class JsonFormatter final : public spdlog::formatter {
 public:
  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    const auto since_epoch = msg.time.time_since_epoch();
    const std::time_t seconds = std::chrono::duration_cast<std::chrono::seconds>(since_epoch).count();
    const auto millis = std::chrono::duration_cast<std::chrono::milliseconds>(since_epoch).count() % 1000;
    std::tm utc{};
    ::gmtime_r(&seconds, &utc);
    const spdlog::string_view_t level = spdlog::level::to_string_view(msg.level);
    const std::string logger = msg.logger_name.size() ? std::string(msg.logger_name.data(), msg.logger_name.size())
                                                      : std::string("visq");
    std::string line = absl::StrFormat(
        "{\"time\":\"%04d-%02d-%02dT%02d:%02d:%02d.%03dZ\",\"level\":\"%s\",\"logger\":\"%s\",\"message\":\"%s\"",
        utc.tm_year + 1900, utc.tm_mon + 1, utc.tm_mday, utc.tm_hour, utc.tm_min, utc.tm_sec,
        static_cast<int>(millis), std::string_view(level.data(), level.size()), EscapeForJson(logger),
        EscapeForJson(std::string_view(msg.payload.data(), msg.payload.size())));
    if (current_fields != nullptr)
      for (const LogField& field : *current_fields) absl::StrAppend(&line, ",\"", EscapeForJson(field.name), "\":", field.json);
    line += "}\n";
    dest.append(line.data(), line.data() + line.size());
  }
  std::unique_ptr<spdlog::formatter> clone() const override { return std::make_unique<JsonFormatter>(); }
};

// The length of the valid UTF-8 sequence at text[i], or 0 (RFC 3629: no
// overlong forms, no surrogates, nothing past U+10FFFF).
size_t Utf8SequenceLength(std::string_view text, size_t i) {
  const auto byte = [&](size_t k) { return static_cast<unsigned char>(text[k]); };
  const unsigned char c = byte(i);
  size_t n = 0;
  unsigned char low = 0x80, high = 0xbf;  // the second byte's range
  if (c >= 0xc2 && c <= 0xdf) n = 2;
  else if (c >= 0xe0 && c <= 0xef) {
    n = 3;
    if (c == 0xe0) low = 0xa0;
    if (c == 0xed) high = 0x9f;
  } else if (c >= 0xf0 && c <= 0xf4) {
    n = 4;
    if (c == 0xf0) low = 0x90;
    if (c == 0xf4) high = 0x8f;
  } else {
    return 0;
  }
  if (i + n > text.size()) return 0;
  if (byte(i + 1) < low || byte(i + 1) > high) return 0;
  for (size_t k = 2; k < n; ++k)
    if (byte(i + k) < 0x80 || byte(i + k) > 0xbf) return 0;
  return n;
}

}  // namespace

std::string EscapeForJson(std::string_view text) {
  std::string out;
  out.reserve(text.size() + 8);
  for (size_t i = 0; i < text.size();) {
    const auto c = static_cast<unsigned char>(text[i]);
    if (c >= 0x80) {
      const size_t n = Utf8SequenceLength(text, i);
      if (n == 0) {
        out += "\\ufffd";
        ++i;
      } else {
        out.append(text.substr(i, n));
        i += n;
      }
      continue;
    }
    if (c == '"') out += "\\\"";
    else if (c == '\\') out += "\\\\";
    else if (c == '\n') out += "\\n";
    else if (c == '\r') out += "\\r";
    else if (c == '\t') out += "\\t";
    else if (c < 0x20 || c == 0x7f) out += absl::StrFormat("\\u%04x", c);
    else out += static_cast<char>(c);
    ++i;
  }
  return out;
}

void RouteLibraryLogsToSpdlog() {
  google::protobuf::SetLogHandler([](google::protobuf::LogLevel level, const char* file, int line,
                                     const std::string& message) {
    const auto spd = level >= google::protobuf::LOGLEVEL_ERROR     ? spdlog::level::err
                     : level == google::protobuf::LOGLEVEL_WARNING ? spdlog::level::warn
                                                                   : spdlog::level::info;
    spdlog::log(spd, "protobuf {}:{}: {}", file, line, message);
  });
  gpr_set_log_function([](gpr_log_func_args* args) {
    const auto spd = args->severity == GPR_LOG_SEVERITY_ERROR  ? spdlog::level::err
                     : args->severity == GPR_LOG_SEVERITY_INFO ? spdlog::level::info
                                                                : spdlog::level::debug;
    spdlog::log(spd, "grpc {}:{}: {}", args->file, args->line, args->message);
  });
}

LogField LogField::String(std::string name, std::string_view value) {
  return {std::move(name), absl::StrCat("\"", EscapeForJson(value), "\"")};
}

LogField LogField::Number(std::string name, double value) {
  return {std::move(name), std::isfinite(value) ? absl::StrFormat("%.3f", value) : std::string("null")};
}

ScopedLogFields::ScopedLogFields(std::vector<LogField> fields) : fields_(std::move(fields)), outer_(current_fields) {
  current_fields = &fields_;
}

ScopedLogFields::~ScopedLogFields() { current_fields = outer_; }

void UseJsonLogFormat() { spdlog::set_formatter(std::make_unique<JsonFormatter>()); }

std::string EscapeForLog(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (char ch : text) {
    const auto c = static_cast<unsigned char>(ch);
    if (!NeedsEscape(c)) out += ch;
    else if (c == '\n') out += "\\n";
    else if (c == '\r') out += "\\r";
    else if (c == '\t') out += "\\t";
    else if (c == '\\') out += "\\\\";
    else out += absl::StrFormat("\\x%02x", c);
  }
  return out;
}

void UseEscapingLogFormat(const std::string& pattern) {
  spdlog::set_formatter(std::make_unique<EscapingFormatter>(pattern));
}

}  // namespace visq::service
