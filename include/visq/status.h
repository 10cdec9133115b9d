// Status values at module boundaries, for every floor and for programs that
// use the installed client. visq uses absl::Status / absl::StatusOr (the
// library gRPC itself is built on); this header adds the two propagation
// helpers absl keeps private. lib/common/status.h adds what only the source
// tree needs (fmt formatting, string_view conversion).
#pragma once

#include <absl/status/status.h>
#include <absl/status/statusor.h>

#include <utility>

namespace visq {

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
