// Operations: the real visq-server on loopback, scraped over HTTP
// (/metrics), its JSON logs parsed line by line, and grpc.reflection.v1
// compared with gRPC's own v1alpha on the wire.
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>
#include <thread>

#include <google/protobuf/descriptor.pb.h>
#include <grpcpp/create_channel.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/security/credentials.h>
#include <gtest/gtest.h>
#include <httplib.h>
#include <nlohmann/json.hpp>

#include "grpc/reflection/v1/reflection.pb.h"
#include "proto_builders.h"
#include "raw_grpc_call.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq::testing {
namespace {

namespace fs = std::filesystem;
using client::Client;

int ReadPort(const fs::path& file) {
  std::ifstream in(file);
  int port = 0;
  in >> port;
  return port;
}

// A scrape as "name{labels}" -> value, checking each line's grammar on the
// way: comments are # HELP or # TYPE, every sample's family was TYPEd
// before it, and every sample line is name{labels} value.
struct Scrape {
  std::map<std::string, double> samples;
  std::map<std::string, std::string> types;
  std::string text;
  double Get(const std::string& key) const {
    auto it = samples.find(key);
    return it == samples.end() ? 0 : it->second;
  }
};

Scrape Parse(const std::string& text) {
  Scrape s;
  s.text = text;
  static const std::regex type(R"(# TYPE ([a-zA-Z_:][a-zA-Z0-9_:]*) (counter|gauge|histogram|summary|untyped))");
  static const std::regex help(R"(# HELP ([a-zA-Z_:][a-zA-Z0-9_:]*) .*)");
  static const std::regex sample(
      R"(([a-zA-Z_:][a-zA-Z0-9_:]*)(\{([a-zA-Z_][a-zA-Z0-9_]*="([^"\\]|\\.)*",?)*\})? ([-+0-9.eE]+|\+Inf|-Inf|NaN))");
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    std::smatch m;
    if (std::regex_match(line, m, type)) {
      EXPECT_EQ(s.types.count(m[1]), 0u) << "family TYPEd twice: " << line;
      s.types[m[1]] = m[2];
    } else if (std::regex_match(line, help)) {
    } else if (std::regex_match(line, m, sample)) {
      std::string family = m[1];
      for (const char* suffix : {"_bucket", "_sum", "_count"})
        if (!s.types.count(family) && family.size() > std::strlen(suffix) &&
            family.compare(family.size() - std::strlen(suffix), std::string::npos, suffix) == 0)
          family = family.substr(0, family.size() - std::strlen(suffix));
      EXPECT_TRUE(s.types.count(family)) << "sample before its # TYPE: " << line;
      const std::string value = m[m.size() - 1];
      s.samples[line.substr(0, line.rfind(' '))] = value == "+Inf" ? HUGE_VAL : std::strtod(value.c_str(), nullptr);
    } else {
      ADD_FAILURE() << "not exposition format 0.0.4: '" << line << "'";
    }
  }
  return s;
}

Scrape ScrapeMetrics(int port, double* ms = nullptr) {
  httplib::Client http("127.0.0.1", port);
  http.set_read_timeout(std::chrono::seconds(10));
  const auto start = std::chrono::steady_clock::now();
  auto result = http.Get("/metrics");
  if (ms) *ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  EXPECT_TRUE(result) << "no answer from /metrics: " << httplib::to_string(result.error());
  if (!result) return {};
  EXPECT_EQ(result->status, 200);
  EXPECT_EQ(result->get_header_value("Content-Type"), "text/plain; version=0.0.4; charset=utf-8");
  return Parse(result->body);
}

// The histogram of one method: buckets rise with le and never fall, and
// +Inf equals _count.
void ExpectHistogram(const Scrape& s, const std::string& method) {
  const std::string prefix = "visq_rpc_duration_seconds_bucket{method=\"" + method + "\",le=\"";
  std::vector<std::pair<double, double>> buckets;  // le, count
  for (const auto& [key, value] : s.samples)
    if (key.rfind(prefix, 0) == 0) {
      const std::string le = key.substr(prefix.size(), key.size() - prefix.size() - 2);
      buckets.emplace_back(le == "+Inf" ? HUGE_VAL : std::stod(le), value);
    }
  std::sort(buckets.begin(), buckets.end());
  ASSERT_GE(buckets.size(), 2u) << method << "\n" << s.text;
  EXPECT_EQ(buckets.back().first, HUGE_VAL) << "the last bucket is +Inf";
  for (size_t i = 1; i < buckets.size(); ++i)
    EXPECT_LE(buckets[i - 1].second, buckets[i].second) << method << ": buckets are cumulative";
  const double count = s.Get("visq_rpc_duration_seconds_count{method=\"" + method + "\"}");
  EXPECT_EQ(buckets.back().second, count) << method << ": +Inf equals _count";
  EXPECT_GT(count, 0) << method;
  EXPECT_GE(s.Get("visq_rpc_duration_seconds_sum{method=\"" + method + "\"}"), 0) << method;
}

std::string Handled(const std::string& method, const std::string& code) {
  return "visq_rpc_handled_total{method=\"" + method + "\",code=\"" + code + "\"}";
}

TEST(MetricsEndpoint, CountsRealCallsByStatusWithCumulativeHistograms) {
  ScratchDir repo, files;
  auto server = ServerProcess::Start(
      {repo.path(),
       {"--seed-samples", "--metrics-address", "127.0.0.1:0", "--metrics-port-file", (files.path() / "mp").string()}});
  ASSERT_NE(server, nullptr);
  const int port = ReadPort(files.path() / "mp");
  ASSERT_GT(port, 0) << server->Log();
  Client client({.address = server->address()});

  const Scrape before = ScrapeMetrics(port);
  ASSERT_TRUE(client.ListScenes().ok());
  ASSERT_TRUE(client.ListScenes().ok());
  EXPECT_EQ(client.GetScene("no_such_scene").status().code(), absl::StatusCode::kNotFound);
  v1::PatchVisibilityRequest query;
  query.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(query.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(query.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  query.set_receiver_columns(4);
  query.set_receiver_rows(4);
  query.set_method(v1::PLUCKER_EXACT);
  auto answer = client.PatchVisibility(query);
  ASSERT_TRUE(answer.ok()) << answer.status();
  auto stats = client.GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();

  double ms = 0;
  const Scrape after = ScrapeMetrics(port, &ms);
  std::printf("scrape: %.2f ms, %zu bytes, %zu samples\n", ms, after.text.size(), after.samples.size());
  const auto moved = [&](const std::string& key) { return after.Get(key) - before.Get(key); };
  EXPECT_EQ(moved(Handled("ListScenes", "OK")), 2) << after.text;
  EXPECT_EQ(moved(Handled("GetScene", "NOT_FOUND")), 1);
  EXPECT_EQ(moved(Handled("GetScene", "OK")), 0);
  EXPECT_EQ(moved("visq_rpc_errors_total{method=\"GetScene\"}"), 1);
  EXPECT_EQ(moved("visq_rpc_errors_total{method=\"ListScenes\"}"), 0);
  EXPECT_EQ(moved(Handled("PatchVisibility", "OK")), 1);
  EXPECT_EQ(moved(Handled("GetStats", "OK")), 1);
  EXPECT_EQ(after.types.at("visq_rpc_duration_seconds"), "histogram");
  EXPECT_EQ(after.types.at("visq_rpc_handled_total"), "counter");
  for (const char* method : {"ListScenes", "GetScene", "PatchVisibility"}) ExpectHistogram(after, method);
  EXPECT_EQ(moved("visq_rpc_duration_seconds_count{method=\"ListScenes\"}"), 2);
  EXPECT_EQ(after.Get("visq_requests_in_flight"), 0) << "nothing is running between calls";

  // The figures GetStats reports, in the same scrape.
  EXPECT_EQ(after.Get("visq_build_info{version=\"" + stats->server_version() + "\",commit=\"" +
                      stats->build_commit() + "\"}"),
            1)
      << after.text;
  EXPECT_EQ(after.Get("visq_scenes_resident"), stats->scenes_resident());
  EXPECT_GE(after.Get("visq_scenes_resident"), 1);
  EXPECT_EQ(after.Get("visq_memory_bytes{kind=\"scene_cpu\"}"), stats->scene_memory().cpu_bytes());
  EXPECT_GT(after.Get("visq_work_memory_capacity_bytes"), 0);
  EXPECT_GT(after.Get("visq_cache_capacity_bytes{cache=\"light_visibility\"}"), 0);
  EXPECT_EQ(after.Get("visq_gpu_contexts_lost_total"), 0);
  EXPECT_GE(after.Get("visq_structure_build_seconds_count{structure=\"scene_load\"}"), 1);
  EXPECT_GE(after.Get("visq_structure_build_seconds_count{structure=\"triangle_index\"}"), 1)
      << "the exact query built the scene's triangle index";

  // Latency buckets reach the hours a bake takes.
  for (const char* le : {"120", "300", "600", "1800", "3600", "7200", "14400"})
    EXPECT_EQ(after.samples.count("visq_rpc_duration_seconds_bucket{method=\"ListScenes\",le=\"" + std::string(le) +
                                  "\"}"),
              1u)
        << le << "\n" << after.text;

  // The standard process_* family, of the server's own process.
  for (const auto& [family, type] : std::map<std::string, std::string>{{"process_cpu_seconds_total", "counter"},
                                                                      {"process_resident_memory_bytes", "gauge"},
                                                                      {"process_virtual_memory_bytes", "gauge"},
                                                                      {"process_open_fds", "gauge"},
                                                                      {"process_max_fds", "gauge"},
                                                                      {"process_start_time_seconds", "gauge"}}) {
    ASSERT_EQ(after.types.count(family), 1u) << family << "\n" << after.text;
    EXPECT_EQ(after.types.at(family), type) << family;
    EXPECT_EQ(after.samples.count(family), 1u) << family;
  }
  EXPECT_GT(after.Get("process_cpu_seconds_total"), 0);
  EXPECT_GE(after.Get("process_cpu_seconds_total"), before.Get("process_cpu_seconds_total"));
  EXPECT_GT(after.Get("process_resident_memory_bytes"), 1 << 20);
  EXPECT_GE(after.Get("process_virtual_memory_bytes"), after.Get("process_resident_memory_bytes"));
  EXPECT_GT(after.Get("process_open_fds"), 3) << "at least the standard three and the listening sockets";
  EXPECT_GE(after.Get("process_max_fds"), after.Get("process_open_fds"));
  // The server started within this test (a second's slack for the clock
  // tick rounding).
  const double now = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  EXPECT_LE(after.Get("process_start_time_seconds"), now + 1);
  EXPECT_GT(after.Get("process_start_time_seconds"), now - 600);
  EXPECT_EQ(after.Get("process_start_time_seconds"), before.Get("process_start_time_seconds"));

  // Only GET /metrics is served.
  httplib::Client http("127.0.0.1", port);
  auto other = http.Get("/");
  ASSERT_TRUE(other);
  EXPECT_EQ(other->status, 404);
  auto post = http.Post("/metrics", "x", "text/plain");
  ASSERT_TRUE(post);
  EXPECT_EQ(post->status, 404);
}

// Runs visq-server to completion (it must fail at start-up); returns its
// exit status and output.
int RunServerToExit(const std::vector<std::string>& args, std::string* output) {
  ScratchDir scratch;
  std::string command = VISQ_SERVER_BINARY;
  for (const auto& a : args) command += " '" + a + "'";
  command += " > '" + (scratch.path() / "log").string() + "' 2>&1";
  const int status = std::system(command.c_str());
  std::ifstream in(scratch.path() / "log");
  std::stringstream text;
  text << in.rdbuf();
  *output = text.str();
  return status;
}

TEST(MetricsEndpoint, RemoteAddressNeedsAnExplicitChoiceAndABindFailureStopsStartUp) {
  ScratchDir repo;
  std::string output;
  EXPECT_NE(RunServerToExit({"--address", "127.0.0.1:0", "--scene-repo", repo.path().string(), "--metrics-address",
                             "0.0.0.0:0"},
                            &output),
            0);
  EXPECT_NE(output.find("--metrics-allow-remote"), std::string::npos) << output;

  EXPECT_NE(RunServerToExit({"--address", "127.0.0.1:0", "--scene-repo", repo.path().string(), "--metrics-address",
                             "localhost"},
                            &output),
            0);
  EXPECT_NE(output.find("expected HOST:PORT"), std::string::npos) << output;

  // A port in use (held here by a listening socket).
  const int sock = ::socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(sock, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(sock, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)), 0);
  ASSERT_EQ(::listen(sock, 1), 0);
  socklen_t length = sizeof(addr);
  ASSERT_EQ(::getsockname(sock, reinterpret_cast<sockaddr*>(&addr), &length), 0);
  const std::string taken = "127.0.0.1:" + std::to_string(ntohs(addr.sin_port));
  EXPECT_NE(RunServerToExit({"--address", "127.0.0.1:0", "--scene-repo", repo.path().string(), "--metrics-address",
                             taken},
                            &output),
            0);
  ::close(sock);
  EXPECT_NE(output.find("cannot listen"), std::string::npos) << output;
}

TEST(JsonLogs, EveryLineIsOneObjectWhateverTheClientSent) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--log-format", "json"}});
  ASSERT_NE(server, nullptr);
  const std::string hostile = "we\"ird\nna\\me\x1b[31m";
  {
    Client client({.address = server->address()});
    EXPECT_FALSE(client.GetScene(hostile).ok());
    EXPECT_FALSE(client.LoadFromRepository(hostile).ok());
    // Not UTF-8: protobuf refuses the message, and says so in a log line
    // of its own, which must be JSON too.
    EXPECT_FALSE(client.GetScene(hostile + "\xff").ok());
    ASSERT_TRUE(client.ListScenes().ok());
  }
  ASSERT_EQ(server->Stop(), 0);
  const std::string log = server->Log();
  std::istringstream in(log);
  static const std::regex rfc3339(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z)");
  int lines = 0;
  bool hostile_logged = false, protobuf_logged = false, list_ended = false;
  for (std::string line; std::getline(in, line);) {
    ++lines;
    nlohmann::json object;
    try {
      object = nlohmann::json::parse(line);
    } catch (const std::exception& e) {
      ADD_FAILURE() << "not JSON: " << e.what() << "\n" << line;
      continue;
    }
    ASSERT_TRUE(object.is_object()) << line;
    for (const char* key : {"time", "level", "logger", "message"})
      ASSERT_TRUE(object.contains(key) && object[key].is_string()) << key << " in " << line;
    EXPECT_TRUE(std::regex_match(object["time"].get<std::string>(), rfc3339)) << line;
    // The name comes back exactly.
    if (object["message"].get<std::string>().find(hostile) != std::string::npos) hostile_logged = true;
    if (object["message"].get<std::string>().find("protobuf") != std::string::npos) protobuf_logged = true;
    // A call's end carries its id, method, status and duration as fields
    // of their own, the same as its message says.
    if (object.contains("status")) {
      ASSERT_TRUE(object["request_id"].is_string() && object["method"].is_string()) << line;
      ASSERT_TRUE(object["status"].is_string() && object["duration_ms"].is_number()) << line;
      std::string tag = "[";
      tag += object["request_id"].get<std::string>();
      tag += " ";
      tag += object["method"].get<std::string>();
      tag += "] ";
      tag += object["status"].get<std::string>();
      EXPECT_EQ(object["message"].get<std::string>().rfind(tag, 0), 0u) << line;
      list_ended |= object["method"] == "ListScenes" && object["status"] == "OK";
    }
  }
  EXPECT_GT(lines, 5);
  EXPECT_TRUE(list_ended) << "no ListScenes line with status OK as a field\n" << log;
  EXPECT_TRUE(hostile_logged) << log;
  EXPECT_TRUE(protobuf_logged) << "protobuf's own line goes through the JSON format\n" << log;
}


constexpr char kV1[] = "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo";
constexpr char kV1alpha[] = "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo";

TEST(ReflectionV1, ListsAndDescribesTheServiceAsV1alphaDoes) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  namespace refl = grpc::reflection::v1;

  refl::ServerReflectionRequest list;
  list.set_list_services("");
  std::string answer;
  ASSERT_TRUE(RawBidiCall(server->address(), kV1, list.SerializeAsString(), &answer).ok());
  refl::ServerReflectionResponse listed;
  ASSERT_TRUE(listed.ParseFromString(answer));
  std::vector<std::string> names;
  for (const auto& s : listed.list_services_response().service()) names.push_back(s.name());
  EXPECT_NE(std::find(names.begin(), names.end(), "visq.v1.VisibilityService"), names.end());
  EXPECT_NE(std::find(names.begin(), names.end(), "grpc.reflection.v1.ServerReflection"), names.end());

  // file_containing_symbol: the descriptor of visq.proto, byte for byte what
  // gRPC's own v1alpha answers (same field numbers, same files).
  refl::ServerReflectionRequest symbol;
  symbol.set_file_containing_symbol("visq.v1.VisibilityService");
  std::string v1_answer, v1alpha_answer;
  ASSERT_TRUE(RawBidiCall(server->address(), kV1, symbol.SerializeAsString(), &v1_answer).ok());
  ASSERT_TRUE(RawBidiCall(server->address(), kV1alpha, symbol.SerializeAsString(), &v1alpha_answer).ok());
  refl::ServerReflectionResponse described;
  ASSERT_TRUE(described.ParseFromString(v1_answer));
  ASSERT_GE(described.file_descriptor_response().file_descriptor_proto_size(), 1) << described.DebugString();
  google::protobuf::FileDescriptorProto file;
  ASSERT_TRUE(file.ParseFromString(described.file_descriptor_response().file_descriptor_proto(0)));
  EXPECT_EQ(file.name(), "visq/v1/visq.proto");
  ASSERT_GE(file.service_size(), 1);
  EXPECT_EQ(file.service(0).name(), "VisibilityService");
  EXPECT_EQ(described.original_request().file_containing_symbol(), "visq.v1.VisibilityService");
  EXPECT_EQ(v1_answer, v1alpha_answer) << "v1 and v1alpha differ on the wire";

  // An unknown symbol is an error_response with NOT_FOUND, as in v1alpha.
  symbol.set_file_containing_symbol("visq.v1.NoSuchThing");
  answer.clear();
  ASSERT_TRUE(RawBidiCall(server->address(), kV1, symbol.SerializeAsString(), &answer).ok());
  refl::ServerReflectionResponse missing;
  ASSERT_TRUE(missing.ParseFromString(answer));
  EXPECT_EQ(missing.error_response().error_code(), static_cast<int>(grpc::StatusCode::NOT_FOUND));
}

TEST(ReflectionV1, NeedsTheTokenWhenOneIsSet) {
  ScratchDir repo, files;
  std::ofstream(files.path() / "token") << "0123456789abcdef0123456789abcdef\n";
  auto locked = ServerProcess::Start({repo.path(), {"--auth-token-file", (files.path() / "token").string()}});
  ASSERT_NE(locked, nullptr);
  grpc::reflection::v1::ServerReflectionRequest list;
  list.set_list_services("");
  std::string answer;
  const grpc::Status status = RawBidiCall(locked->address(), kV1, list.SerializeAsString(), &answer);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNIMPLEMENTED) << status.error_message();
  EXPECT_EQ(answer.find("visq.v1.VisibilityService"), std::string::npos) << "v1 reflection answered without the token";
}

// The container's first start: no token given, so the server makes one in
// the data volume and logs where, never what.
TEST(TokenAtFirstStart, CreatedOnceReadableByTheOwnerOnlyAndNeverLogged) {
  ScratchDir repo, files;
  const fs::path token_file = files.path() / "token";
  const std::vector<std::string> args = {"--seed-samples", "--auth-token-file", token_file.string(),
                                         "--auth-token-create"};
  std::string token;
  {
    auto server = ServerProcess::Start({repo.path(), args});
    ASSERT_NE(server, nullptr);
    ASSERT_TRUE(fs::exists(token_file));
    EXPECT_EQ(fs::status(token_file).permissions() & fs::perms::all, fs::perms::owner_read | fs::perms::owner_write);
    std::ifstream(token_file) >> token;
    EXPECT_TRUE(std::regex_match(token, std::regex("[0-9a-f]{64}"))) << token;
    EXPECT_TRUE(Client({.address = server->address(), .auth_token = token}).ListScenes().ok());
    EXPECT_EQ(Client({.address = server->address()}).ListScenes().status().code(),
              absl::StatusCode::kUnauthenticated);
    EXPECT_NE(server->Log().find(token_file.string()), std::string::npos) << server->Log();
    EXPECT_EQ(server->Log().find(token), std::string::npos) << "the token was logged";
  }
  // A restart keeps the token that is there.
  auto again = ServerProcess::Start({repo.path(), args});
  ASSERT_NE(again, nullptr);
  std::string kept;
  std::ifstream(token_file) >> kept;
  EXPECT_EQ(kept, token);
  EXPECT_TRUE(Client({.address = again->address(), .auth_token = token}).ListScenes().ok());
}

TEST(Drain, DrainSecondsIsValidatedAndUsed) {
  ScratchDir repo;
  std::string output;
  EXPECT_NE(RunServerToExit({"--address", "127.0.0.1:0", "--scene-repo", repo.path().string(), "--drain-seconds",
                             "-1"},
                            &output),
            0);
  EXPECT_NE(output.find("--drain-seconds"), std::string::npos) << output;
  auto server = ServerProcess::Start({repo.path(), {"--drain-seconds", "3"}});
  ASSERT_NE(server, nullptr);
  ASSERT_EQ(server->Stop(), 0);
  EXPECT_NE(server->Log().find("draining requests for up to 3000 ms"), std::string::npos) << server->Log();
}

// The ceiling light onto the floor of the Cornell box at 1024 x 512 texels
// and 4096 samples: two billion segments, far longer than any test waits.
v1::HiddenSampleMapRequest LongCeilingMap(v1::VisibilityMethod method) {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  request.mutable_samples()->set_count(4096);
  request.set_width(1024);
  request.set_height(512);
  request.set_method(method);
  return request;
}

// A map far longer than the drain, by each sampled method: SIGTERM during it
// ends the process within the drain and a second, and the call is answered
// UNAVAILABLE (retry elsewhere), not cut without a word.
TEST(Drain, ALongCallIsAnsweredUnavailableAndTheServerExitsWithinItsDrain) {
  for (v1::VisibilityMethod method : {v1::RAYCAST, v1::RASTER}) {
    SCOPED_TRACE(v1::VisibilityMethod_Name(method));
    ScratchDir repo;
    auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--drain-seconds", "2"}});
    ASSERT_NE(server, nullptr);
    const v1::HiddenSampleMapRequest request = LongCeilingMap(method);
    absl::StatusCode code = absl::StatusCode::kOk;
    std::thread call([&] {
      Client client({.address = server->address(), .deadline = std::chrono::minutes(10),
                     .stream_deadline = std::chrono::milliseconds(0)});
      code = client.ComputeHiddenSampleMap(request).status().code();
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(1500));  // under way
    const auto start = std::chrono::steady_clock::now();
    EXPECT_EQ(server->Stop(), 0);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    call.join();
    EXPECT_LT(seconds, 2.0 + 1.0) << server->Log();
    EXPECT_EQ(code, absl::StatusCode::kUnavailable) << server->Log();
    EXPECT_NE(server->Log().find("told to stop"), std::string::npos) << server->Log();
  }
}

// A call whose deadline passes mid-map stops its work within a second of
// it: the server's log has the call's end, with its time, soon after.
TEST(Deadline, ALongMapStopsWithinASecondOfItsDeadline) {
  for (v1::VisibilityMethod method : {v1::RAYCAST, v1::RASTER}) {
    SCOPED_TRACE(v1::VisibilityMethod_Name(method));
    ScratchDir repo;
    auto server = ServerProcess::Start({repo.path(), {"--seed-samples"}});
    ASSERT_NE(server, nullptr);
    const v1::HiddenSampleMapRequest request = LongCeilingMap(method);
    Client client({.address = server->address(), .deadline = std::chrono::seconds(2)});
    EXPECT_EQ(client.ComputeHiddenSampleMap(request).status().code(), absl::StatusCode::kDeadlineExceeded);
    // The server's own end of the call, logged with its duration: its
    // deadline, or the client's cancellation when that arrives first.
    const std::regex ended(R"(HiddenSampleMap\] (CANCELLED|DEADLINE_EXCEEDED) in ([0-9.]+) ms)");
    std::smatch match;
    std::string log;
    for (int i = 0; i < 40; ++i) {
      log = server->Log();
      if (std::regex_search(log, match, ended)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ASSERT_FALSE(match.empty()) << log;
    EXPECT_LT(std::stod(match[2].str()), 2000.0 + 1000.0) << log;
  }
}

}  // namespace
}  // namespace visq::testing

namespace visq::testing {
namespace {

// How long the server took to end the latest-started of the first `count`
// calls of `method` that stopped (its log's "[rN method] CANCELLED /
// DEADLINE_EXCEEDED in X ms"; calls are numbered as they start, and a
// later call can end first), waiting up to `wait` for the lines; -1 when
// they did not come.
double ServerEndOfCall(ServerProcess& server, const std::string& method, int count,
                       std::chrono::seconds wait = std::chrono::seconds(10)) {
  const std::regex ended("\\[r([0-9]+) " + method + "\\] (CANCELLED|DEADLINE_EXCEEDED) in ([0-9.]+) ms");
  const auto give_up = std::chrono::steady_clock::now() + wait;
  do {
    const std::string log = server.Log();
    int seen = 0;
    long latest = -1;
    double ms = -1.0;
    for (auto it = std::sregex_iterator(log.begin(), log.end(), ended); it != std::sregex_iterator() && seen < count;
         ++it, ++seen) {
      if (const long call = std::stol((*it)[1].str()); call > latest) {
        latest = call;
        ms = std::stod((*it)[3].str());
      }
    }
    if (seen == count) return ms;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  } while (std::chrono::steady_clock::now() < give_up);
  return -1.0;
}

// Every long call stops within a second of its deadline, not at the end of
// its GL job: a conservative voxelization, a ray-marched volumetric shadow
// and a depth-peeling bake of Sponza, each far longer than 2 s on llvmpipe
// (a layer or a pass over the scene alone takes seconds there, so they are
// drawn in pieces of a few tens of ms). A GPU may finish one in time: then
// there is nothing to stop.
TEST(Deadline, EveryLongCallStopsWithinASecondOfItsDeadline) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  ScratchDir repo;
  // At debug level the log a failure prints names each GL job that held the
  // GL thread long (a job that does not look at its call is what fails here).
  auto server = ServerProcess::Start({repo.path(), {"--log-level", "debug"}});
  ASSERT_NE(server, nullptr);
  {
    Client uploader({.address = server->address()});
    auto info = uploader.UploadScene(scenes / "sponza_dabrovic/sponza.gltf", "sponza");
    ASSERT_TRUE(info.ok()) << info.status();
  }
  Client client({.address = server->address(), .deadline = std::chrono::seconds(2),
                 .stream_deadline = std::chrono::seconds(2)});

  v1::VoxelizeRequest voxelize;
  voxelize.mutable_scene()->set_name("sponza");
  voxelize.set_width(2048);
  voxelize.set_height(2048);
  voxelize.set_slices(1024);
  voxelize.set_conservative(true);

  v1::VolumetricShadowRequest volumetric;
  volumetric.mutable_scene()->set_name("sponza");
  Set(volumetric.mutable_camera_position(), -10, 2, 0);
  Set(volumetric.mutable_camera_forward(), 1, 0, 0);
  volumetric.set_vertical_fov_deg(60);
  volumetric.set_width(1920);
  volumetric.set_height(1080);
  Set(volumetric.mutable_light_direction(), 0.3, -1, 0.2);
  volumetric.set_shadow_map_size(4096);
  volumetric.set_scattering(0.05);
  volumetric.set_extinction(0.05);
  volumetric.set_method(v1::VolumetricShadowRequest::RAY_MARCHING);

  v1::ComputeObscurancesRequest bake;
  bake.mutable_scene()->set_name("sponza");
  bake.set_resolution(1024);
  bake.set_d_max(2.0);
  bake.set_direction_count(256);
  bake.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);

  // 67M segments on the GPU (on llvmpipe, about 2M a second): traced in GL
  // jobs of about 50 ms, the call looked at between them.
  v1::HiddenSampleMapRequest gpu_rays;
  gpu_rays.mutable_scene()->set_name("sponza");
  SetPatch(gpu_rays.mutable_source(), {-5, 14, -2}, {10, 0, 0}, {0, 0, 4});
  SetPatch(gpu_rays.mutable_receiver(), {-16, 0.2, -7}, {0, 0, 14}, {32, 0, 0});
  gpu_rays.set_width(256);
  gpu_rays.set_height(256);
  gpu_rays.mutable_samples()->set_count(1024);
  gpu_rays.set_method(v1::GPU_RAYCAST);

  const std::vector<std::pair<std::string, std::function<absl::Status()>>> calls = {
      {"HiddenSampleMap", [&] { return client.ComputeHiddenSampleMap(gpu_rays).status(); }},
      {"Voxelize", [&] { return client.Voxelize(voxelize).status(); }},
      {"VolumetricShadow", [&] { return client.VolumetricShadow(volumetric).status(); }},
      {"ComputeObscurances", [&] { return client.ComputeObscurances(bake).status(); }},
  };
  for (const auto& [method, call] : calls) {
    SCOPED_TRACE(method);
    // Once to compile its programs (seconds on llvmpipe, and not cut short:
    // 8.7 s under ASan on a loaded machine), and until the server has ended
    // it, then the call the test times: else it waits behind the compile.
    const bool warm_up_stopped = !call().ok();
    if (warm_up_stopped) {
      ASSERT_GE(ServerEndOfCall(*server, method, 1, std::chrono::seconds(120)), 0.0) << server->Log();
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    const absl::Status status = call();
    if (status.ok()) {
      RecordProperty(method, "finished within its deadline: nothing to stop");
      continue;
    }
    ASSERT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
    const double ms = ServerEndOfCall(*server, method, warm_up_stopped ? 2 : 1);
    ASSERT_GE(ms, 0.0) << server->Log();
    EXPECT_LT(ms, 2000.0 + 1000.0 + 1000.0 * kSanitizedStopSlackSeconds) << server->Log();
    std::printf("%s: ended by the server %.0f ms after its start (deadline 2000 ms)\n", method.c_str(), ms);
  }
}

}  // namespace
}  // namespace visq::testing
