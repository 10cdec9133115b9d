// What the exact method (Mora et al. 2013, lib/exact) would cost one
// request, predicted from probes of that very request: the planner weighs
// it against the sampled methods by this figure (PlanVisibility).
//
// The method's cost per point follows the light and the penumbra's
// occluders (0.01 ms on a lit floor, 50-90 ms behind foliage), so a model
// fitted to other requests mispredicts the next by 1000x (Sponza x4, a copy
// at 1e5: predicted 1.6 ms, took 5,152 ms). The probes instead answer
// lattices of the request's own points on its own trees, so that what they
// build and store is the plan's (docs/default-method.md).
//
// The probing (PredictExactByProbes) and the arithmetic that turns what the
// probes measured into a time (SolveTreeAndPointMs, StoredPointAndCallMs,
// PredictedExactMs) are apart, so that the arithmetic can be checked on its
// own figures.
#pragma once

#include <utility>
#include <vector>

#include "common/status.h"
#include "core/accuracy_planner.h"
#include "core/call_options.h"
#include "core/light_visibility_query.h"

namespace visq::core {

class Engine;

// The exact method's batch for a request, and the receiver grid its points
// lie on (row-major), for the probes' lattices.
struct ExactBatch {
  LightVisibilityQuery batch;
  int width = 0, height = 0;
};

// The exact plan's predicted time, from probes of the request itself.
struct ExactPrediction {
  double ms = 0.0;
  WorkUnits units;       // the request's, after the probes (CostModel units)
  double probe_ms = 0.0;
  bool cut = false;      // a probe ran past its budget: `ms` extrapolates it
};

// The probes, all within `budget_ms` (and the call's deadline and
// cancellation), each a lattice over the receiver answered on the batch's
// own trees (answer_only):
// - every point already stored (a request after another over the same
//   points and light): two lattices of stored points, a few and many, give
//   a stored point's time and a call's fixed cost;
// - otherwise 1: 2 x 2 points, cold: mostly the trees they need; a first
//   probe past the budget extrapolates its trees (`cut`), which is enough
//   to route around the method;
// - 2: up to 8 x 8 other points (a shifted lattice) on the trees now held,
//   stopped at the budget: with the first, a tree's time and a point's;
// - 2b: a third lattice, where half the budget is left: the trees refine
//   lazily, so the latest rate is the one the rest of the batch will see;
// - 3: the first lattice again, from the stores, and every point answered
//   so far: a stored answer's time.
// The request is then predicted at its trees still to build, its points
// still to answer and its stored ones (PredictedExactMs).
[[nodiscard]] StatusOr<ExactPrediction> PredictExactByProbes(Engine& engine, const ExactBatch& exact,
                                                             double budget_ms, const CallOptions& call);

// ---------------------------------------------------------------------------
// The arithmetic.

// A probe's answered points and the milliseconds they took.
struct PointsAndMs {
  double points = 0.0;
  double ms = 0.0;
};

// A new tree's time and a new point's, from two probes that built `trees`
// and answered `points` new points each: ms = trees x tree_ms + points x
// point_ms solved for both. Where the two do not determine both parts, or a
// part comes out negative (noise), the second probe's time per point, and
// what the first leaves over per tree.
struct TreeAndPointMs {
  double tree_ms = 0.0;
  double point_ms = 0.0;
};
TreeAndPointMs SolveTreeAndPointMs(double trees1, double points1, double ms1, double trees2, double points2,
                                   double ms2);

// A stored point's time and a call's fixed cost, from two probes of stored
// points only, with `few`.points < `many`.points; a negative part is 0.
std::pair<double, double> StoredPointAndCallMs(PointsAndMs few, PointsAndMs many);

// What the probes measured, for the rest of the batch.
struct ExactRates {
  double tree_ms = 0.0;      // a tree still to build
  double point_ms = 0.0;     // a new point, as the probe that measured it ran
  double rate_groups = 1.0;  // that probe's groups: one worker each
  // Probes whose every answered point was stored (a look-up each).
  std::vector<PointsAndMs> stored_runs;
};

// The batch's time from `rates`, for what `left` says it still has to do,
// on `workers` workers:
// - its trees still to build;
// - its new points, at the probe's rate spread over the workers the batch's
//   chunks keep busy (RunLightVisibility, 64 points a chunk; a probe's few
//   points per group ran on one worker each);
// - its stored points: a look-up each and a call's fixed cost once, fitted
//   from stored runs of sizes at least 4x apart, else their time per point;
//   never below the cheapest stored run (a fit of two noisy runs can leave
//   next to nothing). Where no stored run was measured (the budget ran out
//   first), a stored point is taken at a new point's rate: the safe side,
//   and never free.
double PredictedExactMs(const ExactRates& rates, const LightVisibilityWork& left, double workers);

}  // namespace visq::core
