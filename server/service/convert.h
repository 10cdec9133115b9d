// Wire messages <-> core types, for the algorithm RPCs. Field-level checks
// that need the message (presence, sizes) live here; everything else is the
// core's to validate.
#pragma once

#include <functional>

#include "common/status.h"
#include "core/light_visibility_query.h"
#include "core/obscurance_query.h"
#include "core/scene_edit_query.h"
#include "core/visibility_sampling_query.h"
#include "core/volumetric_query.h"
#include "core/voxel_query.h"
#include "service/chunked_responses.h"
#include "visq/v1/visq.pb.h"

namespace visq::service {

glm::dvec3 FromProto(const v1::Vec3& v);
// The scene a query names: INVALID_ARGUMENT "scene.name: empty" without one.
[[nodiscard]] Status SceneRefFromProto(const v1::SceneRef& ref, std::string& name, uint64_t& version);
void ToProto(const glm::dvec3& v, v1::Vec3* out);
Bounds FromProto(const v1::Box& box);
void ToProto(const Bounds& box, v1::Box* out);
void ToProto(const std::vector<glm::dvec3>& polygon, v1::Polygon* out);

// `previous` supplies scene and light for stream messages that omit them.
[[nodiscard]] StatusOr<core::LightVisibilityQuery> FromProto(const v1::LightVisibilityRequest& request,
                                                             const core::LightVisibilityQuery* previous = nullptr);
void ToProto(const core::LightVisibilityAnswer& answer, v1::LightVisibilityResponse* out);

// A target as the core takes it (confidence 0 on the wire means 0.95).
StatusOr<core::AccuracyTarget> FromProto(const v1::AccuracyTarget& target);
// The core's statement, field by field.
void ToProto(const core::AccuracyStatement& statement, v1::Accuracy* out);
// The plans the planner weighed, beside the statement of the chosen one.
void ToProto(const core::PlanReport& plan, v1::Accuracy* out);

// Answers streamed in bands (banded_stream.h), each as three kinds of
// message: FirstMessage holds the figures known before any band;
// WriteBand writes a band's messages to `write`, one array chunk of at most
// `chunk_elements` each, each chunk's `offset` counting from the whole
// answer's first element, and stops at the first write that fails;
// LastMessage holds what needs every band (its accuracy; the handler adds
// the timing). DescribeAnswer is the answer's log line.
template <typename Response>
using MessageWrite = std::function<Status(Response)>;

[[nodiscard]] StatusOr<core::HiddenSampleMapQuery> FromProto(const v1::HiddenSampleMapRequest& request);
// First: sizes and source samples. Bands: fractions, colours, bitmask words
// (offsets in words), lookup errors, and the texels' own bounds where asked.
v1::HiddenSampleMapResponse FirstMessage(const sampling::HiddenSampleMapResult& figures);
[[nodiscard]] Status WriteBand(const core::HiddenSampleMapQuery& query, const sampling::HiddenSampleMapResult& figures,
                               const sampling::HiddenSampleMapBand& band,
                               const MessageWrite<v1::HiddenSampleMapResponse>& write,
                               size_t chunk_elements = kChunkElements);
v1::HiddenSampleMapResponse LastMessage(const core::HiddenSampleMapAnswer& answer);
std::string DescribeAnswer(const core::HiddenSampleMapQuery& query, const core::HiddenSampleMapAnswer& answer);

[[nodiscard]] StatusOr<core::PatchVisibilityQuery> FromProto(const v1::PatchVisibilityRequest& request);
void ToProto(const core::PatchVisibilityAnswer& answer, v1::PatchVisibilityResponse* out);

// A whole-bake request with a target is returned unvalidated beyond the
// target's exclusions: the core validates once the planner chose the count.
[[nodiscard]] StatusOr<core::ObscuranceQuery> FromProto(const v1::ComputeObscurancesRequest& request);
// The figures first, then each array in chunks (offsets count floats).
ChunkedResponses<v1::ComputeObscurancesResponse> ToProtoStream(core::ObscuranceAnswer answer, bool want_averages,
                                                               bool want_errors);
// The moved node's request; the core validates the matrix and names.
core::NodeTransformQuery FromProto(const v1::SetNodeTransformRequest& request);
// The update's request; the caller adds the call's options.
core::ObscuranceUpdateQuery FromProto(const v1::UpdateObscurancesRequest& request);
void ToProto(const core::ObscuranceUpdateAnswer& answer, v1::UpdateObscurancesResponse* out);

[[nodiscard]] StatusOr<core::ObscurancePreviewQuery> FromProto(const v1::ObscurancePreviewRequest& request);
// Figures first, then chunks of rgb floats, then of coverage bytes.
ChunkedResponses<v1::ObscurancePreviewResponse> ToProtoStream(core::ObscurancePreviewAnswer answer);

[[nodiscard]] StatusOr<core::ObscuranceExportQuery> FromProto(const v1::ExportObscurancesRequest& request);
// Figures first, then chunks of atlas_uv floats, then of glb bytes.
ChunkedResponses<v1::ExportObscurancesResponse> ToProtoStream(core::ObscuranceExportAnswer answer);

[[nodiscard]] StatusOr<core::VolumetricQuery> FromProto(const v1::VolumetricShadowRequest& request);
// First: sizes, method, integrand, the map's accuracy. Bands: the images'
// floats (offsets in floats, 3 a pixel). Last: the error estimate, stages.
v1::VolumetricShadowResponse FirstMessage(const volumetric_shadows::VolumetricResult& figures);
[[nodiscard]] Status WriteBand(const core::VolumetricQuery& query, const volumetric_shadows::VolumetricResult& figures,
                               const volumetric_shadows::VolumetricBand& band,
                               const MessageWrite<v1::VolumetricShadowResponse>& write,
                               size_t chunk_elements = kChunkElements);
v1::VolumetricShadowResponse LastMessage(const core::VolumetricAnswer& answer);
std::string DescribeAnswer(const core::VolumetricQuery& query, const core::VolumetricAnswer& answer);

[[nodiscard]] StatusOr<core::VoxelizeQuery> FromProto(const v1::VoxelizeRequest& request);
// First: sizes, box, modes, accuracy. Bands: bits (offsets in words) and
// local ranges (in columns). Last: the counts and stages.
v1::VoxelizeResponse FirstMessage(const voxel_reference::VoxelizeResult& figures);
[[nodiscard]] Status WriteBand(const core::VoxelizeQuery& query, const voxel_reference::VoxelizeResult& figures,
                               const voxel_reference::VoxelizeBand& band, const MessageWrite<v1::VoxelizeResponse>& write,
                               size_t chunk_elements = kChunkElements);
v1::VoxelizeResponse LastMessage(const core::VoxelizeAnswer& answer);
std::string DescribeAnswer(const core::VoxelizeQuery& query, const core::VoxelizeAnswer& answer);
[[nodiscard]] StatusOr<core::TransmittanceQuery> FromProto(const v1::TransmittanceRequest& request);
void ToProto(const core::TransmittanceAnswer& answer, v1::TransmittanceResponse* out);

}  // namespace visq::service
