#include "service/auth.h"

#include <absl/strings/ascii.h>
#include <absl/strings/str_cat.h>

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

StatusOr<std::string> ParseAuthToken(std::string_view file_text, std::vector<std::string>* warnings) {
  const absl::string_view stripped = absl::StripAsciiWhitespace(AbslView(file_text));
  const std::string_view token(stripped.data(), stripped.size());
  if (token.empty()) return absl::InvalidArgumentError("the token file holds no token");
  auto warn = [&](std::string line) {
    if (warnings != nullptr) warnings->push_back(std::move(line));
  };
  if (token.find_first_of("\r\n") != std::string_view::npos)
    warn("the token file holds more than one line: the whole text, inner line breaks included, is the token");
  for (char c : token)
    if (static_cast<unsigned char>(c) < 0x21 || static_cast<unsigned char>(c) > 0x7e) {
      warn("the token holds spaces or non-ASCII bytes, which HTTP/2 metadata clients may not send");
      break;
    }
  if (token.size() < 16) warn(absl::StrCat("the token is ", token.size(), " characters; use at least 32 random ones"));
  return std::string(token);
}

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
