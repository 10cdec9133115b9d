#include "visq_client.h"

#include <algorithm>

#include <cmath>
#include <fstream>
#include <optional>
#include <sstream>
#include <thread>
#include <type_traits>

#include <absl/strings/str_cat.h>
#include <grpcpp/client_context.h>
#include <grpcpp/create_channel.h>
#include <grpcpp/security/credentials.h>
#include <nlohmann/json.hpp>

namespace visq::client {
namespace {

// glTF URIs are RFC 3986 references: undo percent-encoding.
std::string DecodeUri(const std::string& uri) {
  std::string out;
  for (size_t i = 0; i < uri.size(); ++i) {
    if (uri[i] == '%' && i + 2 < uri.size()) {
      int value = 0;
      if (std::sscanf(uri.substr(i + 1, 2).c_str(), "%2x", &value) == 1) {
        out.push_back(static_cast<char>(value));
        i += 2;
        continue;
      }
    }
    out.push_back(uri[i]);
  }
  return out;
}

}  // namespace

Status FromGrpcStatus(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  return Status(static_cast<absl::StatusCode>(status.error_code()), status.error_message());
}

namespace {
StatusOr<std::string> ReadPem(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::InvalidArgumentError(absl::StrCat("cannot read ", path));
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}
}  // namespace

StatusOr<std::string> WithDefaultPort(const std::string& address) {
  if (address.empty()) return absl::InvalidArgumentError("address: empty");
  for (const char* scheme : {"unix:", "dns:", "ipv4:", "ipv6:"})
    if (address.rfind(scheme, 0) == 0) return address;
  const std::string default_port = std::to_string(kDefaultServerPort);
  if (address.front() == '[') {
    if (address.find("]:") == std::string::npos) return address + ":" + default_port;
  } else if (std::count(address.begin(), address.end(), ':') > 1) {
    return "[" + address + "]:" + default_port;  // a bare IPv6 address
  } else if (address.find(':') == std::string::npos) {
    return address + ":" + default_port;
  }
  const std::string port = address.substr(address.rfind(':') + 1);
  const bool digits = !port.empty() && port.size() <= 5 &&
                      std::all_of(port.begin(), port.end(), [](char c) { return c >= '0' && c <= '9'; });
  if (!digits || std::stoi(port) < 1 || std::stoi(port) > 65535)
    return absl::InvalidArgumentError(
        absl::StrCat("address: port '", port, "' of '", address, "' is not a number in 1..65535"));
  return address;
}

Client::Client(ClientOptions options) : options_(std::move(options)) {
  if (auto address = WithDefaultPort(options_.address); address.ok()) options_.address = *address;
  else init_status_ = address.status();
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(-1);  // responses can be large bitmask streams
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (!options_.tls_ca_file.empty()) {
    grpc::SslCredentialsOptions ssl;
    auto roots = ReadPem(options_.tls_ca_file);
    if (roots.ok()) ssl.pem_root_certs = *roots;
    else init_status_ = roots.status();
    if (!options_.client_cert_file.empty()) {
      auto cert = ReadPem(options_.client_cert_file);
      auto key = ReadPem(options_.client_key_file);
      if (cert.ok() && key.ok()) {
        ssl.pem_cert_chain = *cert;
        ssl.pem_private_key = *key;
      } else {
        init_status_ = cert.ok() ? key.status() : cert.status();
      }
    }
    if (!options_.tls_server_name.empty()) args.SetSslTargetNameOverride(options_.tls_server_name);
    credentials = grpc::SslCredentials(ssl);
  }
  channel_ = grpc::CreateCustomChannel(options_.address, credentials, args);
  stub_ = v1::VisibilityService::NewStub(channel_);
  health_ = grpc::health::v1::Health::NewStub(channel_);
}

std::unique_ptr<grpc::ClientContext> Client::NewContext(const std::string& scene, bool stream) const {
  auto context = std::make_unique<grpc::ClientContext>();
  const std::chrono::milliseconds deadline =
      stream && options_.stream_deadline.count() >= 0 ? options_.stream_deadline : options_.deadline;
  if (deadline.count() > 0) context->set_deadline(std::chrono::system_clock::now() + deadline);
  if (!options_.request_id.empty()) context->AddMetadata("x-request-id", options_.request_id);
  if (!options_.auth_token.empty()) context->AddMetadata("authorization", "Bearer " + options_.auth_token);
  // Metadata values must be printable ASCII (gRPC aborts the process on
  // anything else); a name that is not goes unrouted and the server refuses
  // it by name.
  const bool routable = std::all_of(scene.begin(), scene.end(), [](char c) { return c >= 0x20 && c < 0x7f; });
  if (options_.route_by_scene && !scene.empty() && routable) context->AddMetadata("x-visq-scene", scene);
  return context;
}

StatusOr<grpc::health::v1::HealthCheckResponse::ServingStatus> Client::Health(const std::string& service) {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext();
  grpc::health::v1::HealthCheckRequest request;
  request.set_service(service);
  grpc::health::v1::HealthCheckResponse response;
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(health_->Check(context.get(), request, &response)));
  return response.status();
}

Status Client::WaitUntilServing(std::chrono::milliseconds timeout) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  Status last = absl::UnavailableError("not tried");
  while (std::chrono::steady_clock::now() < end) {
    auto context = std::make_unique<grpc::ClientContext>();
    context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
    grpc::health::v1::HealthCheckRequest request;
    grpc::health::v1::HealthCheckResponse response;
    last = FromGrpcStatus(health_->Check(context.get(), request, &response));
    if (last.ok() && response.status() == grpc::health::v1::HealthCheckResponse::SERVING) return absl::OkStatus();
    if (last.ok()) last = absl::UnavailableError("server is NOT_SERVING");
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return absl::DeadlineExceededError(absl::StrCat("server at ", options_.address,
                                                  " not SERVING in time: ", last.message()));
}

StatusOr<std::vector<std::string>> ReferencedFiles(const std::filesystem::path& gltf) {
  if (gltf.extension() != ".gltf") return std::vector<std::string>{};
  std::ifstream in(gltf);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", gltf.string()));
  nlohmann::json doc = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) return absl::InvalidArgumentError(absl::StrCat(gltf.string(), ": malformed JSON"));
  // Buffers only: the server drops images, so they are never sent.
  std::vector<std::string> files;
  if (!doc.contains("buffers") || !doc["buffers"].is_array()) return files;
  for (const auto& entry : doc["buffers"]) {
    if (!entry.is_object() || !entry.contains("uri") || !entry["uri"].is_string()) continue;
    const std::string uri = entry["uri"];
    if (uri.rfind("data:", 0) == 0) continue;
    files.push_back(DecodeUri(uri));
  }
  return files;
}

StatusOr<v1::SceneInfo> Client::UploadScene(const std::filesystem::path& file, std::string name, bool replace) {
  if (name.empty()) name = file.stem().string();
  VISQ_ASSIGN_OR_RETURN(std::vector<std::string> referenced, ReferencedFiles(file));
  // Send only what the server will read, skipping referenced files that are
  // absent.
  std::vector<std::pair<std::string, std::filesystem::path>> to_send = {{file.filename().string(), file}};
  uint64_t total = std::filesystem::file_size(file);
  for (const auto& relative : referenced) {
    const auto path = file.parent_path() / relative;
    std::error_code ec;
    if (!std::filesystem::is_regular_file(path, ec)) continue;
    to_send.emplace_back(relative, path);
    total += std::filesystem::file_size(path, ec);
  }

  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext(name, /*stream=*/true);
  v1::SceneInfo info;
  auto writer = stub_->LoadScene(context.get(), &info);
  v1::LoadSceneRequest request;
  auto* header = request.mutable_header();
  header->set_name(name);
  header->set_upload_main_file(file.filename().string());
  header->set_replace(replace);
  header->set_expected_bytes(total);
  bool stream_open = writer->Write(request);
  std::vector<char> buffer(options_.upload_chunk_bytes);
  for (const auto& [relative, path] : to_send) {
    if (!stream_open) break;
    std::ifstream in(path, std::ios::binary);
    if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", path.string()));
    do {
      in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
      const std::streamsize n = in.gcount();
      if (n <= 0) break;
      v1::LoadSceneRequest chunk;
      chunk.mutable_chunk()->set_file(relative);
      chunk.mutable_chunk()->set_data(buffer.data(), static_cast<size_t>(n));
      stream_open = writer->Write(chunk);
    } while (stream_open && in);
  }
  writer->WritesDone();
  const grpc::Status status = writer->Finish();
  NoteServer(*context);
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(status));
  return info;
}

StatusOr<v1::SceneInfo> Client::LoadFromRepository(const std::string& name, bool replace) {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext(name);
  v1::SceneInfo info;
  auto writer = stub_->LoadScene(context.get(), &info);
  v1::LoadSceneRequest request;
  request.mutable_header()->set_name(name);
  request.mutable_header()->set_from_repository(true);
  request.mutable_header()->set_replace(replace);
  writer->Write(request);
  writer->WritesDone();
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(writer->Finish()));
  return info;
}

StatusOr<v1::ListScenesResponse> Client::ListScenes() {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext();
  v1::ListScenesResponse response;
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(stub_->ListScenes(context.get(), v1::ListScenesRequest(), &response)));
  return response;
}

StatusOr<v1::SceneInfo> Client::GetScene(const std::string& name, bool include_nodes, bool load_if_stored) {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext(name);
  v1::GetSceneRequest request;
  request.set_name(name);
  request.set_include_nodes(include_nodes);
  request.set_load_if_stored(load_if_stored);
  v1::SceneInfo response;
  const grpc::Status status = stub_->GetScene(context.get(), request, &response);
  NoteServer(*context);
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(status));
  return response;
}

StatusOr<v1::UnloadSceneResponse> Client::UnloadScene(const std::string& name, bool delete_from_repository) {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext(name);
  v1::UnloadSceneRequest request;
  request.set_name(name);
  request.set_delete_from_repository(delete_from_repository);
  v1::UnloadSceneResponse response;
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(stub_->UnloadScene(context.get(), request, &response)));
  return response;
}

}  // namespace visq::client

namespace visq::client {

StatusOr<v1::ServerStats> Client::GetStats() {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext();
  v1::ServerStats response;
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(stub_->GetStats(context.get(), v1::GetStatsRequest(), &response)));
  return response;
}

}  // namespace visq::client

namespace visq::client {

void Client::NoteServer(const grpc::ClientContext& context) {
  const auto& metadata = context.GetServerInitialMetadata();
  auto it = metadata.find("x-visq-server-id");
  std::lock_guard lock(last_server_mutex_);
  last_server_id_ = it == metadata.end() ? "" : std::string(it->second.data(), it->second.size());
}

std::string Client::last_server_id() const {
  std::lock_guard lock(last_server_mutex_);
  return last_server_id_;
}

}  // namespace visq::client

namespace visq::client {
namespace {

// Appends a streamed chunk of an array, `per_item` elements to an item,
// checking that it starts where the last one ended (`offset` counts items).
template <typename Field, typename Into>
Status AppendChunk(const Field& field, uint64_t offset, Into& into, const char* what, size_t per_item = 1) {
  if (field.empty()) return absl::OkStatus();
  const uint64_t have = uint64_t(into.size()) / per_item;
  if (offset != have) return absl::DataLossError(absl::StrCat(what, " chunk at ", offset, ", have ", have));
  if constexpr (requires { into.Add(field.begin(), field.end()); })
    into.Add(field.begin(), field.end());
  else
    into.insert(into.end(), field.begin(), field.end());
  return absl::OkStatus();
}

// One server-streaming call, with the context of a stream (its deadline):
// each message handed to `take` in order, then the call's end. A message
// `take` refuses cancels the call, and its error is the answer.
template <typename Request, typename Response>
Status CallStreamed(Client& client,
                    std::unique_ptr<grpc::ClientReader<Response>> (v1::VisibilityService::Stub::*rpc)(
                        grpc::ClientContext*, const Request&),
                    const Request& request, const std::type_identity_t<std::function<Status(Response& message)>>& take) {
  VISQ_RETURN_IF_ERROR(client.init_status());
  auto context = client.NewContext(request.scene().name(), /*stream=*/true);
  auto reader = (client.stub().*rpc)(context.get(), request);
  Response message;
  Status taken;
  while (reader->Read(&message)) {
    if (!taken.ok()) continue;  // cancelled: what is still in flight is dropped
    taken = take(message);
    if (!taken.ok()) context->TryCancel();
  }
  const grpc::Status status = reader->Finish();
  client.NoteServer(*context);
  VISQ_RETURN_IF_ERROR(taken);
  return FromGrpcStatus(status);
}

}  // namespace

StatusOr<HiddenSampleMap> Client::ComputeHiddenSampleMap(const v1::HiddenSampleMapRequest& request,
                                                         const StreamProgressCallback& progress) {
  HiddenSampleMap out;
  bool first = true;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::HiddenSampleMap, request,
      [&](v1::HiddenSampleMapResponse& message) -> Status {
        const uint64_t at = message.offset();  // in texels
        VISQ_RETURN_IF_ERROR(AppendChunk(message.visible_fraction(), at, out.visible_fraction, "visible_fraction"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.visible_rgb(), at, out.visible_rgb, "visible_rgb", 3));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.blocked_bits(), at, out.blocked_bits, "blocked_bits"));
        const uint64_t texels = uint64_t{out.figures.width()} * out.figures.height();
        // The figures: sizes and samples from the first message, the
        // accuracy and timing from the last; lookup errors are chunks like
        // the rest.
        if (first) {
          message.clear_visible_fraction();
          message.clear_visible_rgb();
          message.clear_blocked_bits();
          out.figures = std::move(message);
          first = false;
          if (progress) progress(out.visible_fraction.size(), uint64_t{out.figures.width()} * out.figures.height());
          return absl::OkStatus();
        }
        // Every band carries its visible fractions: the texels received so far.
        if (progress && message.visible_fraction_size() > 0) progress(out.visible_fraction.size(), texels);
        VISQ_RETURN_IF_ERROR(AppendChunk(message.lookup_error(), at, *out.figures.mutable_lookup_error(), "lookup_error"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.texel_error(), at, *out.figures.mutable_texel_error(), "texel_error"));
        VISQ_RETURN_IF_ERROR(
            AppendChunk(message.texel_estimate(), at, *out.figures.mutable_texel_estimate(), "texel_estimate"));
        if (message.has_accuracy()) *out.figures.mutable_accuracy() = message.accuracy();
        if (message.has_timing()) *out.figures.mutable_timing() = message.timing();
        return absl::OkStatus();
      }));
  return out;
}

StatusOr<v1::PatchVisibilityResponse> Client::PatchVisibility(const v1::PatchVisibilityRequest& request) {
  return CallUnary(&v1::VisibilityService::Stub::PatchVisibility, request.scene().name(), request);
}

StatusOr<v1::LightVisibilityResponse> Client::LightVisibility(const v1::LightVisibilityRequest& request) {
  return CallUnary(&v1::VisibilityService::Stub::LightVisibility, request.scene().name(), request);
}

StatusOr<std::vector<v1::LightVisibilityResponse>> Client::LightVisibilityStream(
    const std::vector<v1::LightVisibilityRequest>& batches) {
  size_t next_batch = 0;
  std::vector<v1::LightVisibilityResponse> answers;
  VISQ_RETURN_IF_ERROR(LightVisibilityStream(
      batches.empty() ? "" : batches[0].scene().name(),
      [&](v1::LightVisibilityRequest* batch) {
        if (next_batch == batches.size()) return false;
        *batch = batches[next_batch++];
        return true;
      },
      [&](v1::LightVisibilityResponse& answer) {
        answers.push_back(std::move(answer));
        return absl::OkStatus();
      }));
  return answers;
}

Status Client::LightVisibilityStream(const std::string& scene, const LightBatchSource& next,
                                     const LightAnswerSink& answer) {
  VISQ_RETURN_IF_ERROR(init_status_);
  auto context = NewContext(scene, /*stream=*/true);
  auto stream = stub_->LightVisibilityStream(context.get());
  size_t sent = 0, answered = 0;
  Status sink = absl::OkStatus();
  // One batch in flight at a time: the server answers in order, and this
  // keeps memory bounded on both sides.
  v1::LightVisibilityRequest batch;
  while (sink.ok()) {
    batch.Clear();
    if (!next(&batch)) break;
    ++sent;
    if (!stream->Write(batch)) break;
    v1::LightVisibilityResponse response;
    if (!stream->Read(&response)) break;
    ++answered;
    sink = answer(response);
    if (!sink.ok()) context->TryCancel();
  }
  stream->WritesDone();
  const grpc::Status status = stream->Finish();
  NoteServer(*context);
  VISQ_RETURN_IF_ERROR(sink);
  VISQ_RETURN_IF_ERROR(FromGrpcStatus(status));
  if (answered != sent) return absl::DataLossError(absl::StrCat(answered, " answers for ", sent, " batches"));
  return absl::OkStatus();
}

}  // namespace visq::client

namespace visq::client {

StatusOr<VoxelGrid> Client::Voxelize(const v1::VoxelizeRequest& request, const StreamProgressCallback& progress) {
  VoxelGrid out;
  bool first = true;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::Voxelize, request,
      [&](v1::VoxelizeResponse& message) -> Status {
        const bool had_bits = !message.bits().empty();
        VISQ_RETURN_IF_ERROR(AppendChunk(message.bits(), message.offset(), out.bits, "bits"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.column_near(), message.offset(), out.column_near, "column_near"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.column_far(), message.offset(), out.column_far, "column_far"));
        // The figures: sizes, box and accuracy from the first message,
        // counts and timing from the last.
        message.clear_bits();
        message.clear_column_near();
        message.clear_column_far();
        message.clear_offset();
        if (first) {
          out.figures = std::move(message);
          first = false;
        } else {
          out.figures.MergeFrom(message);
        }
        // Bands are whole image rows, each row width x words_per_column words.
        const uint64_t row_words = uint64_t{out.figures.width()} * out.figures.words_per_column();
        if (progress && row_words > 0 && (had_bits || out.bits.empty()))
          progress(out.bits.size() / row_words, out.figures.height());
        return absl::OkStatus();
      }));
  return out;
}

StatusOr<v1::TransmittanceResponse> Client::Transmittance(const v1::TransmittanceRequest& request) {
  return CallUnary(&v1::VisibilityService::Stub::Transmittance, request.scene().name(), request);
}

StatusOr<VolumetricImage> Client::VolumetricShadow(const v1::VolumetricShadowRequest& request,
                                                   const StreamProgressCallback& progress) {
  VolumetricImage out;
  bool first = true;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::VolumetricShadow, request,
      [&](v1::VolumetricShadowResponse& message) -> Status {
        VISQ_RETURN_IF_ERROR(AppendChunk(message.inscattering(), message.offset(), out.inscattering, "inscattering"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.combined(), message.offset(), out.combined, "combined"));
        // The figures from the first message, the timing from the last.
        const bool had_pixels = !message.combined().empty() || !message.inscattering().empty();
        message.clear_inscattering();
        message.clear_combined();
        message.clear_offset();
        if (first) {
          out.figures = std::move(message);
          first = false;
        } else {
          // A later accuracy (the error estimate) replaces the first one
          // whole: merged, an estimate of exactly 0 would keep the first's -1.
          if (message.has_accuracy()) {
            *out.figures.mutable_accuracy() = message.accuracy();
            message.clear_accuracy();
          }
          out.figures.MergeFrom(message);
        }
        // Rows received so far: each band's images are 3 floats a pixel.
        const uint64_t row_floats = uint64_t{3} * out.figures.width();
        const uint64_t floats = std::max(out.combined.size(), out.inscattering.size());
        if (progress && row_floats > 0 && (had_pixels || floats == 0))
          progress(floats / row_floats, out.figures.height());
        return absl::OkStatus();
      }));
  return out;
}

}  // namespace visq::client

namespace visq::client {

StatusOr<ObscuranceBake> Client::ComputeObscurances(const v1::ComputeObscurancesRequest& request,
                                                    const ObscuranceProgressCallback& progress) {
  ObscuranceBake out;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::ComputeObscurances, request,
      [&](v1::ComputeObscurancesResponse& message) -> Status {
        if (message.has_progress()) {
          ++out.progress_messages;
          if (progress) progress(message.progress());
          return absl::OkStatus();
        }
        if (message.has_figures()) out.figures = std::move(*message.mutable_figures());
        const uint64_t at = message.offset();
        VISQ_RETURN_IF_ERROR(AppendChunk(message.w(), at, out.w, "w"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.intensity(), at, out.intensity, "intensity"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.estimated(), at, out.estimated, "estimated"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.triangle_w(), at, out.triangle_w, "triangle_w"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.vertex_w(), at, out.vertex_w, "vertex_w"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.w_error(), at, out.w_error, "w_error"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.triangle_w_error(), at, out.triangle_w_error, "triangle_w_error"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.vertex_w_error(), at, out.vertex_w_error, "vertex_w_error"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.partial_sums(), at, out.partial.sums, "partial_sums"));
        return AppendChunk(message.partial_counts(), at, out.partial.counts, "partial_counts");
      }));
  const auto& f = out.figures;
  out.partial.fingerprint = f.fingerprint();
  out.partial.width = f.atlas().width();
  out.partial.height = f.atlas().height();
  out.partial.channels = f.channels();
  for (const auto& r : f.ranges()) out.partial.ranges.push_back({r.first(), r.count()});
  const size_t texels = static_cast<size_t>(f.atlas().width()) * f.atlas().height();
  if (f.partial_only() ? (out.partial.counts.size() != texels || out.partial.sums.size() != texels * f.channels())
                       : (out.w.size() != texels * 3 || out.estimated.size() != texels))
    return absl::DataLossError(absl::StrCat("obscurance stream ended early: ", texels, " texels expected"));
  return out;
}

StatusOr<v1::SceneInfo> Client::SetNodeTransform(const v1::SetNodeTransformRequest& request) {
  return CallUnary(&v1::VisibilityService::Stub::SetNodeTransform, request.scene().name(), request);
}

StatusOr<v1::UpdateObscurancesResponse> Client::UpdateObscurances(const v1::UpdateObscurancesRequest& request) {
  return CallUnary(&v1::VisibilityService::Stub::UpdateObscurances, request.scene().name(), request);
}

StatusOr<ObscurancePreview> Client::RenderObscurancePreview(const v1::ObscurancePreviewRequest& request) {
  ObscurancePreview out;
  bool first = true;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::RenderObscurancePreview, request,
      [&](v1::ObscurancePreviewResponse& message) -> Status {
        VISQ_RETURN_IF_ERROR(AppendChunk(message.rgb(), message.offset(), out.rgb, "rgb"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.covered(), message.covered_offset(), out.covered, "covered"));
        if (first) {
          message.clear_rgb();
          message.clear_covered();
          out.figures = std::move(message);
          first = false;
        }
        return absl::OkStatus();
      }));
  const size_t pixels = size_t{out.figures.width()} * out.figures.height();
  if (out.rgb.size() != pixels * 3 || out.covered.size() != pixels)
    return absl::DataLossError(absl::StrCat("obscurance preview: ", out.rgb.size(), " rgb floats and ",
                                            out.covered.size(), " coverage bytes for ", out.figures.width(), " x ",
                                            out.figures.height(), " pixels"));
  return out;
}

StatusOr<ObscuranceExport> Client::ExportObscurances(const v1::ExportObscurancesRequest& request) {
  ObscuranceExport out;
  bool first = true;
  VISQ_RETURN_IF_ERROR(CallStreamed(
      *this, &v1::VisibilityService::Stub::ExportObscurances, request,
      [&](v1::ExportObscurancesResponse& message) -> Status {
        VISQ_RETURN_IF_ERROR(AppendChunk(message.atlas_uv(), message.offset(), out.atlas_uv, "atlas_uv"));
        VISQ_RETURN_IF_ERROR(AppendChunk(message.glb(), message.glb_offset(), out.glb, "glb"));
        if (first) {
          message.clear_atlas_uv();
          message.clear_glb();
          out.figures = std::move(message);
          first = false;
        }
        return absl::OkStatus();
      }));
  if (request.want_atlas_uvs() && out.atlas_uv.size() != out.figures.triangles() * 6)
    return absl::DataLossError(absl::StrCat("obscurance export: ", out.atlas_uv.size(), " UV floats for ",
                                            out.figures.triangles(), " triangles"));
  return out;
}

Status MergeObscurancePartials(obscurance::ObscurancePartial& into, const obscurance::ObscurancePartial& from) {
  std::string error;
  if (!obscurance::MergeObscurancePartial(into, from, &error)) return absl::InvalidArgumentError(error);
  return absl::OkStatus();
}

StatusOr<ObscuranceBake> ShardedBake(const std::vector<Client*>& clients, v1::ComputeObscurancesRequest request,
                                     uint32_t shards) {
  if (clients.empty()) return absl::InvalidArgumentError("clients: none given");
  if (shards == 0) return absl::InvalidArgumentError("shards: 0 must be at least 1");
  const uint32_t first = request.first_direction();
  const uint32_t count = request.direction_count() != 0 ? request.direction_count() : 256;
  if (request.total_directions() == 0) request.set_total_directions(first + count);
  request.set_partial_only(true);
  // Consecutive ranges, as even as integers allow; empty ones are dropped.
  std::vector<v1::ComputeObscurancesRequest> parts;
  for (uint32_t i = 0; i < shards; ++i) {
    const uint32_t begin = first + static_cast<uint32_t>(uint64_t{count} * i / shards);
    const uint32_t end = first + static_cast<uint32_t>(uint64_t{count} * (i + 1) / shards);
    if (end == begin) continue;
    v1::ComputeObscurancesRequest part = request;
    part.set_first_direction(begin);
    part.set_direction_count(end - begin);
    parts.push_back(std::move(part));
  }
  std::vector<std::optional<StatusOr<ObscuranceBake>>> results(parts.size());
  {
    std::vector<std::thread> threads;
    for (size_t i = 0; i < parts.size(); ++i)
      threads.emplace_back([&, i] { results[i] = clients[i % clients.size()]->ComputeObscurances(parts[i]); });
    for (auto& t : threads) t.join();
  }
  ObscuranceBake merged;
  for (size_t i = 0; i < results.size(); ++i) {
    StatusOr<ObscuranceBake>& r = *results[i];
    if (!r.ok())
      return Status(r.status().code(), absl::StrCat("shard [", parts[i].first_direction(), ", ",
                                                    parts[i].first_direction() + parts[i].direction_count(),
                                                    "): ", r.status().message()));
    VISQ_RETURN_IF_ERROR(MergeObscurancePartials(merged.partial, r->partial));
    if (i == 0) merged.figures = r->figures;
    merged.progress_messages += r->progress_messages;
  }
  merged.figures.clear_ranges();
  for (const auto& range : merged.partial.ranges) {
    auto* out = merged.figures.add_ranges();
    out->set_first(range.first);
    out->set_count(range.count);
  }
  // The shard's error statement, restated for all the merged directions
  // (the server's formula: a Hoeffding half-width at 95 %, an estimate).
  const double directions = static_cast<double>(std::max<uint64_t>(merged.partial.DirectionCount(), 1));
  auto* accuracy = merged.figures.mutable_accuracy();
  accuracy->set_error_bound(std::sqrt(std::log(2.0 / (1.0 - accuracy->confidence())) / (2.0 * directions)));
  accuracy->set_note(absl::StrCat("merged from ", parts.size(), " shards, ", merged.partial.DirectionCount(),
                                  " directions; estimate, not a bound: Hoeffding half-width at 95 % for independent "
                                  "directions with per-direction values in [0, 1]"));
  merged.figures.clear_timing();
  return merged;
}

StatusOr<ObscuranceBake> ShardedBake(const std::vector<std::string>& addresses, const ClientOptions& options,
                                     v1::ComputeObscurancesRequest request, uint32_t shards) {
  std::vector<std::unique_ptr<Client>> owned;
  std::vector<Client*> clients;
  for (const std::string& address : addresses) {
    ClientOptions o = options;
    o.address = address;
    owned.push_back(std::make_unique<Client>(o));
    VISQ_RETURN_IF_ERROR(owned.back()->init_status());
    clients.push_back(owned.back().get());
  }
  return ShardedBake(clients, std::move(request), shards);
}

}  // namespace visq::client
