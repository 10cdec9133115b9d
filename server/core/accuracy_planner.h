// Ask by error: a caller states the accuracy it needs, or the time
// it can spend, instead of a sample count, and visq picks the method and its
// parameters. Each query kind lists its candidate plans with the error bound
// each could state (from the method's own error model: Hoeffding for sampled
// visibility and obscurances, 0 for the exact Plücker method) and the time
// each would take, predicted by a CostModel fitted to the requests this
// server has actually run on this machine and this scene. Nothing here is a
// constant tuned on one machine: a scene and method with no measurement yet
// is probed (a small run of the same query) before it is predicted.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "common/status.h"
#include "core/call_options.h"
#include "core/query_methods.h"

namespace visq::core {

struct AccuracyTarget {
  double max_error = 0.0;    // half-width on the answered quantity; 0: none
  double confidence = 0.95;  // (0, 1]; 1: a worst-case bound
  double time_budget_ms = 0.0;  // 0: none
  // What max_error is on: the stated bound, or the estimate beside it (the
  // normal approximation at the answer's own variance). kDefault is the
  // bound where the query kind states one.
  enum class Guarantee { kDefault, kRigorous, kEstimate };
  Guarantee guarantee = Guarantee::kDefault;
  bool wants_estimate() const { return guarantee == Guarantee::kEstimate; }
};

// INVALID_ARGUMENT naming "target.<field>" for a bad target.
[[nodiscard]] Status ValidateAccuracyTarget(const AccuracyTarget& target);

// Work in a method's units for the cost model (CostModel: a second unit
// where the method's cost has two parts that grow apart).
struct WorkUnits {
  double work = 0.0;
  double extra = 0.0;
};

// One candidate: a method with its parameters, what it could promise and
// what it would cost.
struct Plan {
  std::string method;  // its name in answers, logs and cost-model series
  PlanMethod runs;     // what the query runs for it
  std::map<std::string, double> parameters;
  double error_bound = 0.0;  // at the target's confidence; 0 for exact methods
  double work = 0.0;         // the cost model's unit for this method
  double extra_work = 0.0;   // its second unit, for methods whose cost has two (CostModel)
  std::string cost_key;      // the cost model's series for this method
  double predicted_ms = 0.0;
  bool meets_target = false;
};

// What the planner weighed and chose, for the response.
struct PlanReport {
  std::vector<Plan> plans;
  size_t chosen = 0;
  double probe_ms = 0.0;  // spent measuring methods not seen before on this scene
  // Why these plans: an AccuracyTarget's, or the server's own choice among
  // methods giving the same answer for a request that named none.
  enum class Reason { kTarget, kFastestOfEqualAnswers };
  Reason reason = Reason::kTarget;
  // kTarget: the target the plans were weighed for, so that the answer can
  // say whether it met it (a prediction can miss).
  std::optional<AccuracyTarget> target;
  // Methods left out because their probe ran past its share of the best
  // plan's time (ChooseFastest), by name.
  std::vector<std::string> cut_probes;
  // Methods whose probe this request's share could not pay for, left to
  // the server's idle time (IdleExplorer), by name.
  std::vector<std::string> left_to_idle_time;
  const Plan& chosen_plan() const { return plans[chosen]; }
};

// A call says what it will run before it starts: the chosen plan, its
// predicted time and the plans weighed, on the server's log under the
// call's tag (info when predicted at a second or more, else debug).
void LogChosenPlan(const PlanReport& report, const CallOptions& call);

// A cost-model file larger than this is not the model's own (4096 series
// of 16 observations are a few MiB): it is left unread.
inline constexpr uintmax_t kMaxCostModelFileBytes = uintmax_t{64} << 20;

// ms = fixed + rate * work per series (a scene, a query kind and a method),
// least-squares over the most recent observations, so it follows the
// machine's load and the scene's caches (the exact method's tree gets
// cheaper as it grows). Thread-safe.
//
// A series may have a second unit of work (`extra`): ms = fixed + rate *
// work + extra_rate * extra, every coefficient at least 0. A method whose
// cost has two parts that grow apart needs it: the GL passes of a map
// (per sample) and its fragments (per texel and sample), or the exact
// method's new trees (the triangles their shafts meet) and its points. With
// one unit, a small probe extrapolates one part by the other's growth.
//
// With a file (PersistTo), the observations outlive the process: a restart
// predicts from what the last one measured instead of probing every scene
// and method again. The series name the scene's content hash, so a file
// left by another scene of the same name predicts nothing.
class CostModel {
 public:
  static constexpr size_t kSeriesKept = 4096;  // bounds the file a hostile series name could grow
  void Record(const std::string& series, double work, double ms, double extra = 0.0);
  // Nothing until the series has an observation.
  std::optional<double> Predict(const std::string& series, double work, double extra = 0.0) const;
  // How many observations the series holds.
  size_t Observations(const std::string& series) const;
  // How many different amounts of work (work and extra) they were made at:
  // one size cannot tell a fixed cost from a rate, nor one unit's rate
  // from the other's.
  size_t DistinctSizes(const std::string& series) const;
  // The most work (first unit) an observation of the series was made at; 0
  // before one.
  double LargestWork(const std::string& series) const;

  // Reads the observations `path` holds (none when it is absent; malformed
  // lines are skipped) and rewrites it, whole and atomically, after every
  // Record. An unreadable or unwritable file costs the persistence only.
  void PersistTo(const std::filesystem::path& path);

  // A probe stopped at its budget (ChooseFastest) says only that the method
  // costs more than the budget on that probe: no observation is kept, and
  // the series is probed again only with a budget several times larger, so
  // a method that is slow here costs each request at most a share of it.
  // The first cut of a series is not held against it: the first probe of a
  // method pays its one-time costs (GL programs compiled, the scene's
  // buffers uploaded), so only a second cut backs off.
  void RecordCutProbe(const std::string& series, double budget_ms);
  // The largest budget a probe of the series was cut at, from its second
  // cut on; 0 before.
  double CutProbeBudget(const std::string& series) const;
  // How many of the series' probes were cut.
  int CutProbes(const std::string& series) const;
  // Exploration credit: each request that leaves an unmeasured method out
  // (its budget too small to learn it) adds that budget to the method's
  // credit, and its next probe may spend the sum; so requests too small to
  // probe on still pay for a method's probe together, at the same share.
  void AddExplorationCredit(const std::string& series, double ms);
  // The credit, which the caller then spends (it is reset).
  double TakeExplorationCredit(const std::string& series);
  double ExplorationCredit(const std::string& series) const;

  // Whether this is the first probe of the series' kind and method (the
  // series name after its scene) at this amount of `extra` work in this
  // process, marking it probed: such a run pays the method's one-time
  // costs (GL programs compiled; a raster map's tables for its sample
  // count: 259 ms for a 4 x 4 Cornell map at 1,024 samples, 3.4 ms the
  // next time).
  bool FirstProbeOfMethod(const std::string& series, double extra);

  struct Observation {
    double work = 0.0;
    double ms = 0.0;
    double extra = 0.0;
  };

 private:
  static constexpr size_t kObservationsKept = 16;
  void SaveLocked() const;
  // Past kSeriesKept series, the one least recently recorded or predicted
  // goes: never one a plan has just probed and is about to predict (the
  // first by name could be, and a plan with no prediction was weighed as
  // free).
  void EvictLeastRecentlyUsedLocked();
  mutable std::mutex mutex_;
  std::map<std::string, std::deque<Observation>> series_;
  mutable std::map<std::string, uint64_t, std::less<>> used_at_;  // each series' last use, by uses_
  mutable uint64_t uses_ = 0;
  struct CutProbe {
    double budget_ms = 0.0;
    int count = 0;
  };
  std::map<std::string, CutProbe> cut_probes_;
  std::map<std::string, double> exploration_credit_;
  std::set<std::pair<std::string, double>> methods_probed_;
  std::filesystem::path file_;
};

// The cost model's series name: "<scene>/<kind>/<method>".
std::string CostSeries(const std::string& scene, const std::string& kind, const std::string& method);

// Samples a Hoeffding bound needs: the smallest N with
// sqrt(ln(2 / (1 - confidence)) / (2 N)) <= max_error.
double HoeffdingSamplesNeeded(double max_error, double confidence);

// Marks the plans that meet the target and picks one (predicted_ms filled):
// - an error target: the cheapest plan meeting it (within the budget, if
//   one is given); OUT_OF_RANGE when no plan can meet it, or none within
//   the budget, naming the best plan available;
// - a budget alone: the most accurate plan predicted to fit, ties to the
//   cheaper; when none fits, the cheapest plan (its predicted_ms says so).
[[nodiscard]] StatusOr<size_t> ChoosePlan(std::vector<Plan>& plans, const AccuracyTarget& target);

// One of several methods that give the same answer (or, for a bake, one
// whose stated bound is at least as tight): for a request that names no
// method, the server runs the one predicted fastest on this device and
// scene. `plan` holds the method, its parameters and bound, its cost series
// and the request's work in the series' units.
struct EqualAnswerOption {
  Plan plan;
  // Small runs of this request (a few receiver points, a few directions)
  // that teach the cost model this method on this scene, smallest first:
  // each returns its compute ms, and runs under `call`, whose deadline is
  // the probe's budget.
  struct Probe {
    double work = 0.0;
    double extra = 0.0;
    std::function<StatusOr<double>(const CallOptions& call)> run;
  };
  std::vector<Probe> probes;
  // Whether the probes own what they run on (the scene, a copy of the
  // request), so that they may run after the call has answered, in the
  // server's idle time (IdleExplorer).
  bool probes_outlive_the_call = false;
};

class IdleExplorer;

// Of a method without observations, at most this share of the best plan
// predicted so far is spent on its probes: a method slower here than the
// others costs a request at most this much more (plus one GL job, the
// granularity at which a probe stops).
inline constexpr double kProbeShareOfBest = 0.25;
// Below this budget a method is not probed at all: the request is cheap
// with the methods already known.
inline constexpr double kSmallestProbeBudgetMs = 10.0;
// A probe after the first runs only while the model predicts it at most
// this share of the whole request.
inline constexpr double kNextProbeShareOfRequest = 0.1;
// A prediction for more than this many times the most work the method was
// measured at extrapolates small runs, whose fixed costs (a thread pool's
// wake-up, a pass's set-up) look like rate: the next larger probe runs
// first, where it is small beside the request.
inline constexpr double kLongestExtrapolation = 64.0;
// A method's first probe on a scene is run twice, and the cheaper run kept,
// where the second run fits in this share of the probe's budget or the
// method was never probed in this process: the first pays one-time costs
// (GL programs compiled, buffers uploaded) that a fit would otherwise take
// for a rate and extrapolate by the request's size.
inline constexpr double kRepeatProbeShareOfBudget = 0.25;
// Where the server explores in its idle time, a probe runs inside a request
// only when the request's share is at least this: a method's first probe
// pays one-time costs of tens of ms on llvmpipe (a raster program compiled:
// 8-30 ms; a Hough table at 4,096 samples: 44 ms), which a smaller share
// cannot cover, so a small request that probed took 1.5-2.2x its time
// (docs/default-method.md). Smaller probes wait for idle time.
inline constexpr double kSmallestInlineProbeBudgetMs = 100.0;

// Predicts every option (probing, in the order given, the ones this series
// has not measured: put the cheapest to probe first; the first option's
// probes have no budget but the call's) and chooses the fastest. An option
// measured at one size only (its larger probe did not fit the first
// request's budget) runs its next probe within each later request's share,
// until the model has two sizes to separate its fixed cost from its rates;
// so does one asked for kLongestExtrapolation times its largest run. An option
// whose probe fails with FAILED_PRECONDITION (it cannot answer this
// request honestly) or runs past its budget is left out; FAILED_PRECONDITION
// when none is left.
//
// With `idle`, a probe whose share is under kSmallestInlineProbeBudgetMs
// is offered to it instead (where the option's probes outlive the call),
// and the request goes on with the methods already measured.
[[nodiscard]] StatusOr<PlanReport> ChooseFastest(CostModel& model, std::vector<EqualAnswerOption> options,
                                                 const CallOptions& call, IdleExplorer* idle = nullptr);

// Runs `option`'s probes from `first_probe` on outside any request (the
// IdleExplorer), within `budget_ms` and `call`'s stop, recording what they
// measure, or a probe cut at the budget (CostModel::RecordCutProbe): OK
// then, and where the option cannot answer its request; the stop's status
// when `call` stopped it; any other failure as it came.
[[nodiscard]] Status ProbeOutsideARequest(CostModel& model, const EqualAnswerOption& option, size_t first_probe,
                                          double budget_ms, const CallOptions& call, double& probe_ms);

// "raycast {samples: 2048}" for messages and logs.
std::string DescribePlan(const Plan& plan);

}  // namespace visq::core
