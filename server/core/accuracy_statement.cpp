#include "core/accuracy_statement.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/accuracy_planner.h"

namespace visq::core {

AccuracyStatement ExactStatement(std::string method, std::string note) {
  AccuracyStatement out;
  out.method = std::move(method);
  out.error_bound = 0.0;
  out.confidence = 1.0;
  out.note = std::move(note);
  return out;
}

void AddChosenPlan(const PlanReport& plan, AccuracyStatement& statement) {
  const Plan& chosen = plan.chosen_plan();
  for (const auto& [name, value] : chosen.parameters) statement.parameters[name] = value;
  statement.predicted_ms = chosen.predicted_ms;
  const std::string probing = plan.probe_ms > 0
                                  ? absl::StrFormat("%.1f ms spent probing methods new to this scene", plan.probe_ms)
                                  : std::string("no probing needed");
  if (plan.reason == PlanReport::Reason::kTarget) {
    absl::StrAppend(&statement.note, "; chosen for the target among ", plan.plans.size(),
                    " plans by the cost model (", probing, ")");
    if (plan.target && plan.target->max_error > 0) {
      // What the target was on, against what the answer states: a plan
      // chosen by a predicted estimate can miss it, and says so. An answer
      // with a bound and no estimate (the exact method's 0) meets an
      // estimate's target by its bound.
      const bool on_estimate = plan.target->wants_estimate() && statement.estimate >= 0;
      const double stated = on_estimate ? statement.estimate : statement.error_bound;
      const bool met = stated >= 0 && stated <= plan.target->max_error;
      statement.parameters["target_met"] = met ? 1.0 : 0.0;
      if (!met)
        absl::StrAppend(&statement.note, "; the target's max_error ", plan.target->max_error, " on the ",
                        on_estimate ? "estimate" : "bound", " was missed: the answer states ",
                        stated >= 0 ? absl::StrCat(stated) : std::string("none"));
    }
    return;
  }
  std::string left_out;
  for (const std::string& method : plan.cut_probes) absl::StrAppend(&left_out, left_out.empty() ? "" : ", ", method);
  absl::StrAppend(&statement.note, "; no method named: the fastest here of ", plan.plans.size(),
                  " methods giving this answer, by the cost model (", probing, ")",
                  left_out.empty() ? std::string()
                                   : absl::StrCat("; not weighed (its probe would cost more than a ",
                                                  kProbeShareOfBest, " share of the best plan): ", left_out));
  std::string idle;
  for (const std::string& method : plan.left_to_idle_time) absl::StrAppend(&idle, idle.empty() ? "" : ", ", method);
  if (!idle.empty())
    absl::StrAppend(&statement.note, "; not weighed yet (its probe, too costly for this request's share, runs "
                    "while the server is idle): ", idle);
}

}  // namespace visq::core
