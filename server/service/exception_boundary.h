// Where a handler's work meets gRPC's threads and the executor's: an
// exception that escapes the work (a library that throws on a hostile file,
// an allocation that fails) becomes the call's INTERNAL status and an error
// log line. Escaping further it would reach a thread's top, and
// std::terminate would end every other client's calls with the process.
#pragma once

#include <exception>
#include <string>

#include <absl/strings/str_cat.h>
#include <spdlog/spdlog.h>

#include "common/status.h"

namespace visq::service {

// The exception being handled (call only inside a catch block), logged under
// the request `id` and `method`, as the status the call fails with.
inline Status StatusOfCurrentException(const std::string& id, const char* method) {
  std::string what = "an exception that is not a std::exception";
  try {
    throw;
  } catch (const std::exception& e) {
    what = e.what();
  } catch (...) {
  }
  spdlog::error("[{} {}] an exception escaped the call's work: {}", id, method, what);
  return absl::InternalError(absl::StrCat("internal error: ", what, " (the call failed; the server goes on)"));
}

// Runs `body` (returning Status or StatusOr<T>); an exception becomes INTERNAL.
template <typename Body>
auto CatchExceptions(const std::string& id, const char* method, Body&& body) -> decltype(body()) {
  try {
    return body();
  } catch (...) {
    return StatusOfCurrentException(id, method);
  }
}

}  // namespace visq::service
