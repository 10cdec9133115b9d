// Per-receiver-texel offset of the source pattern (paper section 6.2). The
// paper's fract(a (sin(b y x) + c x)) is replaced by an integer hash so the
// CPU (DecorrelationOffset) reproduces every offset bit for bit.
uint HsmHash(uint h) {
  h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
  return h;
}
vec2 HsmDecorrelationOffset(uint seed, uint x, uint y, float amplitude) {
  uint h = HsmHash(x * 0x9E3779B1u ^ HsmHash(y * 0x85EBCA77u ^ seed));
  uint g = HsmHash(h ^ 0x68bc21ebu);
  const float kScale = 1.0 / 16777216.0;
  return vec2((float(h >> 8u) * kScale - 0.5) * amplitude, (float(g >> 8u) * kScale - 0.5) * amplitude);
}
