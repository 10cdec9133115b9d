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
// in a 10 m scene): far above the float rounding between coplanar
// triangles, far below any gap that geometry means. A slope term is added
// because hardware rasterizers snap vertices to a sub-pixel grid (1/256 of a
// pixel on NVIDIA) before they set up each triangle's depth plane: two
// coplanar triangles seen at a grazing angle then differ in depth by their
// slope times the snap, which the constant alone does not cover (with the
// constant alone, an H200 baked a pot's base resting on the floor 0.21
// darker than the rays; llvmpipe's rounding stays below the constant). A
// sixteenth of a pixel's depth change is 16x that snap, and a gap a
// sixteenth of a pixel deep is one the bundle cannot resolve anyway.
const float kBackFacingDepthOffset = 8e-6;
const float kBackFacingSlopePixels = 1.0 / 16.0;
//
// The sample's patch is the texel of its atlas coordinates, pulled onto the
// triangle's own atlas triangle first: the interpolated coordinates of a
// pixel the rasterizer counts inside the triangle can fall a hair outside
// it, and at a chart's edge such a sample would land in the gutter, lost to
// the texel whose surface it lies on (rare: a few texels per bake).
in vec2 v_uv;
flat in uint v_triangle;
layout(std430, binding = 0) readonly buffer CornerUv { vec2 corner_uv[]; };  // texels, per corner
layout(binding = 0) uniform sampler2D u_previous_depth;
uniform int u_first;
uniform uvec2 u_atlas_size;
layout(location = 0) out uvec2 o_fragment;
void main() {
  const float slope = fwidth(gl_FragCoord.z);
  const float depth = gl_FrontFacing
                          ? gl_FragCoord.z
                          : min(gl_FragCoord.z + kBackFacingDepthOffset + kBackFacingSlopePixels * slope, 1.0);
  if (u_first == 0 && depth <= texelFetch(u_previous_depth, ivec2(gl_FragCoord.xy), 0).r) discard;
  gl_FragDepth = depth;
  const vec2 a = corner_uv[3u * v_triangle], b = corner_uv[3u * v_triangle + 1u], c = corner_uv[3u * v_triangle + 2u];
  vec2 uv = v_uv;
  const float area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
  if (abs(area) > 1e-12) {
    // Barycentrics of uv; a negative one moves it onto the triangle, then a
    // hair towards the centroid so that an edge on a texel line stays in.
    vec3 l = vec3((b.x - uv.x) * (c.y - uv.y) - (b.y - uv.y) * (c.x - uv.x),
                  (c.x - uv.x) * (a.y - uv.y) - (c.y - uv.y) * (a.x - uv.x),
                  (a.x - uv.x) * (b.y - uv.y) - (a.y - uv.y) * (b.x - uv.x)) / area;
    if (min(l.x, min(l.y, l.z)) < 0.0) {
      l = max(l, vec3(0.0));
      l /= l.x + l.y + l.z;
      l = mix(l, vec3(1.0 / 3.0), 1e-4);
      uv = l.x * a + l.y * b + l.z * c;
    }
  }
  const uvec2 texel = uvec2(clamp(floor(uv), vec2(0.0), vec2(u_atlas_size - 1u)));
  o_fragment = uvec2(texel.y * u_atlas_size.x + texel.x + 1u, v_triangle * 2u + (gl_FrontFacing ? 1u : 0u));
}
