// Log lines that a client cannot forge: every line's text has its control
// characters escaped, whatever string a caller formats into it (scene names,
// file names and status messages come from clients).
#pragma once

#include <string>
#include <string_view>
#include <vector>

namespace visq::service {

// `text` with bytes below 0x20 and 0x7f written as \n, \r, \t or \xNN and
// backslashes doubled; the same text when there is nothing to escape.
std::string EscapeForLog(std::string_view text);

// Makes spdlog's default logger format with `pattern` and escape every
// message's text first.
void UseEscapingLogFormat(const std::string& pattern);

// `text` as the inside of a JSON string: quote, backslash and every control
// character escaped, and each byte that is not part of valid UTF-8 replaced
// by U+FFFD, so that any parser takes the line.
std::string EscapeForJson(std::string_view text);

// One JSON object a line, for log collectors:
// {"time":"2026-01-02T03:04:05.678Z","level":"info","logger":"visq","message":"..."}
// with the time in UTC (RFC 3339), and the ScopedLogFields of the logging
// thread after "message".
void UseJsonLogFormat();

// A member of the JSON format's lines beside "message": its name and its
// value written as JSON (a quoted, escaped string, or a number).
struct LogField {
  std::string name;
  std::string json;
  static LogField String(std::string name, std::string_view value);
  // A finite number with 3 decimals; null otherwise.
  static LogField Number(std::string name, double value);
};

// While it lives, every line the calling thread logs in the JSON format
// carries `fields` as members of their own after "message", so that a log
// collector indexes them without parsing the message; the text format
// leaves them out (its message says the same). spdlog's loggers here are
// synchronous: a line is formatted on the thread that logs it. An inner
// scope's fields replace the outer's until it ends. Names must not be
// time, level, logger or message.
class ScopedLogFields {
 public:
  explicit ScopedLogFields(std::vector<LogField> fields);
  ~ScopedLogFields();
  ScopedLogFields(const ScopedLogFields&) = delete;
  ScopedLogFields& operator=(const ScopedLogFields&) = delete;

 private:
  std::vector<LogField> fields_;
  const std::vector<LogField>* outer_;
};

// Sends what protobuf and gRPC log (to stderr, by default) through spdlog,
// so that those lines take the chosen format and escaping too.
void RouteLibraryLogsToSpdlog();

}  // namespace visq::service
