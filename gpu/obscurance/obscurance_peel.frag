// Keeps only fragments behind the previous layer (the paper's peel test, on
// the exact depth the previous pass wrote, so a surface is never peeled
// twice) and writes (patch + 1, triangle * 2 + front-facing). Front-facing =
// the normal points towards the camera (the image basis has right x up =
// -view, so counter-clockwise in the window is towards the camera).
//
// Back-facing fragments are pushed kBackFacingDepthOffset further away. Two
// coincident surfaces of opposite facing (an object's base resting on the
// floor, a double-sided leaf made of two faces) otherwise peel in whichever
// order the rounding of their depths gives, pixel by pixel: half the time
// they face each other at distance 0, half the time they are back to back,
// and their W comes out near the mean of 0 and what lies beyond. With the
// offset the front-facing one always comes first, so they never see each
// other: the convention of the ray estimator (obscurance_rays.h), which
// skips a surface met closer than its t_min, and the one the update uses.
// 8e-6 of the view depth is 8e-6 of the scene's bounding diameter (0.08 mm
// in a 10 m scene): far above the depth rounding between coplanar
// triangles, far below any gap that geometry means.
const float kBackFacingDepthOffset = 8e-6;
in vec2 v_uv;
flat in uint v_triangle;
layout(binding = 0) uniform sampler2D u_previous_depth;
uniform int u_first;
uniform uvec2 u_atlas_size;
layout(location = 0) out uvec2 o_fragment;
void main() {
  const float depth = gl_FrontFacing ? gl_FragCoord.z : min(gl_FragCoord.z + kBackFacingDepthOffset, 1.0);
  if (u_first == 0 && depth <= texelFetch(u_previous_depth, ivec2(gl_FragCoord.xy), 0).r) discard;
  gl_FragDepth = depth;
  const uvec2 texel = uvec2(clamp(floor(v_uv), vec2(0.0), vec2(u_atlas_size - 1u)));
  o_fragment = uvec2(texel.y * u_atlas_size.x + texel.x + 1u, v_triangle * 2u + (gl_FrontFacing ? 1u : 0u));
}
