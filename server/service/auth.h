// Bearer-token authorization, checked on every visq.v1 call before any work.
// Health checks stay open: orchestrators probe them without credentials.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include <grpcpp/server_context.h>

#include "common/status.h"

namespace visq::service {

// The token in a token file's text: surrounding whitespace (a Windows
// line end, a trailing newline) stripped. `warnings` gets a line for each
// thing that looks wrong with it. Empty text is INVALID_ARGUMENT.
[[nodiscard]] StatusOr<std::string> ParseAuthToken(std::string_view file_text, std::vector<std::string>* warnings);

class Authorizer {
 public:
  // An empty token disables the check.
  explicit Authorizer(std::string token) : token_(std::move(token)) {}
  bool enabled() const { return !token_.empty(); }
  // UNAUTHENTICATED unless the call carries "authorization: Bearer <token>".
  [[nodiscard]] Status Check(const grpc::CallbackServerContext& context) const;

 private:
  std::string token_;
};

}  // namespace visq::service
