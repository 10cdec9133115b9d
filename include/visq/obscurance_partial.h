// Partial obscurance sums of a sharded bake, and their merge. Header-only and
// standard C++ only: the server bakes into these, and the client (in the
// source tree or installed) merges partials from several servers with
// exactly the arithmetic the server uses.
//
// Why integers: the GPU accumulates every transfer as a fixed-point integer
// (kObscuranceFixedPointScale per unit of value), so a sum does not depend on
// the order of the additions. A bake over directions [0, n) therefore equals,
// bit for bit, the merge of bakes over any split of [0, n) into ranges.
#pragma once

#include <algorithm>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace visq::obscurance {

// One unit of obscurance value is 2^20 in the fixed-point sums.
inline constexpr double kObscuranceFixedPointScale = 1048576.0;

struct DirectionRange {
  uint32_t first = 0;
  uint32_t count = 0;
};

struct ObscurancePartial {
  // Identifies what was baked: partials merge only when these agree.
  uint64_t fingerprint = 0;  // hash of scene, atlas and parameters
  uint32_t width = 0;        // atlas texels
  uint32_t height = 0;
  uint32_t channels = 1;     // 1 (eq. 2) or 3 (RGB, eq. 4 with color bleeding)
  // Direction ranges of the sequence that went into the sums, sorted, disjoint.
  std::vector<DirectionRange> ranges;
  // Per patch (texel y * width + x): `channels` fixed-point sums, then counts.
  std::vector<uint64_t> sums;    // size width * height * channels
  std::vector<uint64_t> counts;  // size width * height
  // Optional (empty when the baker did not gather them, and after a merge
  // with a partial that lacks them): the same sums and counts per triangle of
  // the scene, from the samples that fell on that triangle alone, so that a
  // triangle's W is not its texels' W (a texel larger than its triangles
  // mixes theirs); and per texel, then per triangle, the sum over directions
  // of the squared number of samples the direction gave it, from which the
  // effective number of directions behind an estimate follows. The squares
  // are integers held as doubles: exact below 2^53.
  std::vector<uint64_t> triangle_sums;    // triangles * channels
  std::vector<uint64_t> triangle_counts;  // triangles
  std::vector<double> count_squares;      // width * height + triangles

  uint64_t DirectionCount() const {
    uint64_t n = 0;
    for (const DirectionRange& r : ranges) n += r.count;
    return n;
  }
};

// Adds `from` into `into`. Fails (returns false and says why in *error) when
// the two were not baked with the same scene, atlas and parameters, or when
// their direction ranges overlap (a direction would be counted twice). An
// empty `into` (no ranges, no sums) takes `from` as it is.
inline bool MergeObscurancePartial(ObscurancePartial& into, const ObscurancePartial& from, std::string* error) {
  auto fail = [&](std::string message) {
    if (error != nullptr) *error = std::move(message);
    return false;
  };
  if (into.ranges.empty() && into.sums.empty() && into.counts.empty()) {
    into = from;
    return true;
  }
  if (into.fingerprint != from.fingerprint) return fail("partials differ in fingerprint (scene, atlas or parameters)");
  if (into.width != from.width || into.height != from.height || into.channels != from.channels)
    return fail("partials differ in atlas size or channels");
  if (into.sums.size() != from.sums.size() || into.counts.size() != from.counts.size() ||
      into.counts.size() != static_cast<size_t>(into.width) * into.height ||
      into.sums.size() != into.counts.size() * into.channels)
    return fail("partial sums have the wrong size");
  for (const DirectionRange& a : into.ranges)
    for (const DirectionRange& b : from.ranges)
      if (static_cast<uint64_t>(a.first) < static_cast<uint64_t>(b.first) + b.count &&
          static_cast<uint64_t>(b.first) < static_cast<uint64_t>(a.first) + a.count)
        return fail("direction ranges overlap: [" + std::to_string(a.first) + ", " +
                    std::to_string(a.first + a.count) + ") and [" + std::to_string(b.first) + ", " +
                    std::to_string(b.first + b.count) + ")");
  for (size_t i = 0; i < into.sums.size(); ++i) into.sums[i] += from.sums[i];
  for (size_t i = 0; i < into.counts.size(); ++i) into.counts[i] += from.counts[i];
  // The per-triangle parts merge when both partials have them; otherwise the
  // merge has none (W per triangle then falls back to its texels').
  if (!into.triangle_counts.empty() && into.triangle_counts.size() == from.triangle_counts.size() &&
      into.triangle_sums.size() == from.triangle_sums.size() && into.count_squares.size() == from.count_squares.size()) {
    for (size_t i = 0; i < into.triangle_sums.size(); ++i) into.triangle_sums[i] += from.triangle_sums[i];
    for (size_t i = 0; i < into.triangle_counts.size(); ++i) into.triangle_counts[i] += from.triangle_counts[i];
    for (size_t i = 0; i < into.count_squares.size(); ++i) into.count_squares[i] += from.count_squares[i];
  } else {
    into.triangle_sums.clear();
    into.triangle_counts.clear();
    into.count_squares.clear();
  }
  into.ranges.insert(into.ranges.end(), from.ranges.begin(), from.ranges.end());
  std::sort(into.ranges.begin(), into.ranges.end(),
            [](const DirectionRange& a, const DirectionRange& b) { return a.first < b.first; });
  // Adjacent ranges become one, so a complete merge reads [0, n).
  std::vector<DirectionRange> joined;
  for (const DirectionRange& r : into.ranges) {
    if (!joined.empty() && joined.back().first + joined.back().count == r.first)
      joined.back().count += r.count;
    else
      joined.push_back(r);
  }
  into.ranges = std::move(joined);
  return true;
}

}  // namespace visq::obscurance
