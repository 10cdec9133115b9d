// Seeded, portable randomness: splitmix64 (std's distributions differ
// between standard libraries, and sample patterns must be the same
// everywhere) and the radical inverse of the Halton sequences.
#pragma once

#include <cstdint>

namespace visq {

// splitmix64's output for the state x (Steele, Lea & Flood 2014).
inline uint64_t SplitMix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

// The top 53 bits as a double in [0, 1).
inline double UnitFromBits(uint64_t bits) { return static_cast<double>(bits >> 11) * 0x1.0p-53; }

// A generator: the sequence SplitMix64(seed), SplitMix64(seed + gamma), ...
struct SplitMix {
  uint64_t state;
  uint64_t Next() {
    const uint64_t out = SplitMix64(state);
    state += 0x9E3779B97F4A7C15ull;
    return out;
  }
  double Uniform() { return UnitFromBits(Next()); }
};

// The digits of i in `base`, mirrored about the point: the Halton sequence.
inline double RadicalInverse(uint32_t base, uint64_t i) {
  const double inv = 1.0 / base;
  double f = inv, r = 0;
  while (i > 0) {
    r += f * static_cast<double>(i % base);
    i /= base;
    f *= inv;
  }
  return r;
}

}  // namespace visq
