// The one place where visq's status codes become gRPC's.
#pragma once

#include <grpcpp/support/status.h>

#include "common/status.h"

namespace visq::service {

grpc::Status ToGrpcStatus(const Status& status);

}  // namespace visq::service
