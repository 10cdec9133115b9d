// JSON log lines: any bytes a client sends become a string that a strict
// JSON parser reads back.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "service/log_format.h"

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

}  // namespace
}  // namespace visq::service
