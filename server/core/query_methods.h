// The methods a query can run, as the core names them: the server's choice
// among them (accuracy_planner.h) carries the one it chose in its plan.
#pragma once

#include <optional>
#include <variant>

namespace visq::core {

// HiddenSampleMap and PatchVisibility: the paper's raster passes, Embree's
// rays, the exact method (Mora et al.) on the source as an area light, or
// the same rays as Embree's traced on the GPU (gpu/rays).
enum class VisibilityMethod { kRaster, kRaycast, kPluckerExact, kGpuRaycast };

// The paper's GPU bake by depth peeling along bundles of parallel rays, or
// the same estimator traced per patch with Embree (lib/obscurance/
// obscurance_rays.h), which on a machine without a GPU is the cheaper one,
// or that estimator's rays traced on the GPU (gpu/rays).
enum class ObscuranceMethod { kDepthPeeling, kRaycast, kGpuRaycast };

// Whether the method is the per-patch ray estimator (on either tracer); a
// method not chosen yet is not.
constexpr bool IsRayEstimate(ObscuranceMethod method) {
  return method == ObscuranceMethod::kRaycast || method == ObscuranceMethod::kGpuRaycast;
}
constexpr bool IsRayEstimate(const std::optional<ObscuranceMethod>& method) {
  return method.has_value() && IsRayEstimate(*method);
}

// Transmittance: the paper's transmittance shadow map on the GPU, answering
// for the ray through the centre of each point's light-view texel, or each
// point's own ray on the CPU (voxel_reference::TransmittanceByRays).
enum class TransmittanceMethod { kSlicemap, kRayStabbing };

// What a plan runs; monostate where its caller keeps that itself.
using PlanMethod = std::variant<std::monostate, VisibilityMethod, ObscuranceMethod, TransmittanceMethod>;

}  // namespace visq::core
