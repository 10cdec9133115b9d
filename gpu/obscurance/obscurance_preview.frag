// Obscurance preview: the per-texel value (W or intensity) at the fragment's
// atlas position, filtered bilinearly (the atlas's gutters hold neighbour
// values for that); alpha 1 marks a covered pixel (the clear leaves 0).
in vec2 v_uv;
layout(binding = 0) uniform sampler2D u_values;  // RGB32F, atlas_width x atlas_height
uniform vec2 u_inv_atlas_size;
layout(location = 0) out vec4 o_color;
void main() {
  o_color = vec4(texture(u_values, v_uv * u_inv_atlas_size).rgb, 1.0);
}
