// Keeps only fragments behind the previous layer (the paper's peel test, on
// the exact depth the previous pass wrote, so a surface is never peeled
// twice) and writes (patch + 1, triangle * 2 + front-facing). Front-facing =
// the normal points towards the camera (the image basis has right x up =
// -view, so counter-clockwise in the window is towards the camera).
in vec2 v_uv;
flat in uint v_triangle;
layout(binding = 0) uniform sampler2D u_previous_depth;
uniform int u_first;
uniform uvec2 u_atlas_size;
layout(location = 0) out uvec2 o_fragment;
void main() {
  if (u_first == 0 && gl_FragCoord.z <= texelFetch(u_previous_depth, ivec2(gl_FragCoord.xy), 0).r) discard;
  const uvec2 texel = uvec2(clamp(floor(v_uv), vec2(0.0), vec2(u_atlas_size - 1u)));
  o_fragment = uvec2(texel.y * u_atlas_size.x + texel.x + 1u, v_triangle * 2u + (gl_FrontFacing ? 1u : 0u));
}
