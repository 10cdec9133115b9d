// After each direction of the bake: adds the square of the direction's
// sample count of every patch and triangle to its running sum, and clears the
// count for the next direction. An estimate is a mean over directions
// weighted by these counts, so it rests on (sum of counts)^2 / (sum of
// squares) effective directions (Kish), fewer than the directions baked for
// anything small or seen mostly edge-on. One invocation per element: no
// atomics. Doubles hold the integer sums exactly below 2^53.
layout(local_size_x = 64) in;
layout(std430, binding = 5) buffer DirectionCounts { uint direction_counts[]; };
layout(std430, binding = 6) buffer CountSquares { double count_squares[]; };
uniform uint u_first_element;  // this dispatch's band: [u_first_element, u_end_element)
uniform uint u_end_element;
void main() {
  // Rows of groups: an 8192^2 atlas has more elements than one row holds.
  const uint i = u_first_element + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * 64u + gl_GlobalInvocationID.x;
  if (i >= u_end_element) return;
  const uint c = direction_counts[i];
  if (c == 0u) return;
  count_squares[i] += double(c) * double(c);
  direction_counts[i] = 0u;
}
