#include "service/auth.h"

namespace visq::service {
namespace {

// Compares without an early exit, so timing does not reveal a prefix.
bool ConstantTimeEquals(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) return false;
  unsigned char diff = 0;
  for (size_t i = 0; i < a.size(); ++i) diff |= static_cast<unsigned char>(a[i] ^ b[i]);
  return diff == 0;
}

}  // namespace

Status Authorizer::Check(const grpc::CallbackServerContext& context) const {
  if (!enabled()) return absl::OkStatus();
  const auto& metadata = context.client_metadata();
  auto it = metadata.find("authorization");
  if (it == metadata.end()) return absl::UnauthenticatedError("missing authorization: Bearer <token> metadata");
  const std::string_view value(it->second.data(), it->second.size());
  constexpr std::string_view kPrefix = "Bearer ";
  if (value.substr(0, kPrefix.size()) != kPrefix || !ConstantTimeEquals(value.substr(kPrefix.size()), token_))
    return absl::UnauthenticatedError("invalid bearer token");
  return absl::OkStatus();
}

}  // namespace visq::service
