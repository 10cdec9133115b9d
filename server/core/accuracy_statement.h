// What an answer says about its own accuracy: the method that made it, the
// bound (or why there is none), the confidence, and how the bound was
// derived. Each statement is written beside the algorithm whose bound it
// is (the sampled-visibility statement in visibility_sampling_query.cpp,
// the slicemap's in voxel_query.cpp, ...), because "error_bound is the
// voxel's diagonal" is a fact about the slicemap, not about protobuf. The
// transport copies a statement into its message field by field and adds
// nothing.
#pragma once

#include <map>
#include <string>

namespace visq::core {

struct PlanReport;

struct AccuracyStatement {
  std::string method;
  // Absolute, on the answered quantity; negative: no numeric bound, and the
  // note says why.
  double error_bound = -1.0;
  double confidence = 0.0;  // 1 for a worst-case bound, 0 with no bound
  std::string note;
  // Beside the bound, where the answer can estimate its own variance: the
  // normal approximation's half-width at `confidence`, the largest
  // element's. An estimate, not a bound (its coverage is measured, not
  // promised); negative where the answer has none.
  double estimate = -1.0;
  // What produced the answer: samples, directions, hough_resolution, ...
  std::map<std::string, double> parameters;
  // With an accuracy target: the chosen plan's predicted cost.
  double predicted_ms = 0.0;
};

// Exact methods: a worst-case bound of 0 up to the stated floating-point
// sums.
AccuracyStatement ExactStatement(std::string method, std::string note);

// A target's chosen plan: its parameters and predicted cost join the
// statement, and the note says how it was chosen.
void AddChosenPlan(const PlanReport& plan, AccuracyStatement& statement);

}  // namespace visq::core
