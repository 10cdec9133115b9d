// Log lines that a client cannot forge: every line's text has its control
// characters escaped, whatever string a caller formats into it (scene names,
// file names and status messages come from clients).
#pragma once

#include <string>
#include <string_view>

namespace visq::service {

// `text` with bytes below 0x20 and 0x7f written as \n, \r, \t or \xNN and
// backslashes doubled; the same text when there is nothing to escape.
std::string EscapeForLog(std::string_view text);

// Makes spdlog's default logger format with `pattern` and escape every
// message's text first.
void UseEscapingLogFormat(const std::string& pattern);

}  // namespace visq::service
