// The C++ client of visq: a class owning the gRPC stub, with a deadline on
// every call and chunked scene upload. The `visq` CLI is a thin main over it.
//
// Installed (cmake --install) as include/visq/visq_client.h with the public
// floor (visq/status.h, visq/obscurance_partial.h) and the generated proto,
// so this header includes nothing from lib/ or server/ (tests/layout checks).
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <grpcpp/channel.h>

#include "visq/obscurance_partial.h"  // header-only: the merge the server uses
#include "visq/status.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "visq/v1/visq.grpc.pb.h"

namespace visq::client {

// visq-server's default --address port (server/service/server.h).
inline constexpr int kDefaultServerPort = 50051;

// HOST[:PORT] with kDefaultServerPort when no port is given (gRPC's own
// default is 443), brackets added to a bare IPv6 address; unix:, dns:,
// ipv4: and ipv6: targets unchanged. INVALID_ARGUMENT for a port that is
// not a number in 1..65535.
[[nodiscard]] StatusOr<std::string> WithDefaultPort(const std::string& address);

struct ClientOptions {
  std::string address = "127.0.0.1:50051";  // WithDefaultPort applies
  std::chrono::milliseconds deadline{60'000};
  // Server streams, bakes and uploads: < 0 the same as `deadline`, 0 none
  // (their length depends on the scene; the CLI passes 0 unless --timeout).
  std::chrono::milliseconds stream_deadline{-1};
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

// gRPC status -> visq Status (the client's one conversion).
Status FromGrpcStatus(const grpc::Status& status);

// A hidden-sample map reassembled from its streamed chunks.
struct HiddenSampleMap {
  // Sizes and samples (the stream's first message), accuracy and timing
  // (its last), and the lookup errors (HOUGH) and per-texel bounds
  // (want_texel_error) reassembled.
  v1::HiddenSampleMapResponse figures;
  std::vector<float> visible_fraction;  // width * height, row-major
  std::vector<float> visible_rgb;       // 3 per texel for colored lights
  std::vector<uint32_t> blocked_bits;   // words_per_texel per texel (when asked for)
  bool Blocked(size_t texel, uint32_t sample) const {
    return (blocked_bits[texel * figures.words_per_texel() + sample / 32] >> (sample % 32)) & 1u;
  }
};

// A voxel grid reassembled from its streamed chunks.
struct VoxelGrid {
  v1::VoxelizeResponse figures;  // sizes, box, accuracy (first message); counts, timing (last)
  std::vector<uint32_t> bits;    // word (y * width + x) * words_per_column + k / 32, bit k % 32
  std::vector<float> column_near, column_far;
  bool Occupied(uint32_t x, uint32_t y, uint32_t k) const {
    const size_t word = (size_t(y) * figures.width() + x) * figures.words_per_column() + k / 32;
    return (bits[word] >> (k % 32)) & 1u;
  }
};

// A volumetric-shadow image reassembled from its streamed chunks.
struct VolumetricImage {
  v1::VolumetricShadowResponse figures;
  std::vector<float> inscattering;  // RGB per pixel, row 0 at the top
  std::vector<float> combined;
};

// A ComputeObscurances result reassembled from its stream.
struct ObscuranceBake {
  v1::ObscuranceFigures figures;         // atlas, fingerprint, ranges, accuracy, timing
  std::vector<float> w, intensity;       // 3 per texel, index (y * width + x) * 3
  std::vector<uint8_t> estimated;        // per texel: 1 estimated, 0 filled from neighbours
  std::vector<float> triangle_w, vertex_w;  // 3 each (want_averages)
  // Each element's own half-width on its W (want_errors; triangle and vertex
  // ones also want_averages): one per texel, triangle, scene position.
  std::vector<float> w_error, triangle_w_error, vertex_w_error;
  obscurance::ObscurancePartial partial;  // partial_only (and ShardedBake)
  uint32_t progress_messages = 0;
};
using ObscuranceProgressCallback = std::function<void(const v1::ObscuranceProgress&)>;
// A streamed answer's progress, from what its stream carries: `done` of
// `total` units (a map's texels, a grid's or an image's rows) received so
// far. Called on the calling thread, once the sizes are known (done 0) and
// after each chunk.
using StreamProgressCallback = std::function<void(uint64_t done, uint64_t total)>;

// A RenderObscurancePreview picture reassembled from its stream.
struct ObscurancePreview {
  v1::ObscurancePreviewResponse figures;  // width, height, solution_version, quantity, timing
  std::vector<float> rgb;                 // linear RGB per pixel, index (y * width + x) * 3, row 0 at the top
  std::vector<uint8_t> covered;           // per pixel: 1 a surface, 0 background (rgb 0)
};

// An ExportObscurances answer reassembled from its stream.
struct ObscuranceExport {
  v1::ExportObscurancesResponse figures;  // solution_version, width, height, triangles, timing
  std::vector<float> atlas_uv;            // want_atlas_uvs: (u, v) per triangle corner
  std::vector<uint8_t> glb;               // want_gltf: the baked scene as binary glTF
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

  [[nodiscard]] StatusOr<HiddenSampleMap> ComputeHiddenSampleMap(const v1::HiddenSampleMapRequest& request,
                                                                  const StreamProgressCallback& progress = {});
  [[nodiscard]] StatusOr<v1::PatchVisibilityResponse> PatchVisibility(const v1::PatchVisibilityRequest& request);
  [[nodiscard]] StatusOr<v1::LightVisibilityResponse> LightVisibility(const v1::LightVisibilityRequest& request);
  [[nodiscard]] StatusOr<VoxelGrid> Voxelize(const v1::VoxelizeRequest& request,
                                             const StreamProgressCallback& progress = {});
  [[nodiscard]] StatusOr<v1::TransmittanceResponse> Transmittance(const v1::TransmittanceRequest& request);
  [[nodiscard]] StatusOr<VolumetricImage> VolumetricShadow(const v1::VolumetricShadowRequest& request,
                                                           const StreamProgressCallback& progress = {});
  // Sends the batches over one stream; answers come back in order.
  [[nodiscard]] StatusOr<std::vector<v1::LightVisibilityResponse>> LightVisibilityStream(
      const std::vector<v1::LightVisibilityRequest>& batches);
  // The same with batches made on demand, so that neither the requests nor
  // the answers of millions of points are held at once: `next` fills the
  // next batch and returns false when there is none; `answer` receives each
  // batch's answer in order (an error from it cancels the call).
  using LightBatchSource = std::function<bool(v1::LightVisibilityRequest*)>;
  using LightAnswerSink = std::function<Status(v1::LightVisibilityResponse&)>;
  [[nodiscard]] Status LightVisibilityStream(const std::string& scene, const LightBatchSource& next,
                                             const LightAnswerSink& answer);

  // Obscurances. `progress` is called for each progress message (on this
  // thread) while the server bakes.
  [[nodiscard]] StatusOr<ObscuranceBake> ComputeObscurances(const v1::ComputeObscurancesRequest& request,
                                                            const ObscuranceProgressCallback& progress = {});
  // Moves a node (in the server's memory only; see the proto).
  [[nodiscard]] StatusOr<v1::SceneInfo> SetNodeTransform(const v1::SetNodeTransformRequest& request);
  [[nodiscard]] StatusOr<v1::UpdateObscurancesResponse> UpdateObscurances(const v1::UpdateObscurancesRequest& request);
  // The scene from a camera with the current solution's W (or I) applied.
  [[nodiscard]] StatusOr<ObscurancePreview> RenderObscurancePreview(const v1::ObscurancePreviewRequest& request);
  [[nodiscard]] StatusOr<ObscuranceExport> ExportObscurances(const v1::ExportObscurancesRequest& request);

  // The x-visq-server-id of the last response (which replica answered).
  std::string last_server_id() const;

  // For RPCs this class does not wrap yet, and for tests.
  v1::VisibilityService::Stub& stub() { return *stub_; }
  // A context with the deadline (a stream's when `stream`), request id,
  // token and (when `scene` is given) the routing metadata applied.
  std::unique_ptr<grpc::ClientContext> NewContext(const std::string& scene = "", bool stream = false) const;
  // Whether construction succeeded (TLS files readable).
  const Status& init_status() const { return init_status_; }

 private:
  ClientOptions options_;
  Status init_status_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::VisibilityService::Stub> stub_;
  std::unique_ptr<grpc::health::v1::Health::Stub> health_;
  // One unary call: deadline, metadata (scene routing), the replica that
  // answered, and the status conversion.
  template <typename Request, typename Response>
  StatusOr<Response> CallUnary(grpc::Status (v1::VisibilityService::Stub::*rpc)(grpc::ClientContext*, const Request&,
                                                                                 Response*),
                               const std::string& scene, const Request& request) {
    VISQ_RETURN_IF_ERROR(init_status_);
    auto context = NewContext(scene);
    Response response;
    const grpc::Status status = (stub_.get()->*rpc)(context.get(), request, &response);
    NoteServer(*context);
    VISQ_RETURN_IF_ERROR(FromGrpcStatus(status));
    return response;
  }

  mutable std::mutex last_server_mutex_;
  std::string last_server_id_;

 public:
  // Records x-visq-server-id from a finished call's context.
  void NoteServer(const grpc::ClientContext& context);
};


// Adds the partial sums of one shard into `into` (empty: takes `from`):
// exactly the server's arithmetic, so the merge of shards over a split of
// [0, n) equals the bake of [0, n) bit for bit. INVALID_ARGUMENT when the
// partials differ in scene, atlas or parameters, or overlap.
[[nodiscard]] Status MergeObscurancePartials(obscurance::ObscurancePartial& into,
                                             const obscurance::ObscurancePartial& from);

// A bake split across servers: the request's direction range (default
// [0, 256)) cut into `shards` consecutive ranges, assigned round-robin to
// `clients` and baked in parallel with partial_only, then merged. The
// result holds the merged partial (W stays with the servers' atlas: W of an
// estimated texel is sums / (count * kObscuranceFixedPointScale)) and the
// first shard's figures with the merged ranges.
[[nodiscard]] StatusOr<ObscuranceBake> ShardedBake(const std::vector<Client*>& clients,
                                                   v1::ComputeObscurancesRequest request, uint32_t shards);
// The same, over one new client per address (`options` with its address replaced).
[[nodiscard]] StatusOr<ObscuranceBake> ShardedBake(const std::vector<std::string>& addresses,
                                                   const ClientOptions& options,
                                                   v1::ComputeObscurancesRequest request, uint32_t shards);

// The files a .gltf references (buffers and images that are not data: URIs),
// relative to its folder; empty for a .glb.
[[nodiscard]] StatusOr<std::vector<std::string>> ReferencedFiles(const std::filesystem::path& gltf);

}  // namespace visq::client
