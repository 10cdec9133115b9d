// The server's figures in the Prometheus text exposition format, version
// 0.0.4: one # HELP and # TYPE per family, label values escaped, histograms
// as cumulative _bucket{le} series ending in +Inf, with _sum and _count.
#pragma once

#include <string>
#include <string_view>

#include "service/stats.h"

namespace visq::service {

// The content type a scrape answer carries.
inline constexpr char kPrometheusContentType[] = "text/plain; version=0.0.4; charset=utf-8";

// A label value: backslash, double quote and line feed escaped (\\, \", \n).
std::string EscapePrometheusLabelValue(std::string_view value);
// HELP text: backslash and line feed escaped.
std::string EscapePrometheusHelp(std::string_view text);

std::string RenderPrometheusText(const ServerFigures& figures);

}  // namespace visq::service
