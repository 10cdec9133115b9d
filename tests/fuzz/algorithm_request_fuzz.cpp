// libFuzzer target: the validation every algorithm RPC applies before any
// work is queued, exactly as the server runs it: the wire message parsed by
// protobuf, converted by the service layer (service/convert.h), then checked
// by the core against a resident scene (the generated Cornell box, whose
// node names the corpus uses). No GPU and no Embree: what this covers is
// everything a hostile request meets before it may cost GPU time.
//
// Input: one byte choosing the request kind (HiddenSampleMap, PatchVisibility,
// LightVisibility, Voxelize, Transmittance, VolumetricShadow,
// ComputeObscurances, RenderObscurancePreview), then the serialized message.
// Besides the sanitizers, two oracles: validation never crashes or traps,
// and what it accepts respects the caps the server documents (a request
// that passed must be one the GPU may be given).
#include <cmath>
#include <cstdint>
#include <cstdlib>

#include <google/protobuf/stubs/logging.h>

#include "core/light_visibility_query.h"
#include "core/obscurance_query.h"
#include "core/visibility_sampling_query.h"
#include "core/voxel_query.h"
#include "scene/sample_scenes.h"
#include "service/convert.h"
#include "visq/gpu/camera.h"
#include "visq/gpu/obscurance.h"

namespace {

using namespace visq;

const Scene& FuzzScene() {
  static const Scene scene = MakeCornellBox();
  return scene;
}

bool Finite(const glm::dvec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

void Require(bool invariant) {
  if (!invariant) __builtin_trap();
}

template <typename Message>
bool Parse(const uint8_t* data, size_t size, Message* message) {
  return message->ParseFromArray(data, static_cast<int>(size));
}

void HiddenSampleMap(const uint8_t* data, size_t size) {
  v1::HiddenSampleMapRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok() || !core::ValidateHiddenSampleMapQuery(*query).ok()) return;
  const sampling::HiddenSampleMapRequest& r = query->request;
  Require(r.receiver.width > 0 && r.receiver.height > 0);
  if (!query->target && query->method != core::VisibilityMethod::kPluckerExact)
    Require(uint64_t(r.receiver.width) * uint64_t(r.receiver.height) * uint64_t(r.source.sample_count) <=
            core::kMaxHiddenSampleBits);
  Require(r.source.sample_count >= 0 && r.source.sample_count <= sampling::kMaxHiddenSampleMapSamples);
}

void PatchVisibility(const uint8_t* data, size_t size) {
  v1::PatchVisibilityRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok()) return;
  (void)core::ValidatePatchVisibilityQuery(*query);
}

void LightVisibility(const uint8_t* data, size_t size) {
  v1::LightVisibilityRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok() || !core::ValidateLightVisibilityQuery(*query, FuzzScene()).ok()) return;
  Require(query->light.vertices.size() >= 3 && query->light.vertices.size() <= core::kMaxLightVertices);
  Require(std::isfinite(query->light.radiance) && query->light.radiance >= 0);
  if (query->shadow_tolerance) Require(*query->shadow_tolerance >= 0.0 && *query->shadow_tolerance <= 1.0);
  for (const exact::QueryPoint& p : query->points) {
    Require(Finite(p.position));
    if (p.receiver_triangle) Require(*p.receiver_triangle < FuzzScene().TriangleCount());
  }
}

void Voxelize(const uint8_t* data, size_t size) {
  v1::VoxelizeRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok()) return;
  auto params = core::ResolveVoxelizeQuery(*query, FuzzScene());
  if (!params.ok()) return;
  Require(Finite(params->box.center) && Finite(params->box.half_extent));
  for (const auto& range : params->triangles)
    Require(uint64_t(range.first) + range.count <= FuzzScene().TriangleCount());
}

void Transmittance(const uint8_t* data, size_t size) {
  v1::TransmittanceRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok()) return;
  auto params = core::ResolveTransmittanceQuery(*query, FuzzScene());
  if (!params.ok()) return;
  Require(!params->nodes.empty());
  for (const gpu::AbsorbingNode& node : params->nodes) {
    Require(node.node < FuzzScene().nodes.size());
    Require(std::isfinite(node.absorption) && node.absorption >= 0);
  }
  for (const glm::dvec3& p : params->points) Require(Finite(p));
}

void Volumetric(const uint8_t* data, size_t size) {
  v1::VolumetricShadowRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok()) return;
  (void)gpu::ValidateVolumetricParams(query->params);
}

void Obscurances(const uint8_t* data, size_t size) {
  v1::ComputeObscurancesRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok()) return;
  if (query->target) {
    (void)core::ValidateAccuracyTarget(*query->target);
    return;
  }
  Require(core::ValidateObscuranceQuery(*query).ok());  // FromProto validated it already
  Require(std::isfinite(query->params.d_max));
}

void ObscurancePreview(const uint8_t* data, size_t size) {
  v1::ObscurancePreviewRequest request;
  if (!Parse(data, size, &request)) return;
  auto query = service::FromProto(request);
  if (!query.ok() || !gpu::ValidatePinholeCamera(query->camera, gpu::kMaxObscurancePreviewSize).ok()) return;
  Require(Finite(query->camera.position) && Finite(query->camera.forward));
  Require(query->camera.width <= gpu::kMaxObscurancePreviewSize && query->camera.height <= gpu::kMaxObscurancePreviewSize);
}

}  // namespace

// Protobuf logs every string field with invalid UTF-8 it parses; the
// fuzzer makes thousands a second.
void IgnoreProtobufLog(google::protobuf::LogLevel, const char*, int, const std::string&) {}

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  google::protobuf::SetLogHandler(&IgnoreProtobufLog);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const uint8_t kind = data[0] % 8;
  ++data;
  --size;
  switch (kind) {
    case 0: HiddenSampleMap(data, size); break;
    case 1: PatchVisibility(data, size); break;
    case 2: LightVisibility(data, size); break;
    case 3: Voxelize(data, size); break;
    case 4: Transmittance(data, size); break;
    case 5: Volumetric(data, size); break;
    case 6: Obscurances(data, size); break;
    case 7: ObscurancePreview(data, size); break;
  }
  return 0;
}
