// Writes bit patterns to an unsigned-integer target: with the OR logic op
// two draws must combine bitwise, which every bitmask algorithm relies on.
layout(location = 0) out uvec4 out_bits;
uniform uint u_pattern;
void main() { out_bits = uvec4(u_pattern, u_pattern << 1u, 1u, 0u); }
