// The methods a query can run, as the core names them: the server's choice
// among them (accuracy_planner.h) carries the one it chose in its plan.
#pragma once

#include <variant>

namespace visq::core {

// HiddenSampleMap and PatchVisibility: the paper's raster passes, Embree's
// rays, or the exact method (Mora et al.) on the source as an area light.
enum class VisibilityMethod { kRaster, kRaycast, kPluckerExact };

// The paper's GPU bake by depth peeling along bundles of parallel rays, or
// the same estimator traced per patch with Embree (lib/obscurance/
// obscurance_rays.h), which on a machine without a GPU is the cheaper one.
enum class ObscuranceMethod { kDepthPeeling, kRaycast };

// What a plan runs; monostate where its caller keeps that itself.
using PlanMethod = std::variant<std::monostate, VisibilityMethod, ObscuranceMethod>;

}  // namespace visq::core
