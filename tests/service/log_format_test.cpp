// JSON log lines: any bytes a client sends become a string that a strict
// JSON parser reads back.
#include <limits>
#include <memory>
#include <sstream>
#include <vector>

#include <absl/status/status.h>
#include <grpcpp/server_context.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "service/log_format.h"
#include "service/request_log.h"

namespace visq::service {
namespace {

std::string RoundTrip(const std::string& text) {
  std::string quoted(1, '"');
  quoted.append(EscapeForJson(text));
  quoted.push_back('"');
  return nlohmann::json::parse(quoted).get<std::string>();
}

TEST(JsonLogFormat, EscapesQuotesBackslashesAndEveryControlCharacter) {
  EXPECT_EQ(EscapeForJson("a\"b\\c\nd\te\x01\x7f"), "a\\\"b\\\\c\\nd\\te\\u0001\\u007f");
  std::string all;
  for (int c = 1; c < 0x80; ++c) all += static_cast<char>(c);
  EXPECT_EQ(RoundTrip(all), all);
  EXPECT_EQ(RoundTrip(std::string("nul\0byte", 8)), std::string("nul\0byte", 8));
}

TEST(JsonLogFormat, KeepsValidUtf8AndReplacesEveryInvalidByte) {
  EXPECT_EQ(EscapeForJson("caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80"), "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80");
  // A lone continuation byte, a truncated sequence, an overlong '/', a
  // surrogate, and a byte that never appears in UTF-8.
  EXPECT_EQ(EscapeForJson("\x80"), "\\ufffd");
  EXPECT_EQ(EscapeForJson("\xe2\x82"), "\\ufffd\\ufffd");
  EXPECT_EQ(EscapeForJson("\xc0\xaf"), "\\ufffd\\ufffd");
  EXPECT_EQ(EscapeForJson("\xed\xa0\x80"), "\\ufffd\\ufffd\\ufffd");
  EXPECT_EQ(EscapeForJson("\xff"), "\\ufffd");
  EXPECT_EQ(RoundTrip("ok\xff\xc3\xa9"), "ok\xef\xbf\xbd\xc3\xa9");
}

// The default logger writing JSON lines into a string while it lives; the
// logger before it comes back after.
class CapturedJsonLog {
 public:
  CapturedJsonLog() : previous_(spdlog::default_logger()) {
    auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out_);
    spdlog::set_default_logger(std::make_shared<spdlog::logger>("visq", sink));
    UseJsonLogFormat();
  }
  ~CapturedJsonLog() { spdlog::set_default_logger(previous_); }
  std::vector<nlohmann::json> Lines() {
    spdlog::default_logger()->flush();
    std::vector<nlohmann::json> lines;
    std::istringstream in(out_.str());
    for (std::string line; std::getline(in, line);) lines.push_back(nlohmann::json::parse(line));
    return lines;
  }

 private:
  std::ostringstream out_;
  std::shared_ptr<spdlog::logger> previous_;
};

// A call's end, in the JSON format, carries its request id, method, status
// and duration as members of their own (a collector filters and sums them
// without parsing the message), and the call's other lines its id and
// method; the message still says it all.
TEST(JsonLogFormat, ACallsLinesCarryRequestIdMethodStatusAndDurationAsFields) {
  CapturedJsonLog log;
  grpc::CallbackServerContext context;
  {
    RequestLog ok(&context, "ComputeHiddenSampleMap", nullptr);
    ok.Info("scene {}", "box\"1");
    ok.Done(absl::OkStatus());
  }
  RequestLog failed(&context, "UploadScene", nullptr);
  failed.Done(absl::NotFoundError("no scene \"x\""));
  spdlog::info("outside any call");
  const auto lines = log.Lines();
  ASSERT_EQ(lines.size(), 4u);
  const auto& info = lines[0];
  EXPECT_EQ(info["method"], "ComputeHiddenSampleMap");
  ASSERT_TRUE(info["request_id"].is_string());
  EXPECT_EQ(info["request_id"].get<std::string>().rfind('r', 0), 0u);
  EXPECT_FALSE(info.contains("status"));
  EXPECT_NE(info["message"].get<std::string>().find("scene box\"1"), std::string::npos);
  const auto& done = lines[1];
  EXPECT_EQ(done["request_id"], info["request_id"]);
  EXPECT_EQ(done["method"], "ComputeHiddenSampleMap");
  EXPECT_EQ(done["status"], "OK");
  ASSERT_TRUE(done["duration_ms"].is_number());
  EXPECT_GE(done["duration_ms"].get<double>(), 0.0);
  EXPECT_EQ(done["level"], "info");
  const auto& refused = lines[2];
  EXPECT_NE(refused["request_id"], done["request_id"]);
  EXPECT_EQ(refused["method"], "UploadScene");
  EXPECT_EQ(refused["status"], "NOT_FOUND");
  EXPECT_TRUE(refused["duration_ms"].is_number());
  EXPECT_EQ(refused["level"], "warning");
  EXPECT_NE(refused["message"].get<std::string>().find("no scene \"x\""), std::string::npos);
  // The fields end with the call's line.
  for (const char* field : {"request_id", "method", "status", "duration_ms"})
    EXPECT_FALSE(lines[3].contains(field)) << field;
}

TEST(JsonLogFormat, ScopedFieldsNestAndEscapeAndANonFiniteNumberIsNull) {
  CapturedJsonLog log;
  {
    const ScopedLogFields outer({LogField::String("a", "1")});
    {
      const ScopedLogFields inner({LogField::String("b", "q\"\n\xff"), LogField::Number("n", std::numeric_limits<double>::quiet_NaN())});
      spdlog::info("inner");
    }
    spdlog::info("outer");
  }
  const auto lines = log.Lines();
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_FALSE(lines[0].contains("a"));
  EXPECT_EQ(lines[0]["b"], "q\"\n\xef\xbf\xbd");
  EXPECT_TRUE(lines[0]["n"].is_null());
  EXPECT_EQ(lines[1]["a"], "1");
  EXPECT_FALSE(lines[1].contains("b"));
}

}  // namespace
}  // namespace visq::service
