// Bearer-token authorization, checked on every visq.v1 call before any work.
// Health checks stay open: orchestrators probe them without credentials.
#pragma once

#include <string>

#include <grpcpp/server_context.h>

#include "common/status.h"

namespace visq::service {

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
