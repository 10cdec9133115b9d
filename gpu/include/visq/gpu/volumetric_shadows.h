// Volumetric shadows: single scattering in a homogeneous medium with epipolar
// rectification and 1D min-max mipmaps (Chen, Baran, Durand, Jarosz 2011,
// "Real-Time Volumetric Shadows using 1D Min-Max Mipmaps"; slides in
// ../shared/papers/volumetric-shadows-minmax-mipmaps.txt). GL-free and
// protobuf-free: the algorithm and its shaders live in gpu/volumetric_shadows/.
//
// What one call computes, per camera pixel (ray from the eye through the
// pixel center, up to the first surface the camera rasterizes):
//
//   L_in = integral over the lit parts of the ray, inside the medium, of
//          sigma_s * phase(cos) * E_light(x) * exp(-sigma_t * l(x))
//                  * exp(-sigma_t * (s - s_in)) ds
//
// where s is the distance from the eye, s_in where the ray enters the medium,
// l(x) the light's path length inside the medium to x, and "lit" is decided by
// the shadow map. The medium is a world box, VolumetricParams::medium_bounds
// (the scene's bounds unless given): s runs over the part of the ray inside
// it, and inside the light's shadow-map volume:
//   directional light: light enters the medium at the plane, across the
//     light, through the box's corner it reaches first (the near face of the
//     box around the medium in the light's frame, VolumetricResult::
//     medium_box), so l(x) = depth of x below that plane and E_light =
//     intensity (irradiance) * light texture. The shadow map covers that
//     frame box, deepened towards the light over the scene, so occluders
//     outside the medium still shadow it;
//   spot light: also inside the square frustum of the cone (near = 1e-3 of
//     the diagonal, far = beyond the farthest corner of the scene and the
//     medium); l(x) = |x - position| and E_light = intensity (radiant
//     intensity) * cone * texture / l^2.
// Outside the medium there is vacuum (no scattering, no attenuation). Geometry
// far from the medium costs only the shadow map's depth range: a medium box
// given with the request keeps the map's texels on the medium.
//
// The shadow map (the light's depth) is resampled into an epipolar
// rectified map: row = one epipolar slice (a direction from the epipole, the
// eye's projection in the shadow map), column = distance from the epipole.
// Every view ray lies in one slice (the nearest row is used), and its shadow
// test becomes a height-field test along that row: the ray's shadow-map
// depth is affine in the column. Rectified map: shadow_map_size rows x
// shadow_map_size columns (columns span [r_min, r_max], the distances from
// the epipole to the map square; over a full circle when the epipole lies
// inside the map).
//
// Two methods share the code path and the per-texel integral:
//   kMinMaxTraversal: a binary min-max tree over each row; nodes fully below
//     the ray are skipped (shadowed), nodes fully above are integrated over
//     their whole span at once, mixed nodes are refined.
//   kRayMarching: every texel of the row between the ray's ends is tested and
//     integrated in turn.
// They give the same image up to float summation order.
//
// Integrand per lit span (VolumetricResult::integrand says which was used):
//   kAnalytic: directional light without texture: closed form exp(-a s).
//   kPrefixSum: no attenuation (zero extinction or medium.optically_thin)
//     and either a directional light (any phase) or
//     an isotropic phase: the ray-dependent factor is constant along the row's
//     parameter (directional: ds per column; spot: the angle subtended at the
//     light, since ds / l^2 = dphi / h), so a lit span is a difference of
//     per-row prefix sums of the light weight (texture x cone, times the
//     texel's angle for spots), as in the slides.
//   kSvd: the slides' "SVD approximation" (after Baran et al. 2010) for a
//     spot light with extinction or a Henyey-Greenstein phase, and, when
//     asked for, a textured directional light with extinction
//     (gpu/volumetric_shadows/svd_integrand.h has the derivations). The
//     ray-dependent factor f (spot: f(alpha, phi) = phase x attenuation
//     beyond d = |eye - light|, alpha the view ray's angle from the eye's
//     direction to the light, phi the light ray's angle from the light's
//     direction to the eye; directional: f(alpha, p) = exp(-sigma_t p
//     cot(alpha / 2)), p the light ray's offset from the eye's) is tabulated
//     in double and truncated to the smallest rank K <= 8 whose largest
//     residual is below svd_tolerance x max f (else K = 8), and each row
//     keeps K prefix sums (in double) of w V_k dphi (or dp): a lit span
//     costs O(K). Texels cut by the ray's ends or by a shadow edge keep the
//     exact per-texel integral, and so do rays with alpha within
//     kSvdAlphaMargin of 0 or pi (where f's domain pinches) or entering the
//     medium where f < e^-2 (the table's absolute error would be amplified).
//     VolumetricResult reports K and the table's relative error
//     (integrand_error): the largest residual anywhere in the table, a
//     conservative figure (for a spot it sits where the domain pinches;
//     images differ from kPerTexel's by far less, see the tests). kPerTexel
//     also serves when the prefix sums (rows x (columns + 1) x K doubles)
//     exceed the driver's largest storage block (`integrand` says which):
//     on llvmpipe (128 MiB blocks) that is every map above 1024.
//   kPerTexel: the reference, and the default for a textured directional
//     light with extinction (on llvmpipe its per-texel exp beats the SVD's
//     K double reads per span; integrand_choice kSvd takes the SVD there):
//     lit spans are summed texel by texel (shadowed spans are still skipped
//     by the tree), each texel exact in its ds / l^2 factor (atan) with the
//     attenuation and phase at the texel's midpoint.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "volumetric_shadows/volumetric_request.h"
#include "visq/gpu/camera.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

// The requests and answers are lib/volumetric_shadows's
// (volumetric_request.h); this header is the GPU's entry points.
using volumetric_shadows::kMaxVolumetricShadowMapSize;
using volumetric_shadows::kMinVolumetricShadowMapSize;
using volumetric_shadows::kMaxVolumetricImageSize;
using volumetric_shadows::kMaxVolumetricLightTextureSize;
using volumetric_shadows::VolumetricCamera;
using volumetric_shadows::VolumetricLightKind;
using volumetric_shadows::VolumetricLight;
using volumetric_shadows::VolumetricMedium;
using volumetric_shadows::VolumetricMethod;
using volumetric_shadows::VolumetricIntegrand;
using volumetric_shadows::VolumetricIntegrandChoice;
using volumetric_shadows::kSvdAlphaMargin;
using volumetric_shadows::VolumetricParams;
using volumetric_shadows::VolumetricTimings;
using volumetric_shadows::VolumetricBox;
using volumetric_shadows::VolumetricResult;
using volumetric_shadows::VolumetricBand;
using volumetric_shadows::VolumetricBandSink;
using volumetric_shadows::VolumetricIntegrandName;

// Renders `params` over `gpu_scene` (the GPU copy of `scene`; `scene` gives
// the bounds and material colors). Without a sink the result holds the
// whole image; with one, each band goes to the sink and the result holds
// the figures only.
[[nodiscard]] StatusOr<VolumetricResult> RenderVolumetricShadows(GpuWorker& worker, const GpuScene& gpu_scene,
                                                                 const Scene& scene, const VolumetricParams& params,
                                                                 const VolumetricBandSink& sink = {});

// Checks params without touching the GPU: INVALID_ARGUMENT naming the field
// and value, RESOURCE_EXHAUSTED naming the cap.
[[nodiscard]] Status ValidateVolumetricParams(const VolumetricParams& params);

}  // namespace visq::gpu
