// Sizes units of GL work (a map's band of rows, a draw's piece of
// triangles) by their measured time, so that one GL job or one wait for
// the GPU lasts about a target: a call's stop and other calls' jobs get the
// GL thread between units, on a GPU as on a CPU rasterizer. GL thread or
// caller; no GL calls.
#pragma once

#include <algorithm>
#include <cstdint>
#include <utility>

namespace visq::gpu {

// Each unit doubles while it takes under half the target and halves while
// it takes over twice, unless halving did not make it cheaper by a quarter
// (a fixed cost per unit, such as a draw of the scene per pass, dominates):
// then the larger size stays.
class TimedSizer {
 public:
  TimedSizer(double target_ms, int limit, int start)
      : target_ms_(target_ms), limit_(std::max(limit, 1)), size_(std::clamp(start, 1, std::max(limit, 1))) {}
  int size() const { return size_; }
  // At the limit and measured under the target: nothing left to learn.
  bool settled() const { return target_ms_ <= 0.0 || (size_ >= limit_ && last_size_ > 0 && last_ms_ < target_ms_); }
  // The longest unit measured since the last call.
  double TakeLongestMs() { return std::exchange(longest_ms_, 0.0); }
  void Measured(int size, double ms) {
    longest_ms_ = std::max(longest_ms_, ms);
    if (target_ms_ <= 0.0) return;
    int next = size;
    if (last_size_ == 2 * size && ms > 0.75 * last_ms_) {
      next = last_size_;  // halving did not help: the fixed cost dominates
      floor_ = last_size_;
    } else if (ms < 0.5 * target_ms_) {
      next = size > limit_ / 2 ? limit_ : size * 2;
    } else if (ms > 2.0 * target_ms_ && size / 2 >= floor_) {
      next = size / 2;
    }
    last_size_ = size;
    last_ms_ = ms;
    size_ = std::clamp(next, std::max(1, floor_), limit_);
  }

 private:
  double target_ms_;
  int limit_;
  int size_;
  int floor_ = 1;
  int last_size_ = 0;
  double last_ms_ = 0.0;
  double longest_ms_ = 0.0;
};

// The first piece of a draw into `pixels` target pixels, before anything
// is measured: about 2^22 triangle-pixels (a few ms on llvmpipe for an
// ordinary scene, far less on a GPU), between 64 and 65,536 triangles and
// no more than the draw's `triangles`. The sizer doubles it from there.
inline int FirstPieceTriangles(uint64_t pixels, int triangles) {
  const uint64_t by_pixels = (uint64_t{1} << 22) / std::max<uint64_t>(pixels, 1);
  return int(std::min<uint64_t>(std::clamp<uint64_t>(by_pixels, 64, 65536), uint64_t(std::max(triangles, 1))));
}

}  // namespace visq::gpu
