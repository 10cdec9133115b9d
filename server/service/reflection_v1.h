// grpc.reflection.v1, which current tools (grpcurl, Postman) ask for before
// v1alpha. Debian 12's gRPC serves only v1alpha; v1 has the same messages,
// so this answers them from the same source v1alpha uses: the descriptors
// compiled into the binary (protobuf's generated pool). Registered only when
// v1alpha is, that is without a bearer token.
#pragma once

#include <string>
#include <vector>

#include "grpc/reflection/v1/reflection.grpc.pb.h"

namespace visq::service {

class ReflectionV1Service final : public grpc::reflection::v1::ServerReflection::CallbackService {
 public:
  // `services`: the full names list_services answers.
  explicit ReflectionV1Service(std::vector<std::string> services) : services_(std::move(services)) {}

  grpc::ServerBidiReactor<grpc::reflection::v1::ServerReflectionRequest, grpc::reflection::v1::ServerReflectionResponse>*
  ServerReflectionInfo(grpc::CallbackServerContext* context) override;

 private:
  std::vector<std::string> services_;
};

}  // namespace visq::service
