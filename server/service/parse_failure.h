// Why a message's bytes did not parse, in words that name the field: gRPC's
// generated reader only says "no message", which a client-streamed call
// cannot tell from the end of the stream.
#pragma once

#include <string>
#include <string_view>

#include <google/protobuf/descriptor.h>

namespace visq::service {

// For bytes that `type` failed to parse: "chunk.file: invalid UTF-8" when
// the wire format holds and a string field does not (proto3 refuses those),
// else a line saying the message is truncated or malformed.
std::string DescribeParseFailure(const google::protobuf::Descriptor& type, std::string_view bytes);

}  // namespace visq::service
