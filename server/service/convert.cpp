#include "service/convert.h"

#include <absl/strings/str_format.h>

#include "common/check.h"

namespace visq::service {

// The algorithms' enums this file converts most, named by their lib/ floor.
using volumetric_shadows::VolumetricLightKind;
using volumetric_shadows::VolumetricMethod;
using voxel_reference::TransmittanceLightKind;

glm::dvec3 FromProto(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

Status SceneRefFromProto(const v1::SceneRef& ref, std::string& name, uint64_t& version) {
  if (ref.name().empty()) return absl::InvalidArgumentError("scene.name: empty");
  name = ref.name();
  version = ref.version();
  return absl::OkStatus();
}

void ToProto(const glm::dvec3& v, v1::Vec3* out) {
  out->set_x(v.x);
  out->set_y(v.y);
  out->set_z(v.z);
}

Bounds FromProto(const v1::Box& box) {
  Bounds b;
  b.min = FromProto(box.min());
  b.max = FromProto(box.max());
  return b;
}

void ToProto(const Bounds& box, v1::Box* out) {
  ToProto(box.min, out->mutable_min());
  ToProto(box.max, out->mutable_max());
}

void ToProto(const std::vector<glm::dvec3>& polygon, v1::Polygon* out) {
  for (const auto& v : polygon) ToProto(v, out->add_vertices());
}

StatusOr<core::LightVisibilityQuery> FromProto(const v1::LightVisibilityRequest& request,
                                               const core::LightVisibilityQuery* previous) {
  core::LightVisibilityQuery query;
  if (request.scene().name().empty()) {
    if (previous == nullptr) return absl::InvalidArgumentError("scene.name: empty");
    query.scene = previous->scene;
    query.scene_version = previous->scene_version;
  } else {
    query.scene = request.scene().name();
    query.scene_version = request.scene().version();
  }
  if (request.light().vertices().empty()) {
    if (previous == nullptr) return absl::InvalidArgumentError("light.vertices: empty");
    query.light = previous->light;
  } else {
    for (const auto& v : request.light().vertices()) query.light.vertices.push_back(FromProto(v));
    query.light.radiance = request.radiance() == 0.0 ? 1.0 : request.radiance();
  }
  query.points.reserve(request.points_size());
  for (const auto& p : request.points()) {
    exact::QueryPoint point;
    point.position = FromProto(p.position());
    if (p.has_normal()) point.normal = FromProto(p.normal());
    if (p.has_triangle()) point.receiver_triangle = p.triangle();
    query.points.push_back(point);
  }
  query.want_polygons = request.want_polygons();
  if (request.has_receiver_region()) query.receiver_region = FromProto(request.receiver_region());
  else if (previous != nullptr && request.light().vertices().empty()) query.receiver_region = previous->receiver_region;
  query.exclude_nodes.assign(request.exclude_nodes().begin(), request.exclude_nodes().end());
  if (request.has_shadow_tolerance()) query.shadow_tolerance = request.shadow_tolerance();
  else if (previous != nullptr && request.light().vertices().empty()) query.shadow_tolerance = previous->shadow_tolerance;
  if (query.exclude_nodes.empty() && previous != nullptr && request.light().vertices().empty())
    query.exclude_nodes = previous->exclude_nodes;
  return query;
}

void ToProto(const core::LightVisibilityAnswer& answer, v1::LightVisibilityResponse* out) {
  out->mutable_points()->Reserve(static_cast<int>(answer.points.size()));
  for (const auto& p : answer.points) {
    auto* point = out->add_points();
    point->set_visible_fraction(p.visible_area_fraction);
    point->set_visible_solid_angle_fraction(p.visible_solid_angle_fraction);
    point->set_irradiance(p.irradiance);
    point->set_visible_fraction_error(p.visible_area_fraction_error);
    point->set_visible_solid_angle_fraction_error(p.visible_solid_angle_fraction_error);
    point->set_irradiance_error(p.irradiance_error);
    for (const auto& polygon : p.visible_polygons) ToProto(polygon, point->add_visible_polygons());
  }
  auto* tree = out->mutable_tree();
  tree->set_reused(answer.tree_reused);
  tree->set_nodes(answer.tree.nodes);
  tree->set_memory_bytes(answer.tree.memory_bytes);
  tree->set_queries(answer.tree.queries);
  tree->set_hits(answer.tree.hits);
  tree->set_refinements(answer.tree.refinements);
  tree->set_unrefined_leaf_visits(answer.tree.unrefined_leaf_visits);
  tree->set_wholly_visible(answer.tree.wholly_visible);
  tree->set_wholly_hidden(answer.tree.wholly_hidden);
  tree->set_subtracted_directly(answer.tree.subtracted_directly);
  tree->set_answers_reused(answer.tree.answers_reused);
  tree->set_answers_kept(answer.tree.answers_kept);
  tree->set_far_occluders(answer.tree.far_occluders);
  tree->set_near_occluders(answer.tree.near_occluders);
  tree->set_trees(static_cast<uint32_t>(answer.trees));
  tree->set_trees_created(static_cast<uint32_t>(answer.trees_created));
  ToProto(answer.receiver_region, tree->mutable_receiver_region());
  ToProto(core::LightVisibilityStatement(answer), out->mutable_accuracy());
}

namespace {

sampling::Patch PatchFromProto(const v1::Patch& p) {
  return sampling::Patch{FromProto(p.origin()), FromProto(p.edge_u()), FromProto(p.edge_v())};
}

// METHOD_UNSPECIFIED: none, the server chooses.
StatusOr<std::optional<core::VisibilityMethod>> MethodFromProto(v1::VisibilityMethod method) {
  switch (method) {
    case v1::METHOD_UNSPECIFIED: return std::optional<core::VisibilityMethod>();
    case v1::RASTER: return core::VisibilityMethod::kRaster;
    case v1::RAYCAST: return core::VisibilityMethod::kRaycast;
    case v1::GPU_RAYCAST: return core::VisibilityMethod::kGpuRaycast;
    case v1::PLUCKER_EXACT: return core::VisibilityMethod::kPluckerExact;
    default: return absl::InvalidArgumentError(absl::StrCat("method: unknown value ", static_cast<int>(method)));
  }
}

StatusOr<sampling::LookupMode> LookupFromProto(v1::LookupMode lookup) {
  switch (lookup) {
    case v1::LOOKUP_UNSPECIFIED:
    case v1::EXACT: return sampling::LookupMode::kExact;
    case v1::HOUGH: return sampling::LookupMode::kHough;
    default: return absl::InvalidArgumentError(absl::StrCat("lookup: unknown value ", static_cast<int>(lookup)));
  }
}

// Sizes arrive as uint32; the algorithm takes int. Values past int's range
// would wrap, so they are refused here with the field named.
StatusOr<int> SizeFromProto(uint32_t value, const char* field) {
  if (value > (1u << 24)) return absl::InvalidArgumentError(absl::StrCat(field, ": ", value, " is out of range"));
  return static_cast<int>(value);
}

// A request with a target leaves the count and the method to the server.
StatusOr<std::optional<core::AccuracyTarget>> TargetFromRequest(bool has_target, const v1::AccuracyTarget& target,
                                                                v1::VisibilityMethod method) {
  if (!has_target) return std::optional<core::AccuracyTarget>();
  if (method != v1::METHOD_UNSPECIFIED)
    return absl::InvalidArgumentError("method: give either a method or a target, not both");
  VISQ_ASSIGN_OR_RETURN(core::AccuracyTarget out, FromProto(target));
  return std::optional<core::AccuracyTarget>(out);
}

}  // namespace

StatusOr<core::AccuracyTarget> FromProto(const v1::AccuracyTarget& target) {
  core::AccuracyTarget out;
  out.max_error = target.max_error();
  if (target.confidence() != 0.0) out.confidence = target.confidence();
  out.time_budget_ms = target.time_budget_ms();
  switch (target.guarantee()) {
    case v1::AccuracyTarget::GUARANTEE_UNSPECIFIED: out.guarantee = core::AccuracyTarget::Guarantee::kDefault; break;
    case v1::AccuracyTarget::RIGOROUS: out.guarantee = core::AccuracyTarget::Guarantee::kRigorous; break;
    case v1::AccuracyTarget::ESTIMATE: out.guarantee = core::AccuracyTarget::Guarantee::kEstimate; break;
    default: return absl::InvalidArgumentError(absl::StrCat("target.guarantee: unknown value ", target.guarantee()));
  }
  return out;
}

void ToProto(const core::AccuracyStatement& statement, v1::Accuracy* out) {
  out->set_method(statement.method);
  out->set_error_bound(statement.error_bound);
  out->set_confidence(statement.confidence);
  out->set_note(statement.note);
  for (const auto& [name, value] : statement.parameters) (*out->mutable_parameters())[name] = value;
  if (statement.predicted_ms > 0) out->set_predicted_ms(statement.predicted_ms);
  if (statement.estimate >= 0) out->set_estimate(statement.estimate);
}

void ToProto(const core::PlanReport& plan, v1::Accuracy* out) {
  for (const core::Plan& p : plan.plans) {
    v1::PlanEstimate* estimate = out->add_plans();
    estimate->set_method(p.method);
    for (const auto& [name, value] : p.parameters) (*estimate->mutable_parameters())[name] = value;
    estimate->set_error_bound(p.error_bound);
    estimate->set_predicted_ms(p.predicted_ms);
    estimate->set_meets_target(p.meets_target);
  }
}

StatusOr<core::HiddenSampleMapQuery> FromProto(const v1::HiddenSampleMapRequest& request) {
  core::HiddenSampleMapQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  VISQ_ASSIGN_OR_RETURN(query.method, MethodFromProto(request.method()));
  VISQ_ASSIGN_OR_RETURN(query.target, TargetFromRequest(request.has_target(), request.target(), request.method()));
  sampling::HiddenSampleMapRequest& r = query.request;
  r.source.patch = PatchFromProto(request.source());
  VISQ_ASSIGN_OR_RETURN(r.source.sample_count, SizeFromProto(request.samples().count(), "samples.count"));
  switch (request.samples().pattern()) {
    case v1::SamplingSpec::PATTERN_UNSPECIFIED:
    case v1::SamplingSpec::JITTERED: r.source.pattern = sampling::SamplePattern::kJittered; break;
    case v1::SamplingSpec::REGULAR: r.source.pattern = sampling::SamplePattern::kRegular; break;
    case v1::SamplingSpec::CUSTOM: r.source.pattern = sampling::SamplePattern::kCustom; break;
    default: return absl::InvalidArgumentError("samples.pattern: unknown value");
  }
  r.source.seed = request.samples().seed();
  for (const auto& uv : request.samples().custom_uv()) r.source.custom_uv.emplace_back(uv.x(), uv.y());
  for (const auto& uv : request.samples().polygon_uv()) r.source.polygon_uv.emplace_back(uv.x(), uv.y());
  for (const auto& c : request.samples().sample_colors()) r.source.sample_colors.emplace_back(c.x(), c.y(), c.z());
  if (request.samples().color_texture_width() > 0 || request.samples().color_texture_rgb_size() > 0) {
    VISQ_ASSIGN_OR_RETURN(r.source.color_texture_width,
                          SizeFromProto(request.samples().color_texture_width(), "samples.color_texture_width"));
    VISQ_ASSIGN_OR_RETURN(r.source.color_texture_height,
                          SizeFromProto(request.samples().color_texture_height(), "samples.color_texture_height"));
    const auto& rgb = request.samples().color_texture_rgb();
    if (rgb.size() % 3 != 0)
      return absl::InvalidArgumentError(absl::StrCat("samples.color_texture_rgb: ", rgb.size(), " floats, not RGB triples"));
    for (int i = 0; i + 2 < rgb.size(); i += 3) r.source.color_texture.emplace_back(rgb[i], rgb[i + 1], rgb[i + 2]);
  }
  r.receiver.patch = PatchFromProto(request.receiver());
  VISQ_ASSIGN_OR_RETURN(r.receiver.width, SizeFromProto(request.width(), "width"));
  VISQ_ASSIGN_OR_RETURN(r.receiver.height, SizeFromProto(request.height(), "height"));
  r.receiver.heightfield.assign(request.heightfield().begin(), request.heightfield().end());
  r.options.decorrelate = request.decorrelate();
  r.options.decorrelation_seed = request.decorrelation_seed();
  r.options.watertight = request.watertight();
  VISQ_ASSIGN_OR_RETURN(r.options.lookup, LookupFromProto(request.lookup()));
  if (request.hough_resolution() != 0) {
    VISQ_ASSIGN_OR_RETURN(r.options.hough_theta_resolution, SizeFromProto(request.hough_resolution(), "hough_resolution"));
    r.options.hough_r_resolution = r.options.hough_theta_resolution;
  }
  r.options.want_bitmasks = request.want_bitmasks();
  query.want_texel_error = request.want_texel_error();
  if (request.confidence() != 0.0) r.options.confidence = request.confidence();
  return query;
}

v1::HiddenSampleMapResponse FirstMessage(const sampling::HiddenSampleMapResult& map) {
  v1::HiddenSampleMapResponse first;
  first.set_width(map.width);
  first.set_height(map.height);
  first.set_sample_count(map.sample_count);
  first.set_words_per_texel(map.words_per_texel);
  for (const auto& p : map.samples.world) ToProto(p, first.add_source_samples());
  return first;
}

Status WriteBand(const core::HiddenSampleMapQuery& query, const sampling::HiddenSampleMapResult& figures,
                 const sampling::HiddenSampleMapBand& band, const MessageWrite<v1::HiddenSampleMapResponse>& write,
                 size_t chunk_elements) {
  VISQ_CHECK_LT(size_t{0}, chunk_elements);
  const size_t words_per_texel = size_t(figures.words_per_texel);
  using Message = v1::HiddenSampleMapResponse;
  // One array chunk per message; offsets count texels, or words for the
  // bitmasks, from the map's first.
  auto chunks = [&](size_t size, size_t first_offset, auto fill) {
    return WriteChunks<Message>(size, first_offset, chunk_elements, write, fill);
  };
  VISQ_RETURN_IF_ERROR(chunks(band.visible_fraction.size(), band.first, [&](Message& m, size_t a, size_t b) {
    AddRange(band.visible_fraction, a, b, m.mutable_visible_fraction());
  }));
  VISQ_RETURN_IF_ERROR(chunks(band.visible_rgb.size(), band.first, [&](Message& m, size_t a, size_t b) {
    m.mutable_visible_rgb()->Reserve(static_cast<int>(3 * (b - a)));
    for (size_t i = a; i < b; ++i) {
      m.add_visible_rgb(band.visible_rgb[i].r);
      m.add_visible_rgb(band.visible_rgb[i].g);
      m.add_visible_rgb(band.visible_rgb[i].b);
    }
  }));
  VISQ_RETURN_IF_ERROR(chunks(band.blocked_bits.size(), band.first * words_per_texel,
                              [&](Message& m, size_t a, size_t b) {
                                AddRange(band.blocked_bits, a, b, m.mutable_blocked_bits());
                              }));
  VISQ_RETURN_IF_ERROR(chunks(band.lookup_error.size(), band.first, [&](Message& m, size_t a, size_t b) {
    AddRange(band.lookup_error, a, b, m.mutable_lookup_error());
  }));
  if (!query.want_texel_error) return absl::OkStatus();
  VISQ_RETURN_IF_ERROR(chunks(band.texel_error.size(), band.first, [&](Message& m, size_t a, size_t b) {
    AddRange(band.texel_error, a, b, m.mutable_texel_error());
  }));
  return chunks(band.texel_estimate.size(), band.first, [&](Message& m, size_t a, size_t b) {
    AddRange(band.texel_estimate, a, b, m.mutable_texel_estimate());
  });
}

v1::HiddenSampleMapResponse LastMessage(const core::HiddenSampleMapAnswer& answer) {
  v1::HiddenSampleMapResponse last;
  ToProto(answer.accuracy, last.mutable_accuracy());
  if (answer.plan) ToProto(*answer.plan, last.mutable_accuracy());
  return last;
}

std::string DescribeAnswer(const core::HiddenSampleMapQuery& query, const core::HiddenSampleMapAnswer& answer) {
  const sampling::HiddenSampleMapResult& result = answer.result;
  return absl::StrCat(core::VisibilityMethodName(answer.method, query.request.options.lookup), " ", result.width, "x",
                      result.height, " texels, ", result.sample_count, " samples",
                      answer.plan ? absl::StrFormat(" (chosen by the cost model, predicted %.1f ms)",
                                                    answer.plan->chosen_plan().predicted_ms)
                                  : std::string());
}

StatusOr<core::PatchVisibilityQuery> FromProto(const v1::PatchVisibilityRequest& request) {
  core::PatchVisibilityQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  VISQ_ASSIGN_OR_RETURN(query.method, MethodFromProto(request.method()));
  VISQ_ASSIGN_OR_RETURN(query.target, TargetFromRequest(request.has_target(), request.target(), request.method()));
  if (query.target && (request.source_columns() != 0 || request.source_rows() != 0))
    return absl::InvalidArgumentError("source_columns, source_rows: give either a source grid or a target, not both");
  sampling::PatchVisibilityRequest& r = query.request;
  r.source = PatchFromProto(request.source());
  r.receiver = PatchFromProto(request.receiver());
  auto or_default = [](uint32_t v) { return v == 0 ? 32u : v; };
  VISQ_ASSIGN_OR_RETURN(r.source_columns, SizeFromProto(or_default(request.source_columns()), "source_columns"));
  VISQ_ASSIGN_OR_RETURN(r.source_rows, SizeFromProto(or_default(request.source_rows()), "source_rows"));
  VISQ_ASSIGN_OR_RETURN(r.receiver_columns, SizeFromProto(or_default(request.receiver_columns()), "receiver_columns"));
  VISQ_ASSIGN_OR_RETURN(r.receiver_rows, SizeFromProto(or_default(request.receiver_rows()), "receiver_rows"));
  VISQ_ASSIGN_OR_RETURN(r.lookup, LookupFromProto(request.lookup()));
  r.watertight = request.watertight();
  r.unblocked_limit = request.unblocked_limit();
  return query;
}

void ToProto(const core::PatchVisibilityAnswer& answer, v1::PatchVisibilityResponse* out) {
  const sampling::PatchVisibilityResult& result = answer.result;
  out->set_mutual_visible_fraction(result.mutual_visible_fraction);
  out->mutable_source_visible()->Add(result.source_visible.begin(), result.source_visible.end());
  out->mutable_receiver_visible()->Add(result.receiver_visible.begin(), result.receiver_visible.end());
  for (const auto& pair : result.unblocked) {
    auto* p = out->add_unblocked();
    p->set_source_sample(pair.source_sample);
    p->set_receiver_sample(pair.receiver_sample);
  }
  out->set_unblocked_total(result.unblocked_total);
  ToProto(answer.accuracy, out->mutable_accuracy());
  if (answer.plan) ToProto(*answer.plan, out->mutable_accuracy());
}


namespace {

// The pinhole camera fields every image request spells the same way
// (camera_position, camera_forward, camera_up, vertical_fov_deg, width,
// height): unset up is +y, unset (0) field of view 60 degrees.
template <typename Request>
PinholeCamera CameraFromProto(const Request& request) {
  PinholeCamera camera;
  camera.position = FromProto(request.camera_position());
  camera.forward = FromProto(request.camera_forward());
  if (request.has_camera_up()) camera.up = FromProto(request.camera_up());
  camera.vertical_fov_deg = request.vertical_fov_deg() == 0.0 ? 60.0 : request.vertical_fov_deg();
  camera.width = request.width();
  camera.height = request.height();
  return camera;
}

}  // namespace

StatusOr<core::VolumetricQuery> FromProto(const v1::VolumetricShadowRequest& request) {
  core::VolumetricQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  volumetric_shadows::VolumetricParams& p = query.params;
  p.camera = CameraFromProto(request);
  switch (request.light_kind()) {
    case v1::VolumetricShadowRequest::DIRECTIONAL: p.light.kind = VolumetricLightKind::kDirectional; break;
    case v1::VolumetricShadowRequest::SPOT: p.light.kind = VolumetricLightKind::kSpot; break;
    default: return absl::InvalidArgumentError("light_kind: unknown value");
  }
  p.light.direction = FromProto(request.light_direction());
  p.light.position = FromProto(request.light_position());
  if (request.cone_angle_deg() != 0.0) p.light.cone_angle_deg = request.cone_angle_deg();
  p.light.cone_falloff_deg = request.cone_falloff_deg();
  if (request.has_light_color()) p.light.color = FromProto(request.light_color());
  p.light.intensity = request.light_intensity() == 0.0 ? 1.0 : request.light_intensity();
  p.light.texture_width = request.light_texture_width();
  p.light.texture_height = request.light_texture_height();
  p.light.texture.assign(request.light_texture().begin(), request.light_texture().end());
  p.medium.scattering = request.scattering();
  p.medium.extinction = request.extinction();
  p.medium.hg_g = request.hg_g();
  p.medium.optically_thin = request.optically_thin();
  if (request.shadow_map_size() != 0) p.shadow_map_size = request.shadow_map_size();
  switch (request.method()) {
    case v1::VolumetricShadowRequest::MIN_MAX: p.method = VolumetricMethod::kMinMaxTraversal; break;
    case v1::VolumetricShadowRequest::RAY_MARCHING: p.method = VolumetricMethod::kRayMarching; break;
    default: return absl::InvalidArgumentError("method: unknown value");
  }
  p.combined_image = request.combined_image();
  query.estimate_error = request.estimate_error();
  if (request.has_target()) {
    if (request.shadow_map_size() != 0)
      return absl::InvalidArgumentError("shadow_map_size: leave it unset with a target (the server chooses the map)");
    VISQ_ASSIGN_OR_RETURN(query.target, FromProto(request.target()));
  }
  if (request.has_medium_box()) {
    // Given: the medium box whole; unset: the scene's bounds.
    const Bounds box = FromProto(request.medium_box());
    if (!(box.min.x < box.max.x && box.min.y < box.max.y && box.min.z < box.max.z))
      return absl::InvalidArgumentError("medium_box: min must be below max on every axis");
    p.medium_bounds.min = box.min;
    p.medium_bounds.max = box.max;
  }
  return query;
}

v1::VolumetricShadowResponse FirstMessage(const volumetric_shadows::VolumetricResult& result) {
  v1::VolumetricShadowResponse first;
  first.set_width(result.width);
  first.set_height(result.height);
  first.set_method(core::VolumetricMethodName(result.method));
  first.set_integrand(std::string(volumetric_shadows::VolumetricIntegrandName(result.integrand)));
  first.set_rectified_rows(result.rectified_rows);
  first.set_rectified_columns(result.rectified_columns);
  first.set_epipole_inside_map(result.epipole_inside_map);
  ToProto(core::VolumetricStatement(result), first.mutable_accuracy());
  return first;
}

Status WriteBand(const core::VolumetricQuery& /*query*/, const volumetric_shadows::VolumetricResult& /*figures*/,
                 const volumetric_shadows::VolumetricBand& band, const MessageWrite<v1::VolumetricShadowResponse>& write,
                 size_t chunk_elements) {
  VISQ_CHECK_LT(size_t{0}, chunk_elements);
  using Message = v1::VolumetricShadowResponse;
  // Offsets count floats, 3 per pixel.
  auto chunks = [&](const std::vector<float>& values, auto field) {
    return WriteChunks<Message>(values.size(), band.first * 3, chunk_elements, write,
                                [&](Message& m, size_t a, size_t b) { AddRange(values, a, b, (m.*field)()); });
  };
  VISQ_RETURN_IF_ERROR(chunks(band.inscattering, &Message::mutable_inscattering));
  return chunks(band.combined, &Message::mutable_combined);
}

v1::VolumetricShadowResponse LastMessage(const core::VolumetricAnswer& answer) {
  const volumetric_shadows::VolumetricResult& result = answer.result;
  v1::VolumetricShadowResponse last;
  if (const std::optional<core::AccuracyStatement> estimate = core::VolumetricEstimateStatement(answer))
    ToProto(*estimate, last.mutable_accuracy());
  auto& stage_ms = *last.mutable_stage_ms();
  stage_ms["setup"] = result.timings.setup_ms;
  if (result.integrand == volumetric_shadows::VolumetricIntegrand::kSvd)
    stage_ms["integrand_table"] = result.timings.integrand_table_ms;
  stage_ms["shadow_map"] = result.timings.shadow_map_ms;
  stage_ms["camera"] = result.timings.camera_ms;
  stage_ms["rectification"] = result.timings.rectification_ms;
  stage_ms["mipmap"] = result.timings.mipmap_ms;
  stage_ms["traversal"] = result.timings.traversal_ms;
  stage_ms["readback"] = result.timings.readback_ms;
  return last;
}

std::string DescribeAnswer(const core::VolumetricQuery& /*query*/, const core::VolumetricAnswer& answer) {
  const volumetric_shadows::VolumetricResult& result = answer.result;
  return absl::StrFormat("%ux%u %s (%s), %u map(s) rendered, traversal %.1f ms", result.width, result.height,
                         core::VolumetricMethodName(result.method),
                         volumetric_shadows::VolumetricIntegrandName(result.integrand), answer.maps_rendered.size(),
                         result.timings.traversal_ms);
}

StatusOr<core::ObscurancePreviewQuery> FromProto(const v1::ObscurancePreviewRequest& request) {
  core::ObscurancePreviewQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  query.camera = CameraFromProto(request);
  switch (request.quantity()) {
    case v1::ObscurancePreviewRequest::W: query.quantity = core::ObscurancePreviewQuery::Quantity::kW; break;
    case v1::ObscurancePreviewRequest::INTENSITY:
      query.quantity = core::ObscurancePreviewQuery::Quantity::kIntensity;
      break;
    default: return absl::InvalidArgumentError(absl::StrCat("quantity: unknown value ", request.quantity()));
  }
  return query;
}

ChunkedResponses<v1::ObscurancePreviewResponse> ToProtoStream(core::ObscurancePreviewAnswer answer_in) {
  auto kept = std::make_shared<const core::ObscurancePreviewAnswer>(std::move(answer_in));
  const core::ObscurancePreviewAnswer& answer = *kept;
  const obscurance::ObscurancePreviewImage& image = answer.image;
  v1::ObscurancePreviewResponse first;
  first.set_width(image.width);
  first.set_height(image.height);
  first.set_solution_version(answer.solution_version);
  first.set_quantity(answer.quantity == core::ObscurancePreviewQuery::Quantity::kW ? v1::ObscurancePreviewRequest::W
                                                                             : v1::ObscurancePreviewRequest::INTENSITY);
  // The rgb floats, then the coverage bytes.
  ChunkedResponses<v1::ObscurancePreviewResponse> stream(std::move(first));
  stream.Keep(kept);
  stream.Add(image.rgb.size(), [&image](v1::ObscurancePreviewResponse& m, size_t a, size_t b) {
    m.set_offset(a);
    AddRange(image.rgb, a, b, m.mutable_rgb());
  });
  stream.Add(image.covered.size(), [&image](v1::ObscurancePreviewResponse& m, size_t a, size_t b) {
    m.set_covered_offset(a);
    m.set_covered(reinterpret_cast<const char*>(image.covered.data() + a), b - a);
  });
  return stream;
}

StatusOr<core::ObscuranceExportQuery> FromProto(const v1::ExportObscurancesRequest& request) {
  core::ObscuranceExportQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  query.want_atlas_uvs = request.want_atlas_uvs();
  query.want_gltf = request.want_gltf();
  query.want_vertex_colors = request.want_vertex_colors();
  return query;
}

ChunkedResponses<v1::ExportObscurancesResponse> ToProtoStream(core::ObscuranceExportAnswer answer_in) {
  auto kept = std::make_shared<const core::ObscuranceExportAnswer>(std::move(answer_in));
  const core::ObscuranceExportAnswer& answer = *kept;
  v1::ExportObscurancesResponse first;
  first.set_solution_version(answer.solution_version);
  first.set_width(answer.width);
  first.set_height(answer.height);
  first.set_from_lightmap_uvs(answer.from_lightmap_uvs);
  first.set_triangles(answer.triangles);
  ChunkedResponses<v1::ExportObscurancesResponse> stream(std::move(first));
  stream.Keep(kept);
  stream.Add(answer.atlas_uv.size(), [&answer](v1::ExportObscurancesResponse& m, size_t a, size_t b) {
    m.set_offset(a);
    AddRange(answer.atlas_uv, a, b, m.mutable_atlas_uv());
  });
  stream.Add(answer.glb.size(), [&answer](v1::ExportObscurancesResponse& m, size_t a, size_t b) {
    m.set_glb_offset(a);
    m.set_glb(answer.glb.data() + a, b - a);
  });
  return stream;
}

StatusOr<core::VoxelizeQuery> FromProto(const v1::VoxelizeRequest& request) {
  core::VoxelizeQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  if (request.has_box()) {
    const v1::VoxelBox& b = request.box();
    query.box = voxel_reference::OrientedBox{FromProto(b.center()), FromProto(b.axis_u()), FromProto(b.axis_v()),
                                             FromProto(b.axis_w()), FromProto(b.half_extent())};
  }
  if (request.depth_axis() > 2)
    return absl::InvalidArgumentError(absl::StrCat("depth_axis: ", request.depth_axis(), " not in {0, 1, 2}"));
  query.depth_axis = static_cast<int>(request.depth_axis());
  query.params.width = request.width() == 0 ? 128 : request.width();
  query.params.height = request.height() == 0 ? 128 : request.height();
  query.params.slices = request.slices() == 0 ? 128 : request.slices();
  switch (request.mode()) {
    case v1::VoxelizeRequest::SURFACE: query.params.mode = voxel_reference::VoxelizeMode::kSurface; break;
    case v1::VoxelizeRequest::SOLID: query.params.mode = voxel_reference::VoxelizeMode::kSolid; break;
    default: return absl::InvalidArgumentError("mode: unknown value");
  }
  query.params.precision = request.local_precision() ? voxel_reference::SlicePrecision::kLocal
                                                     : voxel_reference::SlicePrecision::kUniform;
  query.params.rasterization = request.conservative() ? voxel_reference::Rasterization::kConservative
                                                      : voxel_reference::Rasterization::kStandard;
  query.nodes.assign(request.nodes().begin(), request.nodes().end());
  return query;
}

v1::VoxelizeResponse FirstMessage(const voxel_reference::VoxelizeResult& result) {
  v1::VoxelizeResponse first;
  const voxel_reference::OrientedBox& box = result.box;
  const voxel_reference::SlicemapGrid& grid = result.grid;
  first.set_width(grid.width);
  first.set_height(grid.height);
  first.set_slices(grid.slices);
  first.set_words_per_column(grid.words_per_column);
  first.set_rasterization(core::RasterizationName(result.rasterization));
  first.set_precision(core::SlicePrecisionName(result.precision));
  auto* b = first.mutable_box();
  ToProto(box.center, b->mutable_center());
  ToProto(box.axis_u, b->mutable_axis_u());
  ToProto(box.axis_v, b->mutable_axis_v());
  ToProto(box.axis_w, b->mutable_axis_w());
  ToProto(box.half_extent, b->mutable_half_extent());
  ToProto(core::VoxelizeStatement(result), first.mutable_accuracy());
  return first;
}

Status WriteBand(const core::VoxelizeQuery& /*query*/, const voxel_reference::VoxelizeResult& figures,
                 const voxel_reference::VoxelizeBand& band, const MessageWrite<v1::VoxelizeResponse>& write,
                 size_t chunk_elements) {
  const size_t words_per_column = figures.grid.words_per_column;
  VISQ_CHECK_LT(size_t{0}, chunk_elements);
  using Message = v1::VoxelizeResponse;
  // Offsets count words for the bits, columns for the local ranges.
  auto chunks = [&](const auto& values, size_t first_offset, auto field) {
    return WriteChunks<Message>(values.size(), first_offset, chunk_elements, write,
                                [&](Message& m, size_t a, size_t b) { AddRange(values, a, b, (m.*field)()); });
  };
  VISQ_RETURN_IF_ERROR(chunks(band.bits, band.first * words_per_column, &Message::mutable_bits));
  VISQ_RETURN_IF_ERROR(chunks(band.column_near, band.first, &Message::mutable_column_near));
  return chunks(band.column_far, band.first, &Message::mutable_column_far);
}

v1::VoxelizeResponse LastMessage(const core::VoxelizeAnswer& answer) {
  constexpr size_t kMaxAmbiguousListed = 10000;
  const voxel_reference::VoxelizeResult& result = answer.result;
  v1::VoxelizeResponse last;
  last.set_occupied_voxels(result.occupied_voxels);
  last.set_passes(result.passes);
  last.set_ambiguous_columns(result.ambiguous_columns);
  last.set_resolved_columns(result.resolved_columns);
  for (size_t i = 0; i < result.ambiguous_column_list.size() && i < kMaxAmbiguousListed; ++i)
    last.add_ambiguous_column_list(result.ambiguous_column_list[i]);
  const auto& stages = result.timings;
  auto& stage_ms = *last.mutable_stage_ms();
  stage_ms["setup"] = stages.setup_ms;
  stage_ms["depth"] = stages.depth_ms;
  stage_ms["voxelize"] = stages.voxelize_ms;
  stage_ms["readback"] = stages.readback_ms;
  stage_ms["resolve"] = stages.resolve_ms;
  return last;
}

std::string DescribeAnswer(const core::VoxelizeQuery& /*query*/, const core::VoxelizeAnswer& answer) {
  const voxel_reference::VoxelizeResult& result = answer.result;
  return absl::StrCat(result.grid.width, "x", result.grid.height, "x", result.grid.slices, " ",
                      core::RasterizationName(result.rasterization), ": ", result.occupied_voxels, " occupied voxels");
}

StatusOr<core::TransmittanceQuery> FromProto(const v1::TransmittanceRequest& request) {
  core::TransmittanceQuery query;
  VISQ_RETURN_IF_ERROR(SceneRefFromProto(request.scene(), query.scene, query.scene_version));
  voxel_reference::TransmittanceParams& p = query.params;
  switch (request.light_kind()) {
    case v1::TransmittanceRequest::POINT: p.light.kind = TransmittanceLightKind::kPoint; break;
    case v1::TransmittanceRequest::DIRECTIONAL: p.light.kind = TransmittanceLightKind::kDirectional; break;
    default: return absl::InvalidArgumentError("light_kind: unknown value");
  }
  p.light.position = FromProto(request.light_position());
  p.light.direction = FromProto(request.light_direction());
  for (const auto& a : request.absorbers()) query.absorbers.emplace_back(a.node(), a.absorption());
  if (query.absorbers.empty()) return absl::InvalidArgumentError("absorbers: empty");
  for (const auto& point : request.points()) p.points.push_back(FromProto(point));
  if (request.has_receiver()) {
    p.patch.origin = FromProto(request.receiver().origin());
    p.patch.u = FromProto(request.receiver().edge_u());
    p.patch.v = FromProto(request.receiver().edge_v());
    p.patch.nu = request.receiver_width();
    p.patch.nv = request.receiver_height();
    if (p.patch.nu == 0 || p.patch.nv == 0)
      return absl::InvalidArgumentError("receiver_width/receiver_height: must be set with receiver");
  }
  if (request.resolution() != 0) p.resolution = request.resolution();
  if (request.slices() != 0) p.slices = request.slices();
  if (!request.has_method()) {
    query.method = std::nullopt;  // the server's choice
  } else {
    switch (request.method()) {
      case v1::TransmittanceRequest::SLICEMAP: query.method = core::TransmittanceMethod::kSlicemap; break;
      case v1::TransmittanceRequest::RAY_STABBING: query.method = core::TransmittanceMethod::kRayStabbing; break;
      default: return absl::InvalidArgumentError(absl::StrCat("method: unknown value ", request.method()));
    }
  }
  return query;
}

void ToProto(const core::TransmittanceAnswer& answer, v1::TransmittanceResponse* out) {
  const voxel_reference::TransmittanceResult& result = answer.result;
  out->mutable_transmittance()->Add(result.transmittance.begin(), result.transmittance.end());
  out->mutable_optical_depth()->Add(result.optical_depth.begin(), result.optical_depth.end());
  out->mutable_optical_depth_error()->Add(result.optical_depth_error.begin(), result.optical_depth_error.end());
  out->mutable_lateral_offset()->Add(result.lateral_offset.begin(), result.lateral_offset.end());
  out->set_max_voxel_length(result.max_voxel_length);
  out->set_max_texel_size(result.max_texel_size);
  out->set_ambiguous_columns(result.ambiguous_columns);
  for (uint8_t a : result.ambiguous) out->add_ambiguous(a != 0);
  ToProto(core::TransmittanceStatement(answer), out->mutable_accuracy());
  if (answer.plan) ToProto(*answer.plan, out->mutable_accuracy());
}

StatusOr<core::ObscuranceQuery> FromProto(const v1::ComputeObscurancesRequest& request) {
  core::ObscuranceQuery query;
  query.scene = request.scene().name();
  query.scene_version = request.scene().version();
  query.resolution = request.resolution() != 0 ? request.resolution() : 256;
  query.force_built_atlas = request.force_built_atlas();
  query.params.d_max = request.d_max();
  query.params.color_bleeding = request.color_bleeding();
  query.params.seed = request.seed() != 0 ? request.seed() : 1;
  query.params.first_direction = request.first_direction();
  query.params.direction_count = request.direction_count() != 0 ? request.direction_count() : 256;
  query.params.bundle_resolution = request.bundle_resolution();
  query.total_directions = request.total_directions();
  query.partial_only = request.partial_only();
  query.want_averages = request.want_averages();
  query.want_errors = request.want_errors();
  query.update_rays_per_patch = request.update_rays_per_patch() != 0 ? request.update_rays_per_patch() : 64;
  switch (request.method()) {
    case v1::ComputeObscurancesRequest::METHOD_UNSPECIFIED:
      // Rays per patch name the ray-cast estimator; otherwise the server chooses.
      query.method = request.rays_per_patch() != 0 ? std::optional(core::ObscuranceMethod::kRaycast) : std::nullopt;
      break;
    case v1::ComputeObscurancesRequest::DEPTH_PEELING: query.method = core::ObscuranceMethod::kDepthPeeling; break;
    case v1::ComputeObscurancesRequest::RAYCAST: query.method = core::ObscuranceMethod::kRaycast; break;
    case v1::ComputeObscurancesRequest::GPU_RAYCAST: query.method = core::ObscuranceMethod::kGpuRaycast; break;
    default: return absl::InvalidArgumentError(absl::StrCat("method: unknown value ", request.method()));
  }
  if (request.rays_per_patch() != 0) query.rays_per_patch = request.rays_per_patch();
  if (request.has_target()) {
    if (request.direction_count() != 0)
      return absl::InvalidArgumentError("direction_count: give either a direction count or a target, not both");
    if (request.method() != v1::ComputeObscurancesRequest::METHOD_UNSPECIFIED || request.rays_per_patch() != 0)
      return absl::InvalidArgumentError("method, rays_per_patch: give either a method or a target, not both");
    VISQ_ASSIGN_OR_RETURN(query.target, service::FromProto(request.target()));
    return query;  // the core validates once the count is chosen
  }
  VISQ_RETURN_IF_ERROR(core::ValidateObscuranceQuery(query));
  return query;
}

namespace {

void AddVec3(const glm::vec3& v, google::protobuf::RepeatedField<float>* out) {
  out->Add(v.x);
  out->Add(v.y);
  out->Add(v.z);
}

}  // namespace

// Figures, then the arrays in the order the proto gives.
ChunkedResponses<v1::ComputeObscurancesResponse> ToProtoStream(core::ObscuranceAnswer answer, bool want_averages,
                                                               bool want_errors) {
  auto kept = std::make_shared<const core::ObscuranceAnswer>(std::move(answer));
  const core::ObscuranceAnswer& a = *kept;
  v1::ComputeObscurancesResponse figures;
  v1::ObscuranceFigures* f = figures.mutable_figures();
  f->set_scene_version(a.scene_version);
  f->mutable_atlas()->set_width(a.width);
  f->mutable_atlas()->set_height(a.height);
  f->mutable_atlas()->set_from_lightmap_uvs(a.from_lightmap_uvs);
  f->mutable_atlas()->set_chart_count(a.chart_count);
  f->mutable_atlas()->set_texels_per_unit(a.texels_per_unit);
  f->set_channels(a.partial.channels);
  f->set_fingerprint(a.partial.fingerprint);
  for (const obscurance::DirectionRange& r : a.partial.ranges) {
    auto* range = f->add_ranges();
    range->set_first(r.first);
    range->set_count(r.count);
  }
  f->set_total_directions(a.total_directions);
  f->set_partial_only(!a.result.has_value());
  ToProto(a.ambient.ambient_intensity, f->mutable_ambient_intensity());
  ToProto(a.ambient.r_ave, f->mutable_r_ave());
  f->set_ambient_clamped(a.ambient.clamped);
  f->set_layers(a.stats.layers);
  f->set_max_layers(a.stats.max_layers);
  f->set_truncated_directions(a.stats.truncated_directions);
  f->set_bundle_resolution(a.stats.bundle_resolution);
  f->set_update_ready(a.update_ready);
  const core::ObscuranceCoverage coverage = core::CoverageOf(a);
  f->set_estimated_texels(coverage.estimated_texels);
  f->set_mean_samples_per_patch(coverage.mean_samples_per_patch);
  service::ToProto(core::ObscuranceStatement(a), f->mutable_accuracy());
  if (a.plan) ToProto(*a.plan, f->mutable_accuracy());

  // The figures alone, then each array's chunks.
  ChunkedResponses<v1::ComputeObscurancesResponse> stream(std::move(figures), /*first_carries_chunk=*/false);
  stream.Keep(kept);
  using Message = v1::ComputeObscurancesResponse;
  if (!a.result) {
    stream.Add(a.partial.sums.size(), [&a](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(a.partial.sums, b, e, m.mutable_partial_sums());
    });
    stream.Add(a.partial.counts.size(), [&a](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(a.partial.counts, b, e, m.mutable_partial_counts());
    });
    return stream;
  }
  const obscurance::ObscuranceResult& r = *a.result;
  // Per-texel and per-triangle colors go as x, y, z floats (offsets count floats).
  auto add_vec3s = [&stream](const std::vector<glm::vec3>& values, auto field) {
    stream.Add(3 * values.size(), [&values, field](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddFlattenedRange(values, b, e, (m.*field)());
    });
  };
  add_vec3s(r.w, &Message::mutable_w);
  add_vec3s(r.intensity, &Message::mutable_intensity);
  stream.Add(r.estimated.size(), [&r](Message& m, size_t b, size_t e) {
    m.set_offset(b);
    m.set_estimated(std::string(reinterpret_cast<const char*>(r.estimated.data() + b), e - b));
  });
  if (want_averages) {
    add_vec3s(r.triangle_w, &Message::mutable_triangle_w);
    add_vec3s(r.vertex_w, &Message::mutable_vertex_w);
  }
  auto add_floats = [&stream](const std::vector<float>& values, auto field) {
    stream.Add(values.size(), [&values, field](Message& m, size_t b, size_t e) {
      m.set_offset(b);
      AddRange(values, b, e, (m.*field)());
    });
  };
  if (want_errors) {
    add_floats(a.bounds.texel, &Message::mutable_w_error);
    if (want_averages) {
      add_floats(a.bounds.triangle, &Message::mutable_triangle_w_error);
      add_floats(a.bounds.vertex, &Message::mutable_vertex_w_error);
    }
  }
  return stream;
}

void ToProto(const core::ObscuranceUpdateAnswer& a, v1::UpdateObscurancesResponse* out) {
  const obscurance::ObscuranceUpdate& u = a.update;
  out->set_from_version(a.from_version);
  out->set_scene_version(a.scene_version);
  out->set_moves_applied(a.moves_applied);
  out->mutable_texels()->Add(u.texels.begin(), u.texels.end());
  for (const glm::vec3& v : u.w) AddVec3(v, out->mutable_w());
  for (const glm::vec3& v : u.intensity) AddVec3(v, out->mutable_intensity());
  out->mutable_triangles()->Add(u.triangles.begin(), u.triangles.end());
  for (const glm::vec3& v : u.triangle_w) AddVec3(v, out->mutable_triangle_w());
  out->mutable_vertices()->Add(u.vertices.begin(), u.vertices.end());
  for (const glm::vec3& v : u.vertex_w) AddVec3(v, out->mutable_vertex_w());
  out->set_influenced_before(u.influenced_before);
  out->set_influenced_after(u.influenced_after);
  out->set_own_patches(u.own_patches);
  out->set_candidates(u.candidates);
  out->set_recomputed(u.recomputed);
  out->set_rays(u.rays);
  out->set_rays_per_patch(a.rays_per_patch);
  out->set_width(a.width);
  out->set_height(a.height);
  for (const glm::vec3& v : a.full_w) AddVec3(v, out->mutable_full_w());
  out->mutable_w_error()->Add(a.bounds.texel.begin(), a.bounds.texel.end());
  out->mutable_triangle_w_error()->Add(a.bounds.triangle.begin(), a.bounds.triangle.end());
  out->mutable_vertex_w_error()->Add(a.bounds.vertex.begin(), a.bounds.vertex.end());
  service::ToProto(core::ObscuranceUpdateStatement(a), out->mutable_accuracy());
}

core::NodeTransformQuery FromProto(const v1::SetNodeTransformRequest& request) {
  core::NodeTransformQuery query;
  query.scene = request.scene().name();
  query.scene_version = request.scene().version();
  if (request.node_case() == v1::SetNodeTransformRequest::kNodeName) query.node_name = request.node_name();
  if (request.node_case() == v1::SetNodeTransformRequest::kNodeIndex) query.node_index = request.node_index();
  query.world_matrix.assign(request.world_matrix().begin(), request.world_matrix().end());
  return query;
}

core::ObscuranceUpdateQuery FromProto(const v1::UpdateObscurancesRequest& request) {
  core::ObscuranceUpdateQuery query;
  query.scene = request.scene().name();
  query.scene_version = request.scene().version();
  query.want_full_w = request.want_full_w();
  return query;
}

}  // namespace visq::service
