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

// Cell j of n cells of equal area that tile the unit square, for every n:
// round(sqrt n) rows along the second coordinate, row r holding
// floor((r + 1) n / rows) - floor(r n / rows) cells of equal width along the
// first, each row's height its count / n, row-major. The cells are near
// square (their sides differ by less than one cell in a row). One
// independent uniform point in each cell is a stratified sample: the
// mean of a bounded function over it is an unbiased estimate of the
// function's integral, and Hoeffding's inequality holds for it (independent,
// not identically distributed). A grid of ceil(sqrt n) columns filled row
// by row would leave the last row partly empty and its strip under-weighted.
struct EqualAreaCell {
  double x0 = 0, width = 1, y0 = 0, height = 1;
};
// The rows of EqualAreaCellOf's n cells: sqrt(n) rounded to the nearest
// integer; row r holds the cells [floor(r n / rows), floor((r + 1) n / rows)).
inline int64_t EqualAreaRowCount(int64_t n) {
  int64_t rows = 1;
  while ((rows + 1) * (rows + 1) <= n) ++rows;  // floor(sqrt n), exactly
  if (rows * rows + rows < n) ++rows;            // then rounded: n > rows^2 + rows means sqrt n > rows + 1/2
  return rows;
}
inline EqualAreaCell EqualAreaCellOf(int64_t n, int64_t j) {
  const int64_t rows = EqualAreaRowCount(n);
  // The row holding j: the last r with floor(r n / rows) <= j.
  int64_t row = j * rows / n;
  while (row + 1 < rows && (row + 1) * n / rows <= j) ++row;
  while (row > 0 && row * n / rows > j) --row;
  const int64_t first = row * n / rows, end = (row + 1) * n / rows;
  const auto cells = static_cast<double>(end - first);
  return {static_cast<double>(j - first) / cells, 1.0 / cells, static_cast<double>(first) / static_cast<double>(n),
          cells / static_cast<double>(n)};
}

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
