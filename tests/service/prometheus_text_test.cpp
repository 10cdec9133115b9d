// The exposition format 0.0.4 as Prometheus parses it: escaping in label
// values and HELP, and one histogram rendered in full.
#include <gtest/gtest.h>

#include "service/metrics.h"
#include "service/prometheus_text.h"

namespace visq::service {
namespace {

TEST(PrometheusText, LabelValuesEscapeBackslashQuoteAndLineFeedOnly) {
  EXPECT_EQ(EscapePrometheusLabelValue("plain value"), "plain value");
  EXPECT_EQ(EscapePrometheusLabelValue("a\\b\"c\nd"), "a\\\\b\\\"c\\nd");
  EXPECT_EQ(EscapePrometheusLabelValue("tab\there"), "tab\there") << "only the three are escaped";
  EXPECT_EQ(EscapePrometheusHelp("say \"x\"\\\n"), "say \"x\"\\\\\\n") << "HELP keeps quotes as they are";
}

TEST(PrometheusText, OneMethodsHistogramIsCumulativeWithSumAndCount) {
  Metrics metrics;
  for (double ms : {0.2, 3.0, 3.0, 700.0, 1e6}) {  // the last beyond every finite bucket
    metrics.Begin("GetScene");
    metrics.Record("GetScene", ms, ms > 500 ? absl::StatusCode::kNotFound : absl::StatusCode::kOk);
  }
  metrics.Begin("GetScene");  // one still running
  ServerFigures figures;
  figures.version = "1.2.3";
  figures.build_commit = "abc\"def";
  figures.device.gl_renderer = "line\nbreak";
  figures.methods = metrics.Summaries();
  const std::string text = RenderPrometheusText(figures);

  const auto has = [&](const std::string& line) {
    return text.find("\n" + line + "\n") != std::string::npos || text.rfind(line + "\n", 0) == 0;
  };
  EXPECT_TRUE(has("visq_build_info{version=\"1.2.3\",commit=\"abc\\\"def\"} 1")) << text;
  EXPECT_NE(text.find("renderer=\"line\\nbreak\""), std::string::npos) << text;
  EXPECT_TRUE(has("# TYPE visq_rpc_duration_seconds histogram")) << text;
  // 0.2 ms lies in le=0.0005; the two 3 ms calls in 0.005; 700 ms in 1; 1e6 ms only in +Inf.
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.0005\"} 1")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.0025\"} 1")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.005\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.5\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"1\"} 4")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"120\"} 4")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"+Inf\"} 5")) << text;
  const std::string sum = "visq_rpc_duration_seconds_sum{method=\"GetScene\"} ";
  ASSERT_NE(text.find(sum), std::string::npos) << text;
  EXPECT_NEAR(std::stod(text.substr(text.find(sum) + sum.size())), 1000.7062, 1e-9);
  EXPECT_TRUE(has("visq_rpc_duration_seconds_count{method=\"GetScene\"} 5")) << text;
  EXPECT_TRUE(has("visq_rpc_handled_total{method=\"GetScene\",code=\"OK\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_handled_total{method=\"GetScene\",code=\"NOT_FOUND\"} 2")) << text;
  EXPECT_TRUE(has("visq_rpc_errors_total{method=\"GetScene\"} 2")) << text;
  EXPECT_TRUE(has("visq_rpc_in_flight{method=\"GetScene\"} 1")) << text;
  // Every family once: a second # TYPE for a name is a scrape error.
  EXPECT_EQ(text.find("# TYPE visq_rpc_duration_seconds "), text.rfind("# TYPE visq_rpc_duration_seconds "));
  EXPECT_EQ(text.back(), '\n');
}

TEST(PrometheusText, AbandonedCallsLeaveInFlightWithoutCounting) {
  Metrics metrics;
  metrics.Begin("ListScenes");
  metrics.Abandon("ListScenes");
  const auto summaries = metrics.Summaries();
  ASSERT_EQ(summaries.size(), 1u);
  EXPECT_EQ(summaries[0].in_flight, 0u);
  EXPECT_EQ(summaries[0].calls, 0u);
}

}  // namespace
}  // namespace visq::service
