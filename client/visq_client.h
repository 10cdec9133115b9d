// The C++ client of visq: a class owning the gRPC stub, with a deadline on
// every call and chunked scene upload. The `visq` CLI is a thin main over it.
#pragma once

#include <chrono>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>

#include <grpcpp/channel.h>

#include "common/status.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "visq/v1/visq.grpc.pb.h"

namespace visq::client {

struct ClientOptions {
  std::string address = "127.0.0.1:50051";
  std::chrono::milliseconds deadline{60'000};
  size_t upload_chunk_bytes = 1 << 20;  // well under any message limit
  std::string request_id;               // sent as x-request-id when set
  std::string auth_token;               // sent as "authorization: Bearer ..." when set
  // TLS: on when tls_ca_file is set (PEM roots that sign the server's
  // certificate); client_cert_file/client_key_file for mutual TLS.
  std::string tls_ca_file;
  std::string client_cert_file;
  std::string client_key_file;
  std::string tls_server_name;          // override the name checked in the certificate
  // Sent as x-visq-scene on calls that name a scene, so a proxy can route
  // each scene to the replicas that hold it (see deploy/nginx).
  bool route_by_scene = true;
};

// A hidden-sample map reassembled from its streamed chunks.
struct HiddenSampleMap {
  v1::HiddenSampleMapResponse figures;  // sizes, accuracy, timing, lookup error, samples
  std::vector<float> visible_fraction;  // width * height, row-major
  std::vector<float> visible_rgb;       // 3 per texel for colored lights
  std::vector<uint32_t> blocked_bits;   // words_per_texel per texel (when asked for)
  bool Blocked(size_t texel, uint32_t sample) const {
    return (blocked_bits[texel * figures.words_per_texel() + sample / 32] >> (sample % 32)) & 1u;
  }
};

class Client {
 public:
  explicit Client(ClientOptions options);

  // SERVING / NOT_SERVING / ... of `service` ("" = the whole server).
  [[nodiscard]] StatusOr<grpc::health::v1::HealthCheckResponse::ServingStatus> Health(
      const std::string& service = "");
  // Polls health until SERVING or `timeout` passes.
  [[nodiscard]] Status WaitUntilServing(std::chrono::milliseconds timeout);

  // Uploads a .glb, or a .gltf and every file its buffers and images
  // reference, in chunks. `name` defaults to the file's stem.
  [[nodiscard]] StatusOr<v1::SceneInfo> UploadScene(const std::filesystem::path& file, std::string name = "",
                                                    bool replace = false);
  [[nodiscard]] StatusOr<v1::SceneInfo> LoadFromRepository(const std::string& name, bool replace = false);
  [[nodiscard]] StatusOr<v1::ListScenesResponse> ListScenes();
  [[nodiscard]] StatusOr<v1::SceneInfo> GetScene(const std::string& name, bool include_nodes = false,
                                                 bool load_if_stored = false);
  [[nodiscard]] StatusOr<v1::UnloadSceneResponse> UnloadScene(const std::string& name,
                                                              bool delete_from_repository = false);

  [[nodiscard]] StatusOr<v1::ServerStats> GetStats();

  [[nodiscard]] StatusOr<HiddenSampleMap> ComputeHiddenSampleMap(const v1::HiddenSampleMapRequest& request);
  [[nodiscard]] StatusOr<v1::PatchVisibilityResponse> PatchVisibility(const v1::PatchVisibilityRequest& request);
  [[nodiscard]] StatusOr<v1::LightVisibilityResponse> LightVisibility(const v1::LightVisibilityRequest& request);
  // Sends the batches over one stream; answers come back in order.
  [[nodiscard]] StatusOr<std::vector<v1::LightVisibilityResponse>> LightVisibilityStream(
      const std::vector<v1::LightVisibilityRequest>& batches);

  // The x-visq-server-id of the last response (which replica answered).
  std::string last_server_id() const;

  // For RPCs this class does not wrap yet, and for tests.
  v1::VisibilityService::Stub& stub() { return *stub_; }
  // A context with the deadline, request id, token and (when `scene` is
  // given) the routing metadata applied.
  std::unique_ptr<grpc::ClientContext> NewContext(const std::string& scene = "") const;
  // Whether construction succeeded (TLS files readable).
  const Status& init_status() const { return init_status_; }

 private:
  ClientOptions options_;
  Status init_status_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::VisibilityService::Stub> stub_;
  std::unique_ptr<grpc::health::v1::Health::Stub> health_;
  mutable std::mutex last_server_mutex_;
  std::string last_server_id_;

 public:
  // Records x-visq-server-id from a finished call's context.
  void NoteServer(const grpc::ClientContext& context);
};

// gRPC status -> visq Status (the client's one conversion).
Status FromGrpcStatus(const grpc::Status& status);

// The files a .gltf references (buffers and images that are not data: URIs),
// relative to its folder; empty for a .glb.
[[nodiscard]] StatusOr<std::vector<std::string>> ReferencedFiles(const std::filesystem::path& gltf);

}  // namespace visq::client
