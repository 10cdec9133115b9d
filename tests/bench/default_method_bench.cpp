// The server's choice of method, measured: a suite of requests that name no
// method, each run through the real server beside the same request naming
// each method that gives the same answer (RASTER and RAYCAST for sampled
// visibility; DEPTH_PEELING and RAYCAST at the same bound for a bake). For
// every request it prints the chosen method's time over the fastest
// method's, on the first call (the probes of a fresh server included) and
// warm, and the cost model's predicted compute time beside the measured one.
// Every mode of a scene gets a fresh server of its own, so the first calls
// start from nothing; the requests of a scene then follow one another on it.
// Not a test: `--quick` (the Cornell box, small sizes) runs in ctest as a
// smoke test of the table.
//
//   visq_bench_default_method [--scenes ../shared/scenes] [--quick]
//   visq_bench_default_method --exact [--scenes ../shared/scenes]
//
// --exact: the exact method's predicted time (Accuracy.plans) against its
// measured one, per request with a target, on the shared scenes (Sponza,
// veach-ajar, the flowers, the bunny, and Sponza with a copy 1e5 away):
// each scene on a fresh server, two requests in a row (the second elsewhere
// in the scene, after the first taught the cost model), each followed by the
// same request naming PLUCKER_EXACT, which finds the trees and answers the
// target call's probes left, as the exact plan would have.
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <fstream>

#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using testing::ServerProcess;

void SetVec(v1::Vec3* v, double x, double y, double z) {
  v->set_x(x);
  v->set_y(y);
  v->set_z(z);
}
// A patch's origin, edge_u and edge_v.
using PatchSpec = std::array<std::array<double, 3>, 3>;
void SetPatch(v1::Patch* p, const PatchSpec& patch) {
  SetVec(p->mutable_origin(), patch[0][0], patch[0][1], patch[0][2]);
  SetVec(p->mutable_edge_u(), patch[1][0], patch[1][1], patch[1][2]);
  SetVec(p->mutable_edge_v(), patch[2][0], patch[2][1], patch[2][2]);
}

// What one call gave: the client's wall time, the method that ran, and the
// cost model's prediction beside the server's compute time.
struct Run {
  bool ok = false;
  std::string error;
  double wall_ms = 0.0;
  std::string method;
  double predicted_ms = 0.0;
  double compute_ms = 0.0;
  std::string weighed;  // each plan weighed, with its predicted ms
};

void NoteAccuracy(const v1::Accuracy& accuracy, Run& run) {
  run.method = accuracy.method();
  run.predicted_ms = accuracy.predicted_ms();
  for (const v1::PlanEstimate& plan : accuracy.plans()) {
    char text[96];
    std::snprintf(text, sizeof text, "%s%s %.1f ms", run.weighed.empty() ? "" : ", ", plan.method().c_str(),
                  plan.predicted_ms());
    run.weighed += text;
  }
  const size_t left_out = accuracy.note().find("not weighed");
  if (left_out != std::string::npos) run.weighed += "; " + accuracy.note().substr(left_out);
}

// What a call answered: its error, or what the accuracy and timing of
// `figures(answer)` state.
template <typename Answer, typename Figures>
void NoteAnswer(const Answer& answer, const Figures& figures, Run& run) {
  run.ok = answer.ok();
  if (!answer.ok()) {
    run.error = std::string(answer.status().message());
    return;
  }
  const auto& stated = figures(*answer);
  NoteAccuracy(stated.accuracy(), run);
  run.compute_ms = stated.timing().compute_ms();
}

// A request of the suite, sent with `mode` ("auto", or a method's name).
struct Row {
  std::string label;
  std::vector<std::string> modes;  // the methods that give the same answer
  std::function<Run(client::Client&, const std::string& mode)> call;
};

struct Scene {
  std::string name;
  std::filesystem::path file;  // empty: the server's generated sample scene
  std::vector<Row> rows;
};

template <typename Body>
Run Timed(Body body) {
  Run run;
  const auto start = std::chrono::steady_clock::now();
  body(run);
  run.wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return run;
}

v1::VisibilityMethod SampledMethod(const std::string& mode) {
  if (mode == "raster") return v1::RASTER;
  if (mode == "raycast") return v1::RAYCAST;
  return v1::METHOD_UNSPECIFIED;
}

Row MapRow(const std::string& scene, const PatchSpec& source, const PatchSpec& receiver, uint32_t side,
           uint32_t samples) {
  Row row;
  row.label = "map " + std::to_string(side) + "^2 N=" + std::to_string(samples);
  row.modes = {"raster", "raycast"};
  row.call = [=](client::Client& client, const std::string& mode) {
    return Timed([&](Run& run) {
      v1::HiddenSampleMapRequest request;
      request.mutable_scene()->set_name(scene);
      SetPatch(request.mutable_source(), source);
      SetPatch(request.mutable_receiver(), receiver);
      request.mutable_samples()->set_count(samples);
      request.mutable_samples()->set_seed(3);
      request.set_width(side);
      request.set_height(side);
      request.set_method(SampledMethod(mode));
      auto map = client.ComputeHiddenSampleMap(request);
      NoteAnswer(map, [](const auto& a) -> const auto& { return a.figures; }, run);
    });
  };
  return row;
}

Row PatchRow(const std::string& scene, const PatchSpec& source, const PatchSpec& receiver, uint32_t source_grid,
             uint32_t receiver_grid) {
  Row row;
  row.label = "patches " + std::to_string(source_grid) + "^2 x " + std::to_string(receiver_grid) + "^2";
  row.modes = {"raster", "raycast"};
  row.call = [=](client::Client& client, const std::string& mode) {
    return Timed([&](Run& run) {
      v1::PatchVisibilityRequest request;
      request.mutable_scene()->set_name(scene);
      SetPatch(request.mutable_source(), source);
      SetPatch(request.mutable_receiver(), receiver);
      request.set_source_columns(source_grid);
      request.set_source_rows(source_grid);
      request.set_receiver_columns(receiver_grid);
      request.set_receiver_rows(receiver_grid);
      request.set_method(SampledMethod(mode));
      auto answer = client.PatchVisibility(request);
      NoteAnswer(answer, [](const auto& a) -> const auto& { return a; }, run);
    });
  };
  return row;
}

Row BakeRow(const std::string& scene, uint32_t resolution, uint32_t directions) {
  Row row;
  row.label = "bake " + std::to_string(resolution) + " D=" + std::to_string(directions);
  row.modes = {"depth-peeling", "raycast"};
  row.call = [=](client::Client& client, const std::string& mode) {
    return Timed([&](Run& run) {
      v1::ComputeObscurancesRequest request;
      request.mutable_scene()->set_name(scene);
      request.set_resolution(resolution);
      request.set_d_max(1.0);
      if (mode == "raycast") {
        request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
        request.set_rays_per_patch(directions);
      } else {
        if (mode == "depth-peeling") request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
        request.set_direction_count(directions);
      }
      auto bake = client.ComputeObscurances(request);
      NoteAnswer(bake, [](const auto& a) -> const auto& { return a.figures; }, run);
    });
  };
  return row;
}

// Transmittance through one absorbing node under a directional light, for
// a receiver patch's side x side texels: the slicemap answers each for its
// light-view texel's centre ray, ray stabbing for its own ray, at least as
// tightly, so either may answer a request that names no method.
Row TransmittanceRow(const std::string& scene, const std::string& absorber, double absorption,
                     const std::array<double, 3>& light, const PatchSpec& receiver, uint32_t side) {
  Row row;
  row.label = "transmittance " + std::to_string(side) + "^2";
  row.modes = {"slicemap", "ray-stabbing"};
  row.call = [=](client::Client& client, const std::string& mode) {
    return Timed([&](Run& run) {
      v1::TransmittanceRequest request;
      request.mutable_scene()->set_name(scene);
      request.set_light_kind(v1::TransmittanceRequest::DIRECTIONAL);
      SetVec(request.mutable_light_direction(), light[0], light[1], light[2]);
      auto* a = request.add_absorbers();
      a->set_node(absorber);
      a->set_absorption(absorption);
      SetPatch(request.mutable_receiver(), receiver);
      request.set_receiver_width(side);
      request.set_receiver_height(side);
      if (mode == "slicemap") request.set_method(v1::TransmittanceRequest::SLICEMAP);
      if (mode == "ray-stabbing") request.set_method(v1::TransmittanceRequest::RAY_STABBING);
      auto answer = client.Transmittance(request);
      NoteAnswer(answer, [](const auto& a) -> const auto& { return a; }, run);
    });
  };
  return row;
}

std::vector<Scene> Suite(const std::optional<std::filesystem::path>& shared, bool quick) {
  std::vector<Scene> scenes;
  {
    // The generated Cornell box: the ceiling light onto the floor.
    const PatchSpec light = {{{-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5}}};
    const PatchSpec floor = {{{-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998}}};
    Scene cornell{"cornell_box_visq", {}, {}};
    cornell.rows.push_back(MapRow(cornell.name, light, floor, 8, 32));
    cornell.rows.push_back(MapRow(cornell.name, light, floor, 64, 256));
    cornell.rows.push_back(PatchRow(cornell.name, light, floor, 16, 16));
    cornell.rows.push_back(BakeRow(cornell.name, 32, 16));
    cornell.rows.push_back(TransmittanceRow(cornell.name, "short_box", 2.0, {0, -1, 0}, floor, quick ? 32 : 64));
    if (!quick) {
      cornell.rows.push_back(MapRow(cornell.name, light, floor, 256, 1024));
      cornell.rows.push_back(BakeRow(cornell.name, 128, 128));
    }
    scenes.push_back(std::move(cornell));
  }
  if (quick || !shared) return scenes;
  {
    // Sponza: the sky patch over the atrium floor.
    const PatchSpec sky = {{{-5, 14, -2}, {10, 0, 0}, {0, 0, 4}}};
    const PatchSpec floor = {{{-16, 0.2, -7}, {0, 0, 14}, {32, 0, 0}}};
    Scene sponza{"sponza", *shared / "sponza_dabrovic/sponza.gltf", {}};
    for (auto [side, samples] : std::vector<std::pair<uint32_t, uint32_t>>{{8, 32}, {64, 256}, {128, 1024}, {256, 256}})
      sponza.rows.push_back(MapRow(sponza.name, sky, floor, side, samples));
    sponza.rows.push_back(PatchRow(sponza.name, sky, floor, 32, 32));
    // Sponza's 5,624 atlas charts need 512 texels across.
    sponza.rows.push_back(BakeRow(sponza.name, 512, 16));
    sponza.rows.push_back(BakeRow(sponza.name, 512, 64));
    scenes.push_back(std::move(sponza));
  }
  {
    // The flowers: thin occluders under a light above the vases.
    const PatchSpec light = {{{-0.1, 0.35, -0.15}, {0.3, 0, 0}, {0, 0, 0.25}}};
    const PatchSpec floor = {{{-0.15, 0.001, -0.2}, {0, 0, 0.35}, {0.45, 0, 0}}};
    Scene flowers{"flowers", *shared / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf", {}};
    flowers.rows.push_back(MapRow(flowers.name, light, floor, 64, 256));
    flowers.rows.push_back(MapRow(flowers.name, light, floor, 128, 1024));
    flowers.rows.push_back(BakeRow(flowers.name, 256, 32));
    scenes.push_back(std::move(flowers));
  }
  {
    // The bunny as an absorber (69K triangles, open at its base), lit from
    // the side: a receiver through it.
    const PatchSpec receiver = {{{-0.12, 0.03, 0.0}, {0.2, 0, 0}, {0, 0.17, 0}}};
    Scene bunny{"bunny", *shared / "bunny/bunny.gltf", {}};
    for (const uint32_t side : {96u, 512u})
      bunny.rows.push_back(TransmittanceRow(bunny.name, "bunny", 20.0, {1, -0.3, 0.2}, receiver, side));
    scenes.push_back(std::move(bunny));
  }
  return scenes;
}

struct Measured {
  Run first, warm;
};

// --exact: one target request, then the exact method on the same request.
struct ExactRequest {
  std::string label;
  PatchSpec light, receiver;
};
struct ExactScene {
  std::string name;
  std::filesystem::path file;
  std::vector<ExactRequest> requests;
};

// Sponza with a second copy of its whole hierarchy 1e5 m away in x, the
// copies' nodes sharing the meshes (a glTF beside a link to sponza.bin).
std::optional<std::filesystem::path> WriteFarCopies(const std::filesystem::path& sponza_dir,
                                                    const std::filesystem::path& out_dir) {
  std::ifstream in(sponza_dir / "sponza.gltf");
  if (!in) return std::nullopt;
  nlohmann::json gltf = nlohmann::json::parse(in, nullptr, false);
  if (gltf.is_discarded()) return std::nullopt;
  nlohmann::json& nodes = gltf["nodes"];
  const size_t count = nodes.size();
  const int root = gltf["scenes"][0]["nodes"][0].get<int>();
  for (size_t i = 0; i < count; ++i) {
    nlohmann::json copy = nodes[i];
    if (copy.contains("children"))
      for (auto& child : copy["children"]) child = child.get<int>() + int(count);
    if (int(i) == root) {
      copy["name"] = "far copy";
      copy["matrix"][12] = copy["matrix"][12].get<double>() + 1e5;
    }
    nodes.push_back(copy);
  }
  gltf["scenes"][0]["nodes"].push_back(root + int(count));
  std::filesystem::create_directories(out_dir);
  std::error_code ec;
  std::filesystem::create_symlink(std::filesystem::absolute(sponza_dir / "sponza.bin"), out_dir / "sponza.bin", ec);
  std::ofstream(out_dir / "sponza_far.gltf") << gltf.dump();
  return out_dir / "sponza_far.gltf";
}

std::vector<ExactScene> ExactSuite(const std::filesystem::path& shared, const std::filesystem::path& scratch) {
  std::vector<ExactScene> scenes;
  const PatchSpec sky = {{{-5, 14, -2}, {10, 0, 0}, {0, 0, 4}}};
  const PatchSpec atrium = {{{-16, 0.2, -7}, {0, 0, 14}, {32, 0, 0}}};
  const PatchSpec corner = {{{-12, 0.2, -5}, {0, 0, 6}, {8, 0, 0}}};
  scenes.push_back({"sponza", shared / "sponza_dabrovic/sponza.gltf",
                    {{"atrium", sky, atrium}, {"corner", sky, corner}}});
  const PatchSpec veach_light = {{{-2.34, 3.23, -4.73}, {2.46, 0, 0}, {0, 0, 2.46}}};
  scenes.push_back({"veach-ajar", shared / "interior_veach_ajar/veach_ajar.gltf",
                    {{"floor", veach_light, {{{-7.94, 0.67, -6.78}, {13.7, 0, 0}, {0, 0, 6.56}}}},
                     {"near the door", veach_light, {{{-4, 0.67, -6}, {6, 0, 0}, {0, 0, 4}}}}}});
  const PatchSpec flowers_floor = {{{-0.15, 0.001, -0.2}, {0, 0, 0.35}, {0.45, 0, 0}}};
  scenes.push_back({"flowers", shared / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf",
                    {{"wide light", {{{-0.1, 0.35, -0.15}, {0.3, 0, 0}, {0, 0, 0.25}}}, flowers_floor},
                     {"small light", {{{0.0, 0.4, -0.1}, {0.2, 0, 0}, {0, 0, 0.2}}}, flowers_floor}}});
  const PatchSpec bunny_floor = {{{-0.2, 0.03, -0.2}, {0, 0, 0.4}, {0.4, 0, 0}}};
  scenes.push_back({"bunny", shared / "bunny/bunny.gltf",
                    {{"above", {{{-0.05, 0.3, -0.05}, {0.1, 0, 0}, {0, 0, 0.1}}}, bunny_floor},
                     {"aside", {{{0.05, 0.25, 0.0}, {0.08, 0, 0}, {0, 0, 0.08}}}, bunny_floor}}});
  if (std::optional<std::filesystem::path> far = WriteFarCopies(shared / "sponza_dabrovic", scratch / "far")) {
    PatchSpec far_sky = sky, far_atrium = atrium;
    far_sky[0][0] += 1e5;
    far_atrium[0][0] += 1e5;
    scenes.push_back({"sponza_far", *far, {{"atrium", sky, atrium}, {"atrium at 1e5", far_sky, far_atrium}}});
  }
  return scenes;
}

v1::HiddenSampleMapRequest ExactMapRequest(const std::string& scene, const ExactRequest& r, uint32_t side) {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name(scene);
  SetPatch(request.mutable_source(), r.light);
  SetPatch(request.mutable_receiver(), r.receiver);
  request.set_width(side);
  request.set_height(side);
  return request;
}

int RunExactPredictions(const std::filesystem::path& shared, uint32_t side, double max_error, const std::string& only,
                        bool verbose) {
  visq::testing::ScratchDir scratch;
  std::printf("%-14s %-14s %-22s %10s %10s %8s | %10s %12s %8s\n", "scene", "request", "target chose", "exact pred",
              "exact meas", "pred/meas", "chosen ms", "exact/chosen", "probes");
  int within = 0, rows = 0, failures = 0;
  for (const ExactScene& scene : ExactSuite(shared, scratch.path())) {
    if (!only.empty() && scene.name != only) continue;
    visq::testing::ScratchDir repo;
    std::vector<std::string> flags;
    if (verbose) flags = {"--log-level", "debug"};
    auto server = ServerProcess::Start({repo.path(), flags});
    if (!server) return 1;
    client::ClientOptions options;
    options.address = server->address();
    options.deadline = std::chrono::minutes(30);
    options.stream_deadline = std::chrono::milliseconds(0);
    client::Client client(options);
    auto info = client.UploadScene(scene.file, scene.name);
    if (!info.ok()) {
      std::fprintf(stderr, "%s: upload failed: %s\n", scene.name.c_str(), std::string(info.status().message()).c_str());
      ++failures;
      continue;
    }
    for (const ExactRequest& r : scene.requests) {
      v1::HiddenSampleMapRequest request = ExactMapRequest(scene.name, r, side);
      request.mutable_target()->set_max_error(max_error);
      const auto start = std::chrono::steady_clock::now();
      auto target = client.ComputeHiddenSampleMap(request);
      const double target_wall = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
      if (!target.ok()) {
        std::printf("%-14s %-14s failed: %s\n", scene.name.c_str(), r.label.c_str(),
                    std::string(target.status().message()).c_str());
        ++failures;
        continue;
      }
      const v1::Accuracy& accuracy = target->figures.accuracy();
      double exact_predicted = -1.0;
      for (const v1::PlanEstimate& plan : accuracy.plans())
        if (plan.method() == "plucker-exact") exact_predicted = plan.predicted_ms();
      const double chosen_ms = target->figures.timing().compute_ms();
      double exact_measured = chosen_ms;
      if (accuracy.method() != "plucker-exact") {
        v1::HiddenSampleMapRequest exact = ExactMapRequest(scene.name, r, side);
        exact.set_method(v1::PLUCKER_EXACT);
        auto answer = client.ComputeHiddenSampleMap(exact);
        if (!answer.ok()) {
          std::printf("%-14s %-14s exact failed: %s\n", scene.name.c_str(), r.label.c_str(),
                      std::string(answer.status().message()).c_str());
          ++failures;
          continue;
        }
        exact_measured = answer->figures.timing().compute_ms();
      }
      const double q = exact_predicted / exact_measured;
      ++rows;
      within += q >= 0.5 && q <= 2.0;
      std::string chose = accuracy.method();
      if (accuracy.parameters().contains("samples"))
        chose += " " + std::to_string(int(accuracy.parameters().at("samples")));
      std::printf("%-14s %-14s %-22s %10.1f %10.1f %8.2f | %10.1f %12.2f %8.0f\n", scene.name.c_str(),
                  r.label.c_str(), chose.c_str(), exact_predicted, exact_measured, q, chosen_ms,
                  accuracy.method() == "plucker-exact" ? 1.0 : exact_measured / chosen_ms,
                  target_wall - chosen_ms);
      std::fflush(stdout);
    }
    if (verbose) {
      // The server's own account of its exact probes (VISQ_LOG_LEVEL=debug).
      const std::string log = server->Log();
      for (size_t at = log.find("exact probes"); at != std::string::npos; at = log.find("exact probes", at + 1))
        std::printf("    %s\n", log.substr(at, log.find('\n', at) - at).c_str());
    }
  }
  std::printf("\n%d requests (%d failed), %ux%u, target +-%.3f: the exact plan's prediction within 2x of its "
              "measured time: %d of %d\n", rows, failures, side, side, max_error, within, rows);
  return failures == 0 ? 0 : 1;
}

}  // namespace
}  // namespace visq

int main(int argc, char** argv) {
  using namespace visq;
  CLI::App app{"visq: the server's choice of method against the fastest, per request"};
  std::string scenes_dir;
  bool quick = false;
  app.add_option("--scenes", scenes_dir, "the shared scenes (default: ../shared/scenes when present)");
  app.add_flag("--quick", quick, "the Cornell box at small sizes (the ctest smoke run)");
  std::string only;
  bool verbose = false;
  app.add_flag("--verbose", verbose, "print the plans each of auto's calls weighed");
  app.add_option("--only", only, "run the requests of this scene alone (cornell_box_visq, sponza, flowers, bunny)");
  double pause_ms = 0.0;
  app.add_option("--pause-ms", pause_ms,
                 "idle time after every call, in every mode (an editor's user between requests); the server "
                 "probes in idle time what no request's share could pay for");
  bool explore_when_idle = true;
  app.add_option("--explore-when-idle", explore_when_idle, "the servers' --explore-when-idle");
  bool exact = false;
  uint32_t exact_side = 32;
  double exact_error = 0.02;
  app.add_flag("--exact", exact, "the exact method's predicted time against its measured one (the shared scenes)");
  app.add_option("--exact-side", exact_side, "--exact: the map's side in texels");
  app.add_option("--exact-error", exact_error, "--exact: the target's max_error");
  CLI11_PARSE(app, argc, argv);
  std::optional<std::filesystem::path> shared;
  if (!scenes_dir.empty() && std::filesystem::exists(scenes_dir)) shared = scenes_dir;
  if (!shared) shared = visq::testing::SharedScenesDir();
  if (exact) {
    if (!shared) {
      std::printf("--exact: the shared scenes are absent: nothing measured\n");
      return 77;
    }
    return RunExactPredictions(*shared, exact_side, exact_error, only, verbose);
  }

  std::vector<Scene> suite = Suite(shared, quick);
  if (!only.empty())
    std::erase_if(suite, [&](const Scene& scene) { return scene.name != only; });
  std::printf("%-26s %-22s %9s %9s | %9s %9s | %s\n", "request", "auto chose", "first x", "warm x", "pred ms",
              "comp ms", "each method's first / warm ms (auto's first)");
  int rows = 0, failures = 0, predictions = 0, predictions_within_2x = 0;
  uint64_t idle_probes = 0, idle_preempted = 0;
  double idle_ms = 0.0;
  double worst_first = 0.0, worst_warm = 0.0;
  for (const Scene& scene : suite) {
    std::vector<std::string> modes = {"auto"};
    for (const Row& row : scene.rows)
      for (const std::string& m : row.modes)
        if (std::find(modes.begin(), modes.end(), m) == modes.end()) modes.push_back(m);
    // mode -> row -> first and warm runs, each mode on a fresh server.
    std::map<std::string, std::vector<Measured>> by_mode;
    for (const std::string& mode : modes) {
      visq::testing::ScratchDir repo;
      auto server = ServerProcess::Start(
          {repo.path(), {"--seed-samples", explore_when_idle ? "--explore-when-idle=true" : "--explore-when-idle=false"}});
      if (!server) {
        std::fprintf(stderr, "the server did not start\n");
        return 1;
      }
      client::ClientOptions options;
      options.address = server->address();
      options.deadline = std::chrono::minutes(30);
      options.stream_deadline = std::chrono::milliseconds(0);
      client::Client client(options);
      if (!scene.file.empty()) {
        auto info = client.UploadScene(scene.file, scene.name);
        if (!info.ok()) {
          std::fprintf(stderr, "%s: upload failed: %s\n", scene.name.c_str(), std::string(info.status().message()).c_str());
          return 1;
        }
      }
      for (const Row& row : scene.rows) {
        Measured m;
        const bool runs = mode == "auto" || std::find(row.modes.begin(), row.modes.end(), mode) != row.modes.end();
        const auto pause = [&] {
          std::this_thread::sleep_for(std::chrono::microseconds(static_cast<int64_t>(pause_ms * 1000.0)));
        };
        if (runs) {
          m.first = row.call(client, mode);
          pause();
          m.warm = row.call(client, mode);
          pause();
        }
        by_mode[mode].push_back(m);
      }
      if (mode == "auto") {
        if (auto stats = client.GetStats(); stats.ok() && stats->has_idle_exploration()) {
          idle_probes += stats->idle_exploration().probes_run();
          idle_preempted += stats->idle_exploration().probes_preempted();
          idle_ms += stats->idle_exploration().total_ms();
        }
      }
    }
    for (size_t r = 0; r < scene.rows.size(); ++r) {
      const Row& row = scene.rows[r];
      const Measured& chosen = by_mode["auto"][r];
      ++rows;
      if (!chosen.first.ok || !chosen.warm.ok) {
        ++failures;
        std::printf("%-26s failed: %s\n", (scene.name + " " + row.label).c_str(),
                    (chosen.first.ok ? chosen.warm.error : chosen.first.error).c_str());
        continue;
      }
      double best_first = 1e300, best_warm = 1e300;
      std::string each;
      for (const std::string& m : row.modes) {
        const Measured& x = by_mode[m][r];
        if (!x.first.ok || !x.warm.ok) {
          each += " " + m + " failed";
          continue;
        }
        best_first = std::min(best_first, x.first.wall_ms);
        best_warm = std::min(best_warm, x.warm.wall_ms);
        char text[96];
        std::snprintf(text, sizeof text, " %s %.0f / %.0f", m.c_str(), x.first.wall_ms, x.warm.wall_ms);
        each += text;
      }
      char text[64];
      std::snprintf(text, sizeof text, " (auto %.0f / %.0f)", chosen.first.wall_ms, chosen.warm.wall_ms);
      each += text;
      const double first_ratio = chosen.first.wall_ms / best_first, warm_ratio = chosen.warm.wall_ms / best_warm;
      worst_first = std::max(worst_first, first_ratio);
      worst_warm = std::max(worst_warm, warm_ratio);
      // The warm call's prediction (the first's may rest on probes alone).
      if (chosen.warm.predicted_ms > 0 && chosen.warm.compute_ms > 0) {
        ++predictions;
        const double q = chosen.warm.predicted_ms / chosen.warm.compute_ms;
        predictions_within_2x += q <= 2.0 && q >= 0.5;
      }
      std::printf("%-26s %-22s %9.2f %9.2f | %9.1f %9.1f |%s\n", (scene.name + " " + row.label).c_str(),
                  chosen.warm.method.c_str(), first_ratio, warm_ratio, chosen.warm.predicted_ms,
                  chosen.warm.compute_ms, each.c_str());
      if (verbose)
        std::printf("    first: %s\n    warm:  %s\n", chosen.first.weighed.c_str(), chosen.warm.weighed.c_str());
    }
  }
  std::printf("\n%d requests (%d failed): the chosen method's time over the fastest, worst %.2fx on the first call "
              "(probes included), %.2fx warm; predictions within 2x of the compute time: %d of %d\n",
              rows, failures, worst_first, worst_warm, predictions_within_2x, predictions);
  std::printf("the auto servers' idle-time probes (%.0f ms paused after each call): %llu run, %llu stopped by a "
              "call, %.0f ms\n",
              pause_ms, static_cast<unsigned long long>(idle_probes), static_cast<unsigned long long>(idle_preempted),
              idle_ms);
  return failures == 0 ? 0 : 1;
}
