// The visq CLI as a user meets it: the real binary against a real
// visq-server on loopback, its output and files checked against the client
// library's answers.
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "scene/sample_scenes.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;

constexpr char kScene[] = "cornell_box_visq";
constexpr char kLight[] = "-0.25,1.99,-0.25;0.25,1.99,-0.25;0.25,1.99,0.25;-0.25,1.99,0.25";
constexpr char kFloorUp[] = "-0.999,0.001,-0.999;0,0,1.998;1.998,0,0";  // faces +y
constexpr char kCeilingSource[] = "-0.25,1.99,-0.25;0.5,0,0;0,0,0.5";

struct CliRun {
  int exit_code;
  std::string output;  // stdout and stderr
};

CliRun Visq(const std::string& arguments) {
  int status = 0;
  std::string output = testing::RunCommand(std::string(VISQ_CLI_BINARY) + " " + arguments + " 2>&1", &status);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

bool Contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

// A float32 .npy: its shape and values.
struct Npy {
  std::vector<size_t> shape;
  std::vector<float> values;
};

Npy ReadNpy(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::string data((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  Npy npy;
  if (data.size() < 10 || data.compare(0, 6, "\x93NUMPY") != 0) return npy;
  const size_t header_length = static_cast<uint8_t>(data[8]) | (size_t(static_cast<uint8_t>(data[9])) << 8);
  const std::string header = data.substr(10, header_length);
  EXPECT_TRUE(Contains(header, "'descr': '<f4'")) << header;
  EXPECT_EQ((10 + header_length) % 64, 0u) << "header not padded to 64 bytes";
  std::istringstream shape(header.substr(header.find("'shape': (") + 10));
  for (size_t d; shape >> d;) {
    npy.shape.push_back(d);
    if (shape.peek() == ',') shape.get();
  }
  const size_t count = (data.size() - 10 - header_length) / sizeof(float);
  npy.values.resize(count);
  std::memcpy(npy.values.data(), data.data() + 10 + header_length, count * sizeof(float));
  return npy;
}

// A float EXR's channels, interleaved, first scan line (the top) first.
Npy ReadExr(const fs::path& path, const std::vector<std::string>& channels) {
  Imf::InputFile file(path.c_str());
  const auto window = file.header().dataWindow();
  const size_t width = window.max.x - window.min.x + 1, height = window.max.y - window.min.y + 1;
  Npy out{{height, width, channels.size()}, std::vector<float>(width * height * channels.size())};
  Imf::FrameBuffer frame;
  for (size_t c = 0; c < channels.size(); ++c) {
    EXPECT_NE(file.header().channels().findChannel(channels[c].c_str()), nullptr) << channels[c];
    frame.insert(channels[c].c_str(), Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(out.values.data() + c),
                                                 sizeof(float) * channels.size(),
                                                 sizeof(float) * channels.size() * width));
  }
  file.setFrameBuffer(frame);
  file.readPixels(window.min.y, window.max.y);
  return out;
}

// Width and height from a PNG's IHDR chunk.
std::pair<uint32_t, uint32_t> PngSize(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char header[24] = {};
  in.read(reinterpret_cast<char*>(header), sizeof(header));
  auto be32 = [&](int at) {
    return (uint32_t{header[at]} << 24) | (uint32_t{header[at + 1]} << 16) | (uint32_t{header[at + 2]} << 8) |
           header[at + 3];
  };
  return {be32(16), be32(20)};
}

class CliTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    repo_ = new ScratchDir();
    server_ = ServerProcess::Start({repo_->path(), {"--seed-samples"}}).release();
  }
  static void TearDownTestSuite() {
    delete server_;
    delete repo_;
  }
  void SetUp() override { ASSERT_NE(server_, nullptr); }
  static std::string Server() { return "--server " + server_->address(); }

  static ScratchDir* repo_;
  static ServerProcess* server_;
  ScratchDir scratch_;
};
ScratchDir* CliTest::repo_ = nullptr;
ServerProcess* CliTest::server_ = nullptr;

TEST_F(CliTest, GlobalFlagsGoBeforeOrAfterTheSubcommand) {
  for (const std::string& arguments : {Server() + " --json list", "list --json " + Server(), "--json list " + Server()}) {
    const CliRun run = Visq(arguments);
    ASSERT_EQ(run.exit_code, 0) << arguments << "\n" << run.output;
    EXPECT_EQ(nlohmann::json::parse(run.output)["scenes"][0]["name"], kScene) << arguments;
  }
}

TEST_F(CliTest, JsonWritesIntegersAsNumbersAndKeepsZeroFields) {
  const CliRun run = Visq(Server() + " info " + kScene + " --json");
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const auto json = nlohmann::json::parse(run.output);
  EXPECT_TRUE(json["triangle_count"].is_number_unsigned()) << run.output;
  EXPECT_EQ(json["triangle_count"], 36);
  EXPECT_TRUE(json["version"].is_number()) << run.output;
  // Fields at their zero value are printed, not left out.
  ASSERT_TRUE(json.contains("has_lightmap_uvs")) << run.output;
  EXPECT_EQ(json["has_lightmap_uvs"], false);
  ASSERT_TRUE(json["memory"].contains("gpu_bytes")) << run.output;
  EXPECT_TRUE(json["memory"]["gpu_bytes"].is_number());
  // Repeated messages and maps are converted too.
  const CliRun stats = Visq(Server() + " stats --json");
  ASSERT_EQ(stats.exit_code, 0) << stats.output;
  const auto s = nlohmann::json::parse(stats.output);
  ASSERT_FALSE(s["methods"].empty()) << stats.output;
  EXPECT_TRUE(s["methods"][0]["calls"].is_number()) << stats.output;
  EXPECT_TRUE(s["gpu_contexts_lost"].is_number()) << stats.output;
}

TEST_F(CliTest, UnknownEnumValuesAreRefusedNamingTheAllowedOnes) {
  const std::string patches = std::string(" --source '") + kCeilingSource + "' --receiver '" + kFloorUp + "'";
  struct Case {
    std::string arguments, message;
  };
  for (const Case& c : std::vector<Case>{
           {"hidden-map --scene x" + patches + " --method raycats", "'raycats' is not one of auto, raster, raycast, exact"},
           {"hidden-map --scene x" + patches + " --lookup fsat", "'fsat' is not one of exact, hough, fast"},
           {"patch-visibility --scene x" + patches + " --method rastr", "'rastr' is not one of auto, raster, raycast, exact"},
           {std::string("transmittance --scene x --light 0,-1,0 --absorber a=1 --receiver '") + kFloorUp +
                "' --light-kind spot",
            "'spot' is not one of directional, point"},
           {"volumetric --scene x --camera 0,1,3 --forward 0,0,-1 --method raymarch",
            "'raymarch' is not one of min-max, ray-marching"},
       }) {
    const CliRun run = Visq(Server() + " " + c.arguments);
    EXPECT_NE(run.exit_code, 0) << c.arguments;
    EXPECT_TRUE(Contains(run.output, c.message)) << c.arguments << "\n" << run.output;
  }
}

TEST_F(CliTest, AnUnknownSubcommandIsNamedWithTheNearestOne) {
  const CliRun run = Visq(Server() + " lsit");
  EXPECT_EQ(run.exit_code, 2);
  EXPECT_TRUE(Contains(run.output, "unknown subcommand 'lsit' (did you mean 'list'?)")) << run.output;
  const CliRun far = Visq("frobnicate --json");
  EXPECT_EQ(far.exit_code, 2);
  EXPECT_TRUE(Contains(far.output, "unknown subcommand 'frobnicate'")) << far.output;
  EXPECT_FALSE(Contains(far.output, "did you mean")) << far.output;
}

TEST_F(CliTest, LoadingAMissingFileSaysTheFileDoesNotExist) {
  const CliRun run = Visq(Server() + " load ./missing.gltf");
  EXPECT_NE(run.exit_code, 0);
  EXPECT_TRUE(Contains(run.output, "the file './missing.gltf' does not exist")) << run.output;
  // A bare name is still a repository scene.
  const CliRun name = Visq(Server() + " load " + kScene + " --replace");
  EXPECT_EQ(name.exit_code, 0) << name.output;
}

TEST_F(CliTest, AServerWithoutAPortMeansTheServersDefaultPort) {
  const CliRun run = Visq("--server localhost --timeout 2 list");
  // Another server may be listening there; otherwise the error says where
  // the CLI looked.
  if (run.exit_code != 0) {
    EXPECT_TRUE(Contains(run.output, "localhost:50051")) << run.output;
  }
  auto address = client::WithDefaultPort("localhost");
  ASSERT_TRUE(address.ok());
  EXPECT_EQ(*address, "localhost:50051");
  EXPECT_EQ(*client::WithDefaultPort("::1"), "[::1]:50051");
  EXPECT_EQ(*client::WithDefaultPort("[::1]:7"), "[::1]:7");
  EXPECT_EQ(*client::WithDefaultPort("unix:/tmp/visq.sock"), "unix:/tmp/visq.sock");
  EXPECT_FALSE(client::WithDefaultPort("host:99999").ok());
  const CliRun bad = Visq("--server host:x list");
  EXPECT_EQ(bad.exit_code, 2);
  EXPECT_TRUE(Contains(bad.output, "--server")) << bad.output;
}

TEST_F(CliTest, ADeadlineExceededNamesTimeout) {
  const CliRun run = Visq(Server() + " obscurance --scene " + kScene +
                       " --d-max 0.5 --resolution 64 --directions 4096 --timeout 0.3");
  EXPECT_EQ(run.exit_code, 1) << run.output;
  EXPECT_TRUE(Contains(run.output, "DEADLINE_EXCEEDED")) << run.output;
  EXPECT_TRUE(Contains(run.output, "--timeout")) << run.output;
  const CliRun help = Visq("--help");
  EXPECT_TRUE(Contains(help.output, "none for streams, bakes and uploads")) << help.output;
}

TEST_F(CliTest, StreamsHaveNoDeadlineOfTheirOwnUnlessGiven) {
  // What the CLI relies on: stream_deadline 0 lifts the single-call deadline
  // from streams (the CLI sets it unless --timeout is given).
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name(kScene);
  request.set_d_max(0.5);
  request.set_resolution(64);
  request.set_direction_count(512);
  // One method for both calls: with none named, the first call probes the
  // methods and the second runs the fastest (the ray caster's bake, within
  // 200 ms since its batches follow the rays), and the two are not alike.
  request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  const auto deadline = std::chrono::milliseconds(200);
  Client unbounded({.address = server_->address(), .deadline = deadline, .stream_deadline = std::chrono::milliseconds(0)});
  const auto start = std::chrono::steady_clock::now();
  auto bake = unbounded.ComputeObscurances(request);
  const auto took = std::chrono::steady_clock::now() - start;
  ASSERT_TRUE(bake.ok()) << bake.status();
  if (took <= deadline) GTEST_SKIP() << "the bake took less than the deadline on this GPU: nothing to tell apart";
  Client bounded({.address = server_->address(), .deadline = deadline});
  EXPECT_EQ(bounded.ComputeObscurances(request).status().code(), absl::StatusCode::kDeadlineExceeded);
}

TEST_F(CliTest, LightVisibilityPngNeedsAReceiver) {
  const fs::path points = scratch_.path() / "points.txt";
  std::ofstream(points) << "# x y z nx ny nz\n0 0.01 0 0 1 0\n0.5 0.01 0.5\n";
  const fs::path png = scratch_.path() / "out.png";
  const CliRun run = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight + "' --points " +
                       points.string() + " --png " + png.string());
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_TRUE(Contains(run.output, "--png, --npy, --exr: need --receiver")) << run.output;
  EXPECT_FALSE(fs::exists(png));
  EXPECT_FALSE(Contains(run.output, "wrote"));
  // Without --png the points are answered, one line each.
  const CliRun answered = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight +
                            "' --points " + points.string());
  ASSERT_EQ(answered.exit_code, 0) << answered.output;
  EXPECT_TRUE(Contains(answered.output, "2 points in 1 batch(es)")) << answered.output;
  // A line that is not a point is named.
  std::ofstream(points) << "0 0.01 0\n0 zero 0\n";
  const CliRun malformed = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight +
                             "' --points " + points.string());
  EXPECT_EQ(malformed.exit_code, 2);
  EXPECT_TRUE(Contains(malformed.output, "line 2")) << malformed.output;
}

TEST_F(CliTest, LightVisibilityStreamsLargeReceiversAndWritesThePng) {
  const fs::path png = scratch_.path() / "shadow.png", npy = scratch_.path() / "shadow.npy";
  const CliRun run = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight + "' --receiver '" +
                       kFloorUp + "' --width 300 --height 250 --png " + png.string() + " --npy " + npy.string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  EXPECT_TRUE(Contains(run.output, "75000 points in 2 batch(es)")) << run.output;
  EXPECT_EQ(PngSize(png), (std::pair<uint32_t, uint32_t>{300, 250}));
  const Npy fractions = ReadNpy(npy);
  ASSERT_EQ(fractions.shape, (std::vector<size_t>{250, 300}));
  // Row 0 of the array is the receiver's v = 0 row: the library's answer
  // for the same texel centres.
  v1::LightVisibilityRequest request;
  request.mutable_scene()->set_name(kScene);
  for (const auto& [x, z] : {std::pair{-0.25, -0.25}, {0.25, -0.25}, {0.25, 0.25}, {-0.25, 0.25}}) {
    auto* v = request.mutable_light()->add_vertices();
    v->set_x(x);
    v->set_y(1.99);
    v->set_z(z);
  }
  request.set_radiance(1);
  for (int x = 0; x < 300; ++x) {
    auto* point = request.add_points();
    // edge_u is (0, 0, 1.998), edge_v (1.998, 0, 0).
    point->mutable_position()->set_x(-0.999 + 1.998 * 0.5 / 250);
    point->mutable_position()->set_y(0.001);
    point->mutable_position()->set_z(-0.999 + 1.998 * (x + 0.5) / 300);
    point->mutable_normal()->set_y(1);
  }
  Client client({.address = server_->address()});
  auto answer = client.LightVisibility(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  double shadowed = 0;
  for (int x = 0; x < 300; ++x) {
    EXPECT_NEAR(fractions.values[x], answer->points(x).visible_fraction(), 1e-6) << "x " << x;
    shadowed += 1.0 - fractions.values[x];
  }
  EXPECT_GT(shadowed, 1.0) << "the tall box shadows the floor's first row";
}

TEST_F(CliTest, LightVisibilityRefusesAbsurdSizes) {
  const CliRun run = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight + "' --receiver '" +
                       kFloorUp + "' --width 100000 --height 100000");
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_TRUE(Contains(run.output, "--width, --height: 100000 x 100000; each must be in 1..4096")) << run.output;
}

TEST_F(CliTest, ALightFacingAwayFromEveryPointIsWarnedAbout) {
  const std::string clockwise = "-0.25,1.99,-0.25;-0.25,1.99,0.25;0.25,1.99,0.25;0.25,1.99,-0.25";
  const CliRun run = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + clockwise +
                       "' --receiver '" + kFloorUp + "' --width 4 --height 4");
  EXPECT_EQ(run.exit_code, 0) << run.output;
  EXPECT_TRUE(Contains(run.output, "warning: the light's front")) << run.output;
  EXPECT_TRUE(Contains(run.output, "faces away from every point")) << run.output;
  const CliRun facing = Visq(Server() + " light-visibility --scene " + kScene + " --light '" + kLight +
                          "' --receiver '" + kFloorUp + "' --width 4 --height 4");
  EXPECT_EQ(facing.exit_code, 0) << facing.output;
  EXPECT_FALSE(Contains(facing.output, "warning")) << facing.output;
}

TEST_F(CliTest, VoxelizePngKeepsTheBoxAspectRatio) {
  // Two triangles spanning x in [0, 1], y in [0, 1], z in [0, 3].
  const fs::path folder = scratch_.path() / "slab";
  fs::create_directories(folder);
  const float positions[] = {0, 0, 0, 1, 0, 0, 0, 0, 3, 1, 1, 3};
  const uint16_t indices[] = {0, 1, 2, 1, 3, 2};
  {
    std::ofstream bin(folder / "slab.bin", std::ios::binary);
    bin.write(reinterpret_cast<const char*>(positions), sizeof(positions));
    bin.write(reinterpret_cast<const char*>(indices), sizeof(indices));
  }
  std::ofstream(folder / "slab.gltf") << R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
    "nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
    "buffers": [{"uri": "slab.bin", "byteLength": 60}],
    "bufferViews": [{"buffer": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
    "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 3]},
                  {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]})";
  const CliRun load = Visq(Server() + " load " + (folder / "slab.gltf").string() + " --replace");
  ASSERT_EQ(load.exit_code, 0) << load.output;
  const fs::path png = scratch_.path() / "top.png", npy = scratch_.path() / "top.npy";
  const CliRun run = Visq(Server() + " voxelize --scene slab --axis 1 --width 64 --height 64 --slices 32 --json --png " +
                       png.string() + " --npy " + npy.string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const auto json = nlohmann::json::parse(run.output);
  const double extent_u = json["box"]["half_extent"]["x"], extent_v = json["box"]["half_extent"]["y"];
  const auto [width, height] = PngSize(png);
  ASSERT_GT(height, 0u);
  EXPECT_NEAR(double(width) / height, extent_u / extent_v, 0.05) << width << " x " << height;
  EXPECT_EQ(std::max(width, height), 64u) << "the finer axis keeps the grid's count";
  const Npy counts = ReadNpy(npy);
  ASSERT_EQ(counts.shape, (std::vector<size_t>{64, 64}));
  double occupied = 0;
  for (float c : counts.values) occupied += c;
  EXPECT_EQ(occupied, json["occupied_voxels"].get<double>());
  const CliRun help = Visq("voxelize --help");
  EXPECT_TRUE(Contains(help.output, "over the fullest column's")) << help.output;
}

// --errors-npy asks for want_errors: each texel's own bound, written as
// (height, width), 1 on texels filled from neighbours; the JSON's count of
// texels beyond the single bound is the server's own count, and a shard,
// which has no W, refuses the flag by name.
TEST_F(CliTest, ObscuranceErrorsNpyHoldsEachTexelsOwnBound) {
  const fs::path d = scratch_.path();
  const std::string bake = Server() + " obscurance --scene " + kScene + " --d-max 0.5 --resolution 32 --directions 16";
  const CliRun run = Visq(bake + " --json --errors-npy " + (d / "errors.npy").string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  // The progress bar (stderr, no braces) comes first.
  ASSERT_NE(run.output.find('{'), std::string::npos) << run.output;
  const auto json = nlohmann::json::parse(run.output.substr(run.output.find('{')));
  const Npy errors = ReadNpy(d / "errors.npy");
  ASSERT_EQ(errors.shape, (std::vector<size_t>{32, 32}));
  const double stated = json["figures"]["accuracy"]["error_bound"];
  size_t filled = 0, beyond = 0;
  for (float e : errors.values) {
    EXPECT_TRUE(e > 0.0f && e <= 1.0f) << e;
    filled += e == 1.0f;
    beyond += e > stated && e < 1.0f;
  }
  const auto& texel_errors = json["texel_errors"];
  EXPECT_EQ(texel_errors["beyond_error_bound"].get<double>(),
            json["figures"]["accuracy"]["parameters"]["texels_outside_bound"].get<double>());
  EXPECT_LE(beyond, texel_errors["beyond_error_bound"].get<size_t>()) << "estimated texels beyond, below 1";
  EXPECT_GT(filled, 0u) << "the atlas has gutter texels";
  EXPECT_LE(texel_errors["median"].get<double>(), stated) << "most texels are within the single bound";
  EXPECT_GE(texel_errors["max"].get<double>(), texel_errors["p95"].get<double>());
  // The human-readable line, and the flag in the help.
  const CliRun plain = Visq(bake + " --errors-npy " + (d / "plain.npy").string());
  ASSERT_EQ(plain.exit_code, 0) << plain.output;
  EXPECT_TRUE(Contains(plain.output, "own texel errors: median")) << plain.output;
  EXPECT_TRUE(Contains(Visq("obscurance --help").output, "--errors-npy"));
  const CliRun shard = Visq(bake + " --partial-out " + (d / "s.vqp").string() + " --errors-npy " +
                            (d / "s.npy").string());
  EXPECT_EQ(shard.exit_code, 2) << shard.output;
  EXPECT_TRUE(Contains(shard.output, "--partial-out: a shard has no W and no errors")) << shard.output;
  EXPECT_FALSE(fs::exists(d / "s.npy"));
}

TEST_F(CliTest, FarmBakeShardsMergeToTheWholeBakeBitForBit) {
  const fs::path d = scratch_.path();
  const std::string bake = Server() + " obscurance --scene " + kScene + " --d-max 0.5 --resolution 32";
  for (const std::string& arguments :
       {bake + " --directions 8 --partial-out " + (d / "whole.vqp").string(),
        bake + " --directions 3 --total-directions 8 --partial-out " + (d / "a.vqp").string(),
        bake + " --first-direction 3 --directions 5 --total-directions 8 --partial-out " + (d / "b.vqp").string(),
        bake + " --directions 8 --method depth-peeling --npy " + (d / "whole.npy").string()}) {
    const CliRun run = Visq(arguments);
    ASSERT_EQ(run.exit_code, 0) << arguments << "\n" << run.output;
  }
  const CliRun merge = Visq("obscurance-merge " + (d / "b.vqp").string() + " " + (d / "a.vqp").string() + " --out " +
                            (d / "merged.vqp").string() + " --npy " + (d / "merged.npy").string());
  ASSERT_EQ(merge.exit_code, 0) << merge.output;
  EXPECT_TRUE(Contains(merge.output, "directions [0, 8) of 8 (complete)")) << merge.output;
  auto bytes = [](const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  };
  EXPECT_EQ(bytes(d / "merged.vqp"), bytes(d / "whole.vqp")) << "the merged sums differ from one bake's";
  // W from the merged sums is the whole bake's on every texel a direction
  // reached; the others are NaN (the server fills them from neighbours).
  const Npy merged = ReadNpy(d / "merged.npy"), whole = ReadNpy(d / "whole.npy");
  ASSERT_EQ(merged.shape, (std::vector<size_t>{32, 32, 3}));
  ASSERT_EQ(whole.shape, merged.shape);
  size_t estimated = 0;
  for (size_t i = 0; i < merged.values.size(); ++i)
    if (!std::isnan(merged.values[i])) {
      ++estimated;
      EXPECT_EQ(merged.values[i], whole.values[i]) << "value " << i;
    }
  EXPECT_GT(estimated, 0u);
  // Overlapping, truncated and foreign shards are refused by name.
  const CliRun twice = Visq("obscurance-merge " + (d / "a.vqp").string() + " " + (d / "a.vqp").string() + " --out " +
                            (d / "x.vqp").string());
  EXPECT_EQ(twice.exit_code, 2);
  EXPECT_TRUE(Contains(twice.output, "direction ranges overlap")) << twice.output;
  EXPECT_FALSE(fs::exists(d / "x.vqp"));
  std::ofstream(d / "short.vqp", std::ios::binary) << bytes(d / "a.vqp").substr(0, 100);
  std::ofstream(d / "foreign.vqp", std::ios::binary) << "not a shard at all";
  {
    // A header claiming an atlas whose size arithmetic would wrap around.
    std::ofstream huge(d / "huge.vqp", std::ios::binary);
    const uint64_t fingerprint = 1;
    const uint32_t header[7] = {0x80000000u, 0x80000000u, 3, 8, 1, 0, 8};
    huge.write("VISQOBP1", 8);
    huge.write(reinterpret_cast<const char*>(&fingerprint), sizeof(fingerprint));
    huge.write(reinterpret_cast<const char*>(header), sizeof(header));
  }
  for (const char* name : {"short.vqp", "foreign.vqp", "huge.vqp"}) {
    const CliRun bad = Visq("obscurance-merge " + (d / name).string() + " --npy " + (d / "bad.npy").string());
    EXPECT_EQ(bad.exit_code, 2) << name;
    EXPECT_TRUE(Contains(bad.output, "not a visq obscurance partial")) << bad.output;
  }
}

// What --progress wrote on stderr for `what`: each line is either the time
// worked (before the stream has told anything) or a bar of the parts
// arrived; returns the bars' (done, total) in order and checks each line's
// form and the bar's length against its count.
std::vector<std::pair<uint64_t, uint64_t>> ProgressBars(const std::string& output, const std::string& what,
                                                        const std::string& unit) {
  const std::regex worked("^" + what + R"(: the server has worked [0-9]+ s$)");
  const std::regex bar("^" + what + R"(: \[([= ]{30})\] ([0-9]+)/([0-9]+) )" + unit +
                       R"(, [0-9.]+ s(, ~[0-9.]+ s left)?$)");
  std::vector<std::pair<uint64_t, uint64_t>> bars;
  std::istringstream in(output);
  for (std::string line; std::getline(in, line);) {
    if (line.rfind(what + ": ", 0) != 0) continue;
    std::smatch m;
    if (std::regex_match(line, m, bar)) {
      const uint64_t done = std::stoull(m[2]), total = std::stoull(m[3]);
      EXPECT_EQ(std::count(m[1].first, m[1].second, '='), static_cast<long>(30 * done / total)) << line;
      bars.emplace_back(done, total);
    } else {
      EXPECT_TRUE(std::regex_match(line, worked)) << "not a progress line: '" << line << "'";
      EXPECT_TRUE(bars.empty()) << "the time worked after a bar: '" << line << "'";
    }
  }
  return bars;
}

// A map, a voxelization and a light-visibility run long enough to report
// (over a second here) show a bar of what their streams have delivered: a
// map's bands of texels, a grid's bands of rows, the light's batches of
// points; the counts only grow, and the last line has everything. Without
// --progress (and not on a terminal) nothing is said.
TEST_F(CliTest, LongCallsShowAProgressBarOfWhatTheirStreamsDelivered) {
  struct Long {
    std::string what, unit, arguments;
    uint64_t total;
  };
  const std::vector<Long> calls = {
      // About 3 s of Embree rays on two cores, in bands of 16 rows.
      {"hidden-map", "texels",
       std::string("hidden-map --scene ") + kScene + " --source '" + kCeilingSource + "' --receiver '" + kFloorUp +
           "' --width 256 --height 256 --samples 1024 --method raycast",
       256 * 256},
      // About 1.6 s of llvmpipe, in bands of rows.
      {"voxelize", "rows", std::string("voxelize --scene ") + kScene + " --width 768 --height 768 --slices 64 --conservative",
       768},
      // About 1.2 s, 7 batches of 65536 points.
      {"light-visibility", "points",
       std::string("light-visibility --scene ") + kScene + " --light '" + kLight + "' --receiver '" + kFloorUp +
           "' --width 640 --height 640 --png " + (scratch_.path() / "light.png").string(),
       640 * 640},
  };
  int reported = 0;
  for (const Long& call : calls) {
    SCOPED_TRACE(call.what);
    const auto start = std::chrono::steady_clock::now();
    const CliRun run = Visq(Server() + " --progress " + call.arguments);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    ASSERT_EQ(run.exit_code, 0) << run.output;
    const auto bars = ProgressBars(run.output, call.what, call.unit);
    if (seconds < 1.3) {
      RecordProperty(call.what, "too short here to report on");
      continue;
    }
    ++reported;
    ASSERT_FALSE(bars.empty()) << run.output;
    for (size_t i = 0; i < bars.size(); ++i) {
      EXPECT_EQ(bars[i].second, call.total) << run.output;
      if (i > 0) {
        EXPECT_GE(bars[i].first, bars[i - 1].first) << run.output;
      }
    }
    EXPECT_EQ(bars.back().first, call.total) << "the last line has everything\n" << run.output;
    std::printf("%s: %.1f s, %zu progress line(s)\n", call.what.c_str(), seconds, bars.size());
    // The quiet run once: the three share the reporting.
    if (reported > 1) continue;
    const CliRun quiet = Visq(Server() + " " + call.arguments);
    ASSERT_EQ(quiet.exit_code, 0) << quiet.output;
    EXPECT_FALSE(Contains(quiet.output, call.what + ": ")) << quiet.output;
  }
  if (reported == 0) GTEST_SKIP() << "every call took under 1.3 s here: too short to report on";
}

TEST_F(CliTest, FloatImagesAreWrittenAsOpenExr) {
  const fs::path d = scratch_.path();
  const CliRun map = Visq(Server() + " hidden-map --scene " + kScene + " --source '" + kCeilingSource +
                          "' --receiver '" + kFloorUp + "' --width 12 --height 8 --samples 64 --npy " +
                          (d / "map.npy").string() + " --exr " + (d / "map.exr").string());
  ASSERT_EQ(map.exit_code, 0) << map.output;
  const Npy npy = ReadNpy(d / "map.npy"), exr = ReadExr(d / "map.exr", {"Y"});
  ASSERT_EQ(exr.shape, (std::vector<size_t>{8, 12, 1}));
  // The EXR is laid out as the PNG: the receiver's v = 1 row on top.
  for (size_t y = 0; y < 8; ++y)
    for (size_t x = 0; x < 12; ++x) EXPECT_EQ(exr.values[(7 - y) * 12 + x], npy.values[y * 12 + x]) << x << ", " << y;
  const CliRun image = Visq(Server() + " volumetric --scene " + kScene +
                            " --camera 0,1,3.5 --forward 0,0,-1 --width 16 --height 12 --shadow-map 128 --npy " +
                            (d / "shafts.npy").string() + " --exr " + (d / "shafts.exr").string());
  ASSERT_EQ(image.exit_code, 0) << image.output;
  const Npy rgb = ReadExr(d / "shafts.exr", {"R", "G", "B"}), rgb_npy = ReadNpy(d / "shafts.npy");
  EXPECT_EQ(rgb.shape, rgb_npy.shape);
  EXPECT_EQ(rgb.values, rgb_npy.values);
}

TEST_F(CliTest, HiddenMapNpyHoldsTheClientsFractions) {
  const fs::path npy = scratch_.path() / "map.npy";
  const CliRun run = Visq(Server() + " hidden-map --scene " + kScene + " --source '" + kCeilingSource +
                       "' --receiver '" + kFloorUp + "' --width 24 --height 16 --samples 64 --npy " + npy.string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const Npy map = ReadNpy(npy);
  ASSERT_EQ(map.shape, (std::vector<size_t>{16, 24}));
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name(kScene);
  auto set = [](v1::Vec3* v, double x, double y, double z) {
    v->set_x(x);
    v->set_y(y);
    v->set_z(z);
  };
  set(request.mutable_source()->mutable_origin(), -0.25, 1.99, -0.25);
  set(request.mutable_source()->mutable_edge_u(), 0.5, 0, 0);
  set(request.mutable_source()->mutable_edge_v(), 0, 0, 0.5);
  set(request.mutable_receiver()->mutable_origin(), -0.999, 0.001, -0.999);
  set(request.mutable_receiver()->mutable_edge_u(), 0, 0, 1.998);
  set(request.mutable_receiver()->mutable_edge_v(), 1.998, 0, 0);
  request.mutable_samples()->set_count(64);
  request.mutable_samples()->set_seed(1);
  request.set_width(24);
  request.set_height(16);
  Client client({.address = server_->address()});
  auto answer = client.ComputeHiddenSampleMap(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  EXPECT_EQ(map.values, answer->visible_fraction);
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

// The fleet view against two real replicas sharing one repository, as in
// the Kubernetes Deployment: replica-a holds the seeded scene and an upload,
// replica-b the same upload (loaded from the repository) and one of its own.
TEST(CliFleet, StatsHaveARowPerReplicaAndTotalsAndListTheUnionWithItsHolders) {
  ScratchDir repo, files;
  auto a = ServerProcess::Start({repo.path(), {"--seed-samples", "--server-id", "replica-a"}});
  auto b = ServerProcess::Start({repo.path(), {"--no-preload", "--server-id", "replica-b"}});
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  // The seeded scene's files as a user has them (the repository keeps its
  // scenes as blobs).
  ASSERT_TRUE(WriteSampleScenes(files.path()).ok());
  fs::path gltf;
  for (const auto& entry : fs::directory_iterator(files.path() / kScene))
    if (entry.path().extension() == ".gltf" || entry.path().extension() == ".glb") gltf = entry.path();
  ASSERT_FALSE(gltf.empty()) << "no glTF file in the seeded " << kScene;
  for (const std::string& arguments :
       {"--server " + a->address() + " load " + gltf.string() + " --name shared_box",
        "--server " + b->address() + " load shared_box",
        "--server " + b->address() + " load " + gltf.string() + " --name only_b"}) {
    const CliRun run = Visq(arguments);
    ASSERT_EQ(run.exit_code, 0) << arguments << "\n" << run.output;
  }
  // replica-a twice (as localhost too): one row, both addresses.
  const std::string fleet = "--fleet " + a->address() + ",localhost:" + std::to_string(a->port()) + "," + b->address();

  const CliRun stats = Visq("stats --json " + fleet);
  ASSERT_EQ(stats.exit_code, 0) << stats.output;
  const auto s = nlohmann::json::parse(stats.output);
  ASSERT_EQ(s["replicas"].size(), 2u) << s.dump(2);
  EXPECT_EQ(s["replicas"][0]["server_id"], "replica-a");
  EXPECT_EQ(s["replicas"][0]["addresses"].size(), 2u) << s["replicas"][0]["addresses"];
  EXPECT_EQ(s["replicas"][1]["server_id"], "replica-b");
  // The totals are the rows' sums, from the same answers.
  uint64_t calls = 0, scenes = 0, cpu = 0;
  for (const auto& r : s["replicas"]) {
    for (const auto& m : r["stats"]["methods"]) calls += m["calls"].get<uint64_t>();
    scenes += r["stats"]["scenes_resident"].get<uint64_t>();
    cpu += r["stats"]["scene_memory"]["cpu_bytes"].get<uint64_t>();
  }
  const auto& totals = s["totals"];
  EXPECT_EQ(totals["replicas"], 2);
  EXPECT_EQ(totals["unreachable"], 0);
  EXPECT_EQ(totals["calls"], calls);
  EXPECT_GT(calls, 0u);
  EXPECT_EQ(totals["scenes_resident"], scenes);
  EXPECT_EQ(scenes, 4u) << "replica-a: the seeded scene and shared_box; replica-b: shared_box and only_b";
  EXPECT_EQ(totals["scene_memory"]["cpu_bytes"], cpu);
  EXPECT_EQ(totals["versions"].size(), 1u) << totals["versions"];

  const CliRun table = Visq("stats " + fleet);
  ASSERT_EQ(table.exit_code, 0) << table.output;
  for (const char* part : {"replica-a", "replica-b", "TOTAL", "2 of 2 answered", "RPC (fleet)"})
    EXPECT_TRUE(Contains(table.output, part)) << part << "\n" << table.output;

  const CliRun list = Visq("list --json " + fleet);
  ASSERT_EQ(list.exit_code, 0) << list.output;
  std::map<std::string, std::vector<std::string>> holders;
  const auto listed = nlohmann::json::parse(list.output);
  for (const auto& scene : listed["scenes"]) {
    const std::string name = scene["name"].get<std::string>();
    ASSERT_EQ(holders.count(name), 0u) << name << " listed twice (two versions?)\n" << list.output;
    holders[name] = scene["replicas"].get<std::vector<std::string>>();
  }
  ASSERT_EQ(holders.size(), 3u) << list.output;
  EXPECT_EQ(holders[kScene], (std::vector<std::string>{"replica-a"})) << list.output;
  EXPECT_EQ(holders["shared_box"], (std::vector<std::string>{"replica-a", "replica-b"})) << list.output;
  EXPECT_EQ(holders["only_b"], (std::vector<std::string>{"replica-b"})) << list.output;
  const CliRun list_table = Visq("list " + fleet);
  ASSERT_EQ(list_table.exit_code, 0) << list_table.output;
  EXPECT_TRUE(Contains(list_table.output, "replica-a, replica-b")) << list_table.output;

  // A replica that does not answer is a row saying so, the others are still
  // shown, and the command fails. The DNS form finds replica-b.
  const std::string partial_fleet = "--fleet " + a->address() + ",127.0.0.1:1 --fleet-dns " + b->address();
  int status = 0;
  const std::string json =
      testing::RunCommand(std::string(VISQ_CLI_BINARY) + " stats --json " + partial_fleet + " 2>/dev/null", &status);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 1) << json;
  const auto p = nlohmann::json::parse(json);
  ASSERT_EQ(p["replicas"].size(), 3u) << json;
  EXPECT_EQ(p["replicas"][1]["server_id"], "replica-b");
  EXPECT_EQ(p["replicas"][2]["address"], "127.0.0.1:1");
  EXPECT_EQ(p["replicas"][2]["error"]["code"], "UNAVAILABLE");
  EXPECT_EQ(p["totals"]["unreachable"], 1);
  const CliRun partial = Visq("stats " + partial_fleet);
  EXPECT_EQ(partial.exit_code, 1) << partial.output;
  EXPECT_TRUE(Contains(partial.output, "2 of 3 answered")) << partial.output;
  EXPECT_TRUE(Contains(partial.output, "visq: replica 127.0.0.1:1: UNAVAILABLE")) << partial.output;
  const CliRun unresolved = Visq("list --fleet-dns no-such-replica.invalid:50051");
  EXPECT_EQ(unresolved.exit_code, 1);
  EXPECT_TRUE(Contains(unresolved.output, "cannot resolve no-such-replica.invalid")) << unresolved.output;
}

}  // namespace
}  // namespace visq
