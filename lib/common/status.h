// Status values at module boundaries: visq/status.h (the public floor, also
// installed for clients) defines Status, StatusOr and the propagation
// macros; this header adds what the source tree's floors also use.
#pragma once

#include <absl/strings/str_cat.h>
#include <fmt/format.h>

#include <string_view>

#include "visq/status.h"

namespace visq {

// Debian 12's absl is built with its own absl::string_view, distinct from
// std::string_view: convert explicitly where a std::string_view meets absl.
inline absl::string_view AbslView(std::string_view s) { return absl::string_view(s.data(), s.size()); }

}  // namespace visq

// Lets spdlog/fmt print absl::string_view (Status::message()) directly.
template <>
struct fmt::formatter<absl::string_view> : fmt::formatter<fmt::string_view> {
  auto format(absl::string_view s, fmt::format_context& ctx) const {
    return fmt::formatter<fmt::string_view>::format(fmt::string_view(s.data(), s.size()), ctx);
  }
};
