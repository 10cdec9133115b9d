#include "service/reflection_v1.h"

#include <set>

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

namespace visq::service {
namespace {

namespace refl = grpc::reflection::v1;
using google::protobuf::DescriptorPool;
using google::protobuf::FileDescriptor;

// One stream: each request read is answered before the next is read, in
// order. Files already sent on this stream are not sent again (the
// protocol allows it, and clients resolve dependencies across answers).
class ReflectionReactor final : public grpc::ServerBidiReactor<refl::ServerReflectionRequest, refl::ServerReflectionResponse> {
 public:
  explicit ReflectionReactor(const std::vector<std::string>& services) : services_(services) { StartRead(&request_); }

  void OnReadDone(bool ok) override {
    if (!ok) {
      Finish(grpc::Status::OK);  // the client closed its side
      return;
    }
    response_.Clear();
    Answer();
    StartWrite(&response_);
  }
  void OnWriteDone(bool ok) override {
    if (!ok) {
      Finish(grpc::Status(grpc::StatusCode::CANCELLED, "client went away"));
      return;
    }
    StartRead(&request_);
  }
  void OnDone() override { delete this; }

 private:
  void Answer() {
    response_.set_valid_host(request_.host());
    *response_.mutable_original_request() = request_;
    const DescriptorPool* pool = DescriptorPool::generated_pool();
    switch (request_.message_request_case()) {
      case refl::ServerReflectionRequest::kListServices:
        for (const std::string& name : services_)
          response_.mutable_list_services_response()->add_service()->set_name(name);
        return;
      case refl::ServerReflectionRequest::kFileByFilename:
        SendFile(pool->FindFileByName(request_.file_by_filename()), "file", request_.file_by_filename());
        return;
      case refl::ServerReflectionRequest::kFileContainingSymbol:
        SendFile(pool->FindFileContainingSymbol(request_.file_containing_symbol()), "symbol",
                 request_.file_containing_symbol());
        return;
      case refl::ServerReflectionRequest::kFileContainingExtension: {
        const auto& ask = request_.file_containing_extension();
        const auto* type = pool->FindMessageTypeByName(ask.containing_type());
        const auto* extension = type ? pool->FindExtensionByNumber(type, ask.extension_number()) : nullptr;
        SendFile(extension ? extension->file() : nullptr, "extension",
                 ask.containing_type() + " " + std::to_string(ask.extension_number()));
        return;
      }
      case refl::ServerReflectionRequest::kAllExtensionNumbersOfType: {
        const auto* type = pool->FindMessageTypeByName(request_.all_extension_numbers_of_type());
        if (type == nullptr) {
          Error(grpc::StatusCode::NOT_FOUND, "type not found: " + request_.all_extension_numbers_of_type());
          return;
        }
        std::vector<const google::protobuf::FieldDescriptor*> extensions;
        pool->FindAllExtensions(type, &extensions);
        auto* out = response_.mutable_all_extension_numbers_response();
        out->set_base_type_name(type->full_name());
        for (const auto* e : extensions) out->add_extension_number(e->number());
        return;
      }
      default:
        Error(grpc::StatusCode::INVALID_ARGUMENT, "message_request: none of the known requests is set");
    }
  }

  void SendFile(const FileDescriptor* file, const char* what, const std::string& name) {
    if (file == nullptr) {
      Error(grpc::StatusCode::NOT_FOUND, std::string(what) + " not found: " + name);
      return;
    }
    // The file asked for (always, so that each answer names its symbol's
    // file), then what it imports, transitively, unless sent before.
    std::vector<const FileDescriptor*> pending = {file};
    auto* out = response_.mutable_file_descriptor_response();
    while (!pending.empty()) {
      const FileDescriptor* next = pending.back();
      pending.pop_back();
      if (!sent_.insert(next->name()).second && next != file) continue;
      google::protobuf::FileDescriptorProto proto;
      next->CopyTo(&proto);
      out->add_file_descriptor_proto(proto.SerializeAsString());
      for (int i = 0; i < next->dependency_count(); ++i) pending.push_back(next->dependency(i));
    }
  }

  void Error(grpc::StatusCode code, const std::string& message) {
    auto* error = response_.mutable_error_response();
    error->set_error_code(static_cast<int32_t>(code));
    error->set_error_message(message);
  }

  const std::vector<std::string>& services_;
  refl::ServerReflectionRequest request_;
  refl::ServerReflectionResponse response_;
  std::set<std::string> sent_;
};

}  // namespace

grpc::ServerBidiReactor<refl::ServerReflectionRequest, refl::ServerReflectionResponse>*
ReflectionV1Service::ServerReflectionInfo(grpc::CallbackServerContext*) {
  return new ReflectionReactor(services_);
}

}  // namespace visq::service
