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
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "common/status.h"

namespace visq::core {

struct AccuracyTarget {
  double max_error = 0.0;    // half-width on the answered quantity; 0: none
  double confidence = 0.95;  // (0, 1]; 1: a worst-case bound
  double time_budget_ms = 0.0;  // 0: none
};

// INVALID_ARGUMENT naming "target.<field>" for a bad target.
[[nodiscard]] Status ValidateAccuracyTarget(const AccuracyTarget& target);

// One candidate: a method with its parameters, what it could promise and
// what it would cost.
struct Plan {
  std::string method;
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
  const Plan& chosen_plan() const { return plans[chosen]; }
};

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
  void Record(const std::string& series, double work, double ms, double extra = 0.0);
  // Nothing until the series has an observation.
  std::optional<double> Predict(const std::string& series, double work, double extra = 0.0) const;
  // How many observations the series holds.
  size_t Observations(const std::string& series) const;

  // Reads the observations `path` holds (none when it is absent; malformed
  // lines are skipped) and rewrites it, whole and atomically, after every
  // Record. An unreadable or unwritable file costs the persistence only.
  void PersistTo(const std::filesystem::path& path);

  struct Observation {
    double work = 0.0;
    double ms = 0.0;
    double extra = 0.0;
  };

 private:
  static constexpr size_t kObservationsKept = 16;
  static constexpr size_t kSeriesKept = 4096;  // bounds the file a hostile series name could grow
  void SaveLocked() const;
  mutable std::mutex mutex_;
  std::map<std::string, std::deque<Observation>> series_;
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

// "raycast {samples: 2048}" for messages and logs.
std::string DescribePlan(const Plan& plan);

}  // namespace visq::core
