// The light's weight at a point of its shadow-map square, given in NDC
// (x, y in [-1, 1]): light texture (nearest) times, for spots, the cone.
// Outside the square: 0.
uniform ivec2 u_texture_size;  // (0, 0): no texture
uniform float u_tan_half;      // spot: tan of the cone's half-angle
uniform float u_cos_outer;     // spot: cos of the half-angle
uniform float u_cos_inner;     // spot: cos where the falloff starts (== outer: hard edge)
layout(std430, binding = 6) readonly buffer LightTexture { float light_texture[]; };

float LightWeight(vec2 ndc) {
  if (any(lessThan(ndc, vec2(-1.0))) || any(greaterThan(ndc, vec2(1.0)))) return 0.0;
  float w = 1.0;
  if (u_texture_size.x > 0) {
    ivec2 t = clamp(ivec2(floor((ndc * 0.5 + 0.5) * vec2(u_texture_size))), ivec2(0), u_texture_size - 1);
    w = light_texture[t.y * u_texture_size.x + t.x];
  }
#ifdef SPOT
  vec3 dir = normalize(vec3(ndc * u_tan_half, 1.0));
  if (u_cos_inner > u_cos_outer)
    w *= smoothstep(u_cos_outer, u_cos_inner, dir.z);
  else
    w *= dir.z >= u_cos_outer ? 1.0 : 0.0;
#endif
  return w;
}
