#include "core/exact_prediction.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>

#include <spdlog/spdlog.h>

#include "common/job_timing.h"
#include "common/parallel.h"
#include "core/engine.h"

namespace visq::core {
namespace {

constexpr int kFirstSide = 2, kLatticeSide = 8;

// About side x side texels of a width x height receiver, spread evenly
// over it (the texel under each cell centre of a side x side lattice; the
// whole receiver where it is smaller), as increasing indices.
// `quarter` places each texel at that many quarters of its lattice cell
// (2: the centre; 1 or 3: a lattice of as many other texels).
std::vector<uint32_t> LatticeTexels(int width, int height, int side, int quarter = 2) {
  const int columns = std::min(width, side), rows = std::min(height, side);
  std::vector<uint32_t> texels;
  texels.reserve(size_t(columns) * rows);
  for (int r = 0; r < rows; ++r)
    for (int c = 0; c < columns; ++c) {
      const auto x = static_cast<uint32_t>((4 * int64_t{c} + quarter) * width / (4 * columns));
      const auto y = static_cast<uint32_t>((4 * int64_t{r} + quarter) * height / (4 * rows));
      texels.push_back(y * uint32_t(width) + x);
    }
  return texels;  // rows and columns increase, so the indices do
}

// `texels` without those in the sorted `answered`.
std::vector<uint32_t> Without(std::vector<uint32_t> texels, const std::vector<uint32_t>& answered) {
  std::erase_if(texels, [&](uint32_t t) { return std::binary_search(answered.begin(), answered.end(), t); });
  return texels;
}

// One probe's figures.
struct ExactProbeRun {
  double ms = 0.0;
  double answered = 0.0;
  double new_trees = 0.0;    // trees it had to build (not held before)
  double built_trees = 0.0;  // of those, the ones it built (all, unless cut)
  double groups = 0.0;       // the batch's groups its points fall in
  double new_points = 0.0;   // points no held tree had stored
  bool cut = false;
};

// The probes of one request: each answers some of the batch's points on
// the batch's own trees, within the budget's deadline, and adds to what
// the probes cost and to the stored runs.
class ExactProber {
 public:
  ExactProber(Engine& engine, const ExactBatch& exact, double budget_ms, const CallOptions& call)
      : engine_(engine), exact_(exact), call_(call), probe_call_(call), budget_ms_(budget_ms) {
    if (std::isfinite(budget_ms))
      probe_call_.stop.deadline = std::min(
          call.stop.deadline, start_ + std::chrono::microseconds(static_cast<int64_t>(budget_ms * 1000.0)));
  }

  // `only` of the batch's points. A probe stopped by its budget (not by the
  // call) is `cut`, with what it measured so far. `all_stored`: the caller
  // knows every point is stored and no tree is to be built, and the probe
  // skips counting them (which costs as much as a call over stored points
  // on Sponza).
  StatusOr<ExactProbeRun> Run(std::vector<uint32_t> only, bool all_stored = false) {
    LightVisibilityQuery probe = exact_.batch;
    probe.answer_only = std::move(only);
    probe.call = probe_call_;
    std::atomic<size_t> answered{0};
    probe.answered = &answered;
    ExactProbeRun run;
    if (!all_stored) {
      VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork before, EstimateLightVisibilityWork(engine_, probe));
      run.new_trees = double(before.groups - before.cached_groups);
      run.groups = double(before.groups);
      run.new_points = before.points;
    }
    const auto start = std::chrono::steady_clock::now();
    StatusOr<LightVisibilityAnswer> answer = RunLightVisibility(engine_, probe);
    run.ms = MillisecondsSince(start);
    run.answered = double(answered.load());
    probe_ms_ += run.ms;
    if (answer.ok()) {
      run.ms = answer->compute_ms;  // as the plan's run is measured: without the index's build
      run.built_trees = run.new_trees;
      if (run.new_points == 0.0 && run.answered > 0.0) stored_runs_.push_back({run.answered, run.ms});
      return run;
    }
    if (call_.stop.Stopped() || !probe_call_.stop.Stopped()) return answer.status();
    // Stopped by its budget: the trees it built are the ones now held.
    run.cut = true;
    probe.call = call_;
    VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork after, EstimateLightVisibilityWork(engine_, probe));
    run.built_trees = std::max(0.0, run.new_trees - double(after.groups - after.cached_groups));
    return run;
  }

  // What the whole batch still has to do.
  StatusOr<LightVisibilityWork> Left() const { return EstimateLightVisibilityWork(engine_, exact_.batch); }

  // Whether less than `share` of the budget is spent.
  bool BudgetLeft(double share) const {
    return !std::isfinite(budget_ms_) || MillisecondsSince(start_) < share * budget_ms_;
  }

  // Whether the stored runs are of sizes at least 4x apart (enough to tell
  // a call's fixed cost from a point's).
  bool StoredSizesApart() const {
    double fewest = 0.0, most = 0.0;
    for (const PointsAndMs& run : stored_runs_) {
      fewest = fewest == 0.0 ? run.points : std::min(fewest, run.points);
      most = std::max(most, run.points);
    }
    return fewest > 0.0 && most >= 4.0 * fewest;
  }

  const ExactBatch& exact() const { return exact_; }
  const CallOptions& call() const { return call_; }
  double budget_ms() const { return budget_ms_; }
  double probe_ms() const { return probe_ms_; }
  const std::vector<PointsAndMs>& stored_runs() const { return stored_runs_; }

 private:
  Engine& engine_;
  const ExactBatch& exact_;
  const CallOptions& call_;
  CallOptions probe_call_;
  const double budget_ms_;
  const std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
  double probe_ms_ = 0.0;
  std::vector<PointsAndMs> stored_runs_;
};

const char* LogTag(const CallOptions& call) { return call.log_tag.empty() ? "[call]" : call.log_tag.c_str(); }

// Every point already stored: a look-up each, and the call's fixed cost
// once (about 1.8 ms on Sponza, 0.05 ms on the Cornell box), fitted from
// the first lattice and a 16 x 16 one. Probes over a few stored points
// charged the fixed cost to each (Sponza 0.97 ms a point where the batch
// takes 1 us), and the plan lost to sampled ones 17-69x slower. Nothing
// where a probe ran past the budget: the general probes follow.
StatusOr<std::optional<ExactPrediction>> PredictOverStoredPoints(ExactProber& prober) {
  const ExactBatch& exact = prober.exact();
  for (const int side : {kFirstSide, 2 * kLatticeSide}) {
    VISQ_ASSIGN_OR_RETURN(const ExactProbeRun run,
                          prober.Run(LatticeTexels(exact.width, exact.height, side), /*all_stored=*/true));
    if (run.cut) return std::nullopt;
  }
  const std::vector<PointsAndMs>& runs = prober.stored_runs();
  if (runs.size() != 2 || !(runs[1].points > runs[0].points) || !(runs[0].points > 0.0)) return std::nullopt;
  ExactRates rates;
  rates.stored_runs = runs;
  VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork left, prober.Left());
  ExactPrediction out;
  out.units = {left.new_shaft_triangles, left.points};
  out.ms = PredictedExactMs(rates, left, double(ParallelWorkers()));
  out.probe_ms = prober.probe_ms();
  spdlog::debug("{} exact probes (budget {:.1f} ms): every point stored; {:.3f} ms for {} points, {:.3f} ms for {}: "
                "predicted {:.3f} ms",
                LogTag(prober.call()), prober.budget_ms(), runs[0].ms, runs[0].points, runs[1].ms, runs[1].points,
                out.ms);
  return out;
}

// The first probe ran past its budget (a share kProbeShareOfBest of the
// best other plan) on its trees alone: the method is not known to be
// faster than that plan, so it is predicted at least at that plan's time
// (which the other plan then wins), and at least what its trees cost per
// tree. A lower side: routing around the method needs no more (veach-ajar,
// one tree for a 32 x 32 floor: cut at 55 ms, the plan then takes
// 0.5-0.9 s).
double PredictFromCutFirstProbe(const ExactProbeRun& first, const LightVisibilityWork& left, double budget_ms) {
  double ms = first.ms * std::max(1.0, double(left.groups - left.cached_groups) / std::max(1.0, first.new_trees));
  if (std::isfinite(budget_ms)) ms = std::max(ms, budget_ms / kProbeShareOfBest);
  return ms;
}

}  // namespace

TreeAndPointMs SolveTreeAndPointMs(double trees1, double points1, double ms1, double trees2, double points2,
                                   double ms2) {
  const double b1 = std::max(1.0, points1), b2 = std::max(1.0, points2);
  const double det = trees1 * b2 - trees2 * b1;
  TreeAndPointMs out;
  if (std::abs(det) > 1e-9) {
    out.tree_ms = (ms1 * b2 - ms2 * b1) / det;
    out.point_ms = (trees1 * ms2 - trees2 * ms1) / det;
    if (out.tree_ms >= 0.0 && out.point_ms >= 0.0) return out;
  }
  out.point_ms = ms2 / b2;
  out.tree_ms = trees1 > 0.0 ? std::max(0.0, ms1 - out.point_ms * b1) / trees1 : 0.0;
  return out;
}

std::pair<double, double> StoredPointAndCallMs(PointsAndMs few, PointsAndMs many) {
  const double per_point = std::max(0.0, (many.ms - few.ms) / (many.points - few.points));
  return {per_point, std::max(0.0, few.ms - per_point * few.points)};
}

double PredictedExactMs(const ExactRates& rates, const LightVisibilityWork& left, double workers) {
  const double batch_chunks = std::max(double(left.groups), std::ceil(left.points / 64.0));
  const double point_ms = rates.point_ms * std::min(workers, std::max(1.0, rates.rate_groups)) /
                          std::min(workers, std::max(1.0, batch_chunks));
  double ms = double(left.groups - left.cached_groups) * rates.tree_ms + left.points * point_ms;
  if (left.stored_points <= 0.0) return ms;
  if (rates.stored_runs.empty()) return ms + left.stored_points * point_ms;
  const auto [fewest, most] = std::minmax_element(
      rates.stored_runs.begin(), rates.stored_runs.end(),
      [](const PointsAndMs& a, const PointsAndMs& b) { return a.points < b.points; });
  double stored_ms = most->ms / std::max(1.0, most->points), call_ms = 0.0;
  if (fewest->points > 0.0 && most->points >= 4.0 * fewest->points)
    std::tie(stored_ms, call_ms) = StoredPointAndCallMs(*fewest, *most);
  // A look-up is never dearer than answering the point afresh; where no new
  // point was measured (every point stored), the look-ups' own rate.
  if (rates.point_ms > 0.0) stored_ms = std::min(stored_ms, point_ms);
  ms += left.stored_points * stored_ms + call_ms;
  const double cheapest_stored_run =
      std::min_element(rates.stored_runs.begin(), rates.stored_runs.end(), [](const PointsAndMs& a,
                                                                             const PointsAndMs& b) {
        return a.ms < b.ms;
      })->ms;
  return std::max(ms, cheapest_stored_run);
}

StatusOr<ExactPrediction> PredictExactByProbes(Engine& engine, const ExactBatch& exact, double budget_ms,
                                               const CallOptions& call) {
  // The scene's triangle index (built once per scene, outside compute_ms)
  // is fetched before the probes' clock starts.
  VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork before, EstimateLightVisibilityWork(engine, exact.batch));
  ExactProber prober(engine, exact, budget_ms, call);
  if (before.points == 0.0 && before.groups == before.cached_groups && before.stored_points > 0.0) {
    VISQ_ASSIGN_OR_RETURN(std::optional<ExactPrediction> stored, PredictOverStoredPoints(prober));
    if (stored) return *std::move(stored);
  }
  ExactPrediction out;

  // 1: cold, a few points: mostly the trees they need.
  const std::vector<uint32_t> first = LatticeTexels(exact.width, exact.height, kFirstSide);
  VISQ_ASSIGN_OR_RETURN(const ExactProbeRun one, prober.Run(first));
  if (one.cut) {
    VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork left, prober.Left());
    out.cut = true;
    out.units = {left.new_shaft_triangles, left.points};
    out.ms = PredictFromCutFirstProbe(one, left, budget_ms);
    out.probe_ms = prober.probe_ms();
    spdlog::debug("{} exact probes: the first cut at {:.1f} ms (budget {:.1f} ms) for {} trees and {} points; left "
                  "{} of {} trees: predicted {:.1f} ms",
                  LogTag(call), one.ms, budget_ms, one.new_trees, one.new_points, left.groups - left.cached_groups,
                  left.groups, out.ms);
    return out;
  }

  // 2: other points on the trees now held, until the budget: with the
  // first, a tree's time and a point's (a cut probe counts the points it
  // answered).
  ExactRates rates;
  rates.point_ms = one.ms / std::max(1.0, double(first.size()));
  rates.rate_groups = one.groups;
  const std::vector<uint32_t> second = Without(LatticeTexels(exact.width, exact.height, kLatticeSide, 1), first);
  ExactProbeRun two;
  if (!second.empty()) {
    VISQ_ASSIGN_OR_RETURN(two, prober.Run(second));
    out.cut = two.cut;
    const TreeAndPointMs solved = SolveTreeAndPointMs(one.new_trees, one.new_points, one.ms, two.built_trees,
                                                      two.cut ? two.answered : two.new_points, two.ms);
    rates.tree_ms = solved.tree_ms;
    rates.point_ms = solved.point_ms;
    rates.rate_groups = two.groups;
  }
  const double second_points = two.cut ? two.answered : two.new_points;

  // 2b: a third lattice on the trees as the second left them, while at
  // least half the budget is left. The trees refine lazily, so a point
  // answered later costs less (the bunny: 2-4x less than the second
  // lattice's): the rate the rest of the batch will see is the latest one.
  std::vector<uint32_t> answered_so_far = first;
  answered_so_far.insert(answered_so_far.end(), second.begin(), second.end());
  std::sort(answered_so_far.begin(), answered_so_far.end());
  if (!out.cut && rates.point_ms > 0.0 && prober.BudgetLeft(0.5)) {
    const std::vector<uint32_t> third =
        Without(LatticeTexels(exact.width, exact.height, kLatticeSide, 3), answered_so_far);
    if (!third.empty()) {
      VISQ_ASSIGN_OR_RETURN(const ExactProbeRun later, prober.Run(third));
      const double points = later.cut ? later.answered : later.new_points;
      // Only a lattice that built no tree and answered enough points to
      // average over the penumbra's heavy tail.
      if (later.built_trees == 0.0 && points >= 16.0 && later.ms / points < rates.point_ms) {
        rates.point_ms = later.ms / points;
        rates.rate_groups = later.groups;
      }
      answered_so_far.insert(answered_so_far.end(), third.begin(), third.end());
      std::sort(answered_so_far.begin(), answered_so_far.end());
    }
  }

  // 3: stored answers, from two probes of stored points only, a few and
  // many: the probes above where every point they answered was stored, else
  // the first lattice again and every point answered so far. From the
  // first lattice alone the rate was 30-40x the batch's, and the plan lost
  // to sampled ones 17-69x slower.
  if (!prober.StoredSizesApart() && prober.BudgetLeft(0.75)) {
    VISQ_ASSIGN_OR_RETURN(const ExactProbeRun again, prober.Run(first));
    answered_so_far.erase(std::unique(answered_so_far.begin(), answered_so_far.end()), answered_so_far.end());
    if (!again.cut && answered_so_far.size() >= 4 * first.size() && prober.BudgetLeft(0.85))
      VISQ_RETURN_IF_ERROR(prober.Run(answered_so_far).status());
  }
  rates.stored_runs = prober.stored_runs();

  VISQ_ASSIGN_OR_RETURN(const LightVisibilityWork left, prober.Left());
  out.units = {left.new_shaft_triangles, left.points};
  out.ms = PredictedExactMs(rates, left, double(ParallelWorkers()));
  // A second lattice cut after a few points measured the first points a
  // barely refined tree answers, which cost several times the batch's
  // average (the bunny: 23 ms against 2 ms): an upper side. The lower side
  // is that the method is not known to be faster than the best sampled
  // plan (the budget over its share). Their geometric mean is within the
  // square root of their ratio of any time between them.
  if (out.cut && second_points < 16.0 && std::isfinite(budget_ms)) {
    const double lower = budget_ms / kProbeShareOfBest;
    if (out.ms > lower) out.ms = std::sqrt(out.ms * lower);
  }
  out.probe_ms = prober.probe_ms();
  spdlog::debug("{} exact probes (budget {:.1f} ms): {:.1f} ms for {} trees and {} points, {:.1f} ms for {} trees and "
                "{} points{}; a tree {:.2f} ms, a point {:.3f} ms, {} stored runs; left {} of {} trees, {} points, {} "
                "stored: predicted {:.1f} ms",
                LogTag(call), budget_ms, one.ms, one.new_trees, one.new_points, two.ms, two.built_trees,
                second_points, out.cut ? " (cut)" : "", rates.tree_ms, rates.point_ms, rates.stored_runs.size(),
                left.groups - left.cached_groups, left.groups, left.points, left.stored_points, out.ms);
  return out;
}

}  // namespace visq::core
