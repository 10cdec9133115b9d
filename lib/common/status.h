// Status values at module boundaries. visq uses absl::Status / absl::StatusOr
// (the library gRPC itself is built on); this header adds the two propagation
// helpers absl keeps private.
#pragma once

#include <absl/status/status.h>
#include <absl/status/statusor.h>
#include <absl/strings/str_cat.h>
#include <fmt/format.h>

#include <string_view>

namespace visq {

// Debian 12's absl is built with its own absl::string_view, distinct from
// std::string_view: convert explicitly where a std::string_view meets absl.
inline absl::string_view AbslView(std::string_view s) { return absl::string_view(s.data(), s.size()); }

using Status = absl::Status;
template <typename T>
using StatusOr = absl::StatusOr<T>;

}  // namespace visq

#define VISQ_STATUS_CONCAT_INNER(a, b) a##b
#define VISQ_STATUS_CONCAT(a, b) VISQ_STATUS_CONCAT_INNER(a, b)

// Returns from the enclosing function when `expr` yields a non-OK Status.
#define VISQ_RETURN_IF_ERROR(expr)                   \
  do {                                               \
    ::absl::Status visq_status_ = (expr);            \
    if (!visq_status_.ok()) return visq_status_;     \
  } while (false)

// `lhs = value of expr` or return its error. lhs may be a declaration.
#define VISQ_ASSIGN_OR_RETURN(lhs, expr) \
  VISQ_ASSIGN_OR_RETURN_IMPL(VISQ_STATUS_CONCAT(visq_statusor_, __LINE__), lhs, expr)
#define VISQ_ASSIGN_OR_RETURN_IMPL(tmp, lhs, expr) \
  auto tmp = (expr);                               \
  if (!tmp.ok()) return std::move(tmp).status();   \
  lhs = std::move(tmp).value()

// Lets spdlog/fmt print absl::string_view (Status::message()) directly.
template <>
struct fmt::formatter<absl::string_view> : fmt::formatter<fmt::string_view> {
  auto format(absl::string_view s, fmt::format_context& ctx) const {
    return fmt::formatter<fmt::string_view>::format(fmt::string_view(s.data(), s.size()), ctx);
  }
};
