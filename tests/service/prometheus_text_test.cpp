// The exposition format 0.0.4 as Prometheus parses it: escaping in label
// values and HELP, and one histogram rendered in full.
#include <string>
#include <utility>
#include <vector>

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
  for (double ms : {0.2, 3.0, 3.0, 700.0, 1e8}) {  // the last (28 hours) beyond every finite bucket
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
  // 0.2 ms lies in le=0.0005; the two 3 ms calls in 0.005; 700 ms in 1; 1e8 ms only in +Inf.
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.0005\"} 1")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.0025\"} 1")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.005\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"0.5\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"1\"} 4")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"120\"} 4")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"14400\"} 4")) << text;
  EXPECT_TRUE(has("visq_rpc_duration_seconds_bucket{method=\"GetScene\",le=\"+Inf\"} 5")) << text;
  const std::string sum = "visq_rpc_duration_seconds_sum{method=\"GetScene\"} ";
  ASSERT_NE(text.find(sum), std::string::npos) << text;
  EXPECT_NEAR(std::stod(text.substr(text.find(sum) + sum.size())), 100000.7062, 1e-6);
  EXPECT_TRUE(has("visq_rpc_duration_seconds_count{method=\"GetScene\"} 5")) << text;
  EXPECT_TRUE(has("visq_rpc_handled_total{method=\"GetScene\",code=\"OK\"} 3")) << text;
  EXPECT_TRUE(has("visq_rpc_handled_total{method=\"GetScene\",code=\"NOT_FOUND\"} 2")) << text;
  EXPECT_TRUE(has("visq_rpc_errors_total{method=\"GetScene\"} 2")) << text;
  EXPECT_TRUE(has("visq_rpc_in_flight{method=\"GetScene\"} 1")) << text;
  // Every family once: a second # TYPE for a name is a scrape error.
  EXPECT_EQ(text.find("# TYPE visq_rpc_duration_seconds "), text.rfind("# TYPE visq_rpc_duration_seconds "));
  EXPECT_EQ(text.back(), '\n');
}

TEST(PrometheusText, BakesOfHoursLandInBucketsOfTheirOwn) {
  // Before, every call over 120 s shared the +Inf bucket: a 3-minute and a
  // 3-hour bake could not be told apart.
  Metrics metrics;
  for (double seconds : {90.0, 200.0, 1000.0, 3000.0, 5000.0, 10000.0, 20000.0}) {
    metrics.Begin("BakeObscurances");
    metrics.Record("BakeObscurances", seconds * 1e3, absl::StatusCode::kOk);
  }
  ServerFigures figures;
  figures.methods = metrics.Summaries();
  const std::string text = RenderPrometheusText(figures);
  const auto bucket = [](const char* le, int count) {
    return std::string("\nvisq_rpc_duration_seconds_bucket{method=\"BakeObscurances\",le=\"") + le + "\"} " +
           std::to_string(count) + "\n";
  };
  for (const auto& [le, count] : std::vector<std::pair<const char*, int>>{
           {"120", 1}, {"300", 2}, {"600", 2}, {"1800", 3}, {"3600", 4}, {"7200", 5}, {"14400", 6}, {"+Inf", 7}})
    EXPECT_NE(text.find(bucket(le, count)), std::string::npos) << le << "\n" << text;
  // The percentiles GetStats reports reach hours too (within a bucket, 10 %).
  ASSERT_EQ(figures.methods.size(), 1u);
  EXPECT_NEAR(figures.methods[0].p50_ms, 3000e3, 300e3);
  EXPECT_NEAR(figures.methods[0].max_ms, 20000e3, 1e-3);
}

TEST(PrometheusText, TheProcessFamilyIsThereWhenKnownAndAbsentWhenNot) {
  ServerFigures figures;
  figures.process.cpu_seconds = 12.5;
  figures.process.resident_bytes = 123456789;
  figures.process.virtual_bytes = 987654321;
  figures.process.open_fds = 42;
  figures.process.max_fds = 1048576;
  figures.process.start_time_seconds = 1764964800.25;
  const std::string text = RenderPrometheusText(figures);
  for (const char* line :
       {"# TYPE process_cpu_seconds_total counter\nprocess_cpu_seconds_total 12.5\n",
        "# TYPE process_resident_memory_bytes gauge\nprocess_resident_memory_bytes 123456789\n",
        "# TYPE process_virtual_memory_bytes gauge\nprocess_virtual_memory_bytes 987654321\n",
        "# TYPE process_open_fds gauge\nprocess_open_fds 42\n", "# TYPE process_max_fds gauge\nprocess_max_fds 1048576\n",
        "# TYPE process_start_time_seconds gauge\nprocess_start_time_seconds 1764964800.25\n"})
    EXPECT_NE(text.find(line), std::string::npos) << line << "\n" << text;

  figures.process = {};
  figures.process.open_fds = 7;
  const std::string partial = RenderPrometheusText(figures);
  EXPECT_NE(partial.find("\nprocess_open_fds 7\n"), std::string::npos) << partial;
  EXPECT_EQ(partial.find("process_cpu_seconds_total"), std::string::npos) << "no made-up 0: " << partial;
  EXPECT_EQ(partial.find("process_max_fds"), std::string::npos) << partial;
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
