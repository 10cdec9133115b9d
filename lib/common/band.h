// A band: the part of a large answer (rows of a map, of an image, of a
// voxel grid) made at once and handed on as soon as it is made, so the
// whole answer is never held. Every algorithm that streams its answer
// speaks this one vocabulary: its band type derives from BandPlace, and its
// work takes a BandSink.
#pragma once

#include <chrono>
#include <cstddef>
#include <functional>

#include "common/job_timing.h"
#include "common/status.h"

namespace visq {

// Where a band sits in its whole answer: the index of its first element,
// counted in the answer's own unit (a map's texels, an image's pixels, a
// grid's columns). The band's arrays are laid out from there as the whole
// answer's are.
struct BandPlace {
  size_t first = 0;
  // The answer's first band: where a stream sends the figures before it.
  bool opens_answer() const { return first == 0; }
};

// Receives each band in order, with the answer's figures (sizes, modes,
// counts so far) known before its first band. A status other than OK stops
// the work there and is what the work returns.
template <typename Figures, typename Band>
using BandSink = std::function<Status(const Figures& figures, const Band& band)>;

// `sink`, counting into `*delivery_ms` the time its deliveries take: that
// is the reader's pace (a stream's writes), which a work's own timing
// leaves out. Empty where `sink` is.
template <typename Figures, typename Band>
BandSink<Figures, Band> TimedBandSink(const BandSink<Figures, Band>& sink, double* delivery_ms) {
  if (!sink) return {};
  return [&sink, delivery_ms](const Figures& figures, const Band& band) -> Status {
    const auto start = std::chrono::steady_clock::now();
    Status delivered = sink(figures, band);
    *delivery_ms += MillisecondsSince(start);
    return delivered;
  };
}

}  // namespace visq
