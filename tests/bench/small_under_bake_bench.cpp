// Small queries under a bake (issue 44 §2): 8 x 8 hidden-sample maps of the
// Cornell box from N concurrent clients, alone and while one depth-peeling
// bake of Sponza runs, through the real server on loopback. Prints each
// phase's p50 / p99 / max latency and throughput, and the two ratios the
// issue sets goals for:
//   - p99 with the bake over (one bake GL job + the map's own p50 alone at
//     the same N): goal at most 3;
//   - throughput with the bake over throughput alone: goal at least 1/4.
// The bake is far longer than a phase; its stream deadline ends it just
// after the phase, and a bake that ended before the phase did makes the
// phase's figures void (said so in the table). Not a test: figures only.
//
//   visq_bench_small_under_bake [--scenes ../shared/scenes] [--clients 1,8] [--seconds 5]
//                               [--method raster|raycast|auto] [--bake-resolution 1024] [--server HOST:PORT]
// --server: a running server that holds cornell_box_visq and sponza
// (otherwise the bench starts visq-server with --seed-samples and uploads
// Sponza itself).
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>

#include "latency_figures.h"
#include "server_process.h"
#include "test_support.h"
#include "visq/gpu/obscurance.h"
#include "visq_client.h"

namespace visq {
namespace {

using Clock = std::chrono::steady_clock;

void SetVec(v1::Vec3* v, double x, double y, double z) {
  v->set_x(x);
  v->set_y(y);
  v->set_z(z);
}

// The ceiling light onto the floor: every texel sees the light partly
// hidden by the two boxes, so the map does real work.
v1::HiddenSampleMapRequest SmallMap(v1::VisibilityMethod method, uint32_t samples) {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetVec(request.mutable_source()->mutable_origin(), -0.25, 1.99, -0.25);
  SetVec(request.mutable_source()->mutable_edge_u(), 0.5, 0, 0);
  SetVec(request.mutable_source()->mutable_edge_v(), 0, 0, 0.5);
  SetVec(request.mutable_receiver()->mutable_origin(), -0.999, 0.001, -0.999);
  SetVec(request.mutable_receiver()->mutable_edge_u(), 1.998, 0, 0);
  SetVec(request.mutable_receiver()->mutable_edge_v(), 0, 0, 1.998);
  request.mutable_samples()->set_count(samples);
  request.set_width(8);
  request.set_height(8);
  request.set_method(method);
  return request;
}

v1::ComputeObscurancesRequest SponzaBake(uint32_t resolution, uint32_t directions) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("sponza");
  request.set_resolution(resolution);
  request.set_d_max(2.0);
  request.set_direction_count(directions);
  request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  return request;
}

struct Phase {
  std::vector<double> ms;  // each map's latency
  double seconds = 0;      // the phase's length
  size_t failures = 0;
  std::string first_error;
  double Throughput() const { return seconds > 0 ? ms.size() / seconds : 0.0; }
};

// `clients` threads, each with a client of its own, sending maps back to
// back for `seconds`.
Phase RunMaps(const std::string& address, int clients, double seconds, const v1::HiddenSampleMapRequest& request) {
  Phase phase;
  std::mutex mutex;
  const auto start = Clock::now();
  const auto end = start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  std::vector<std::thread> threads;
  for (int c = 0; c < clients; ++c)
    threads.emplace_back([&] {
      client::Client client({.address = address, .deadline = std::chrono::seconds(60)});
      std::vector<double> mine;
      size_t failed = 0;
      std::string error;
      while (Clock::now() < end) {
        const auto t0 = Clock::now();
        auto map = client.ComputeHiddenSampleMap(request);
        if (!map.ok()) {
          if (failed++ == 0) error = std::string(map.status().message());
          continue;
        }
        mine.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
      }
      std::lock_guard lock(mutex);
      phase.ms.insert(phase.ms.end(), mine.begin(), mine.end());
      phase.failures += failed;
      if (phase.first_error.empty()) phase.first_error = error;
    });
  for (auto& t : threads) t.join();
  phase.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return phase;
}

void PrintPhase(int clients, const char* what, const Phase& phase, const char* note = "") {
  const bench::LatencyFigures f = bench::Figures(phase.ms);
  std::printf("%7d  %-10s %6zu %9.1f %9.1f %9.1f %9.1f%s\n", clients, what, f.n, f.p50, f.p99, f.max,
              phase.Throughput(), note);
  if (phase.failures > 0) std::printf("         %zu map(s) failed: %s\n", phase.failures, phase.first_error.c_str());
}

}  // namespace
}  // namespace visq

int main(int argc, char** argv) {
  using namespace visq;
  CLI::App app{"visq: 8x8 maps from N clients, alone and under a Sponza bake"};
  std::string scenes_dir, server_address, method_name = "raster";
  std::vector<int> client_counts = {1, 8};
  double seconds = 5.0, bake_lead_s = 1.5;
  uint32_t samples = 256, bake_resolution = 1024;
  app.add_option("--scenes", scenes_dir, "the shared scenes (default: ../shared/scenes when present)");
  app.add_option("--server", server_address, "a running server holding cornell_box_visq and sponza");
  app.add_option("--clients", client_counts, "concurrent clients, one phase pair each")->delimiter(',')->capture_default_str();
  app.add_option("--seconds", seconds, "length of each phase")->capture_default_str();
  app.add_option("--samples", samples, "the maps' source samples")->capture_default_str();
  app.add_option("--method", method_name, "the maps' method: raster (the GL thread the bake shares), raycast, auto")
      ->check(CLI::IsMember({"raster", "raycast", "auto"}))->capture_default_str();
  app.add_option("--bake-resolution", bake_resolution, "the Sponza bake's atlas")->capture_default_str();
  app.add_option("--bake-lead", bake_lead_s, "seconds the bake runs before a phase starts (its atlas, first steps)")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const v1::VisibilityMethod method = method_name == "raster"    ? v1::RASTER
                                      : method_name == "raycast" ? v1::RAYCAST
                                                                 : v1::METHOD_UNSPECIFIED;

  // The server: given, or started here with the Cornell box and Sponza.
  std::optional<visq::testing::ScratchDir> repo;
  std::unique_ptr<visq::testing::ServerProcess> server;
  if (server_address.empty()) {
    std::optional<std::filesystem::path> shared;
    if (!scenes_dir.empty() && std::filesystem::exists(scenes_dir)) shared = scenes_dir;
    if (!shared) shared = visq::testing::SharedScenesDir();
    if (!shared) {
      std::printf("../shared/scenes is absent (Sponza is the bake): nothing measured\n");
      return 77;
    }
    repo.emplace();
    server = visq::testing::ServerProcess::Start({repo->path(), {"--seed-samples"}});
    if (!server) {
      std::fprintf(stderr, "the server did not start\n");
      return 1;
    }
    server_address = server->address();
    client::Client uploader({.address = server_address, .deadline = std::chrono::minutes(5)});
    auto info = uploader.UploadScene(*shared / "sponza_dabrovic/sponza.gltf", "sponza");
    if (!info.ok()) {
      std::fprintf(stderr, "Sponza upload: %s\n", std::string(info.status().message()).c_str());
      return 1;
    }
  }

  // Warm up: the map's programs, the bake's programs and its atlas (seconds
  // on llvmpipe, paid once, not in any phase).
  const v1::HiddenSampleMapRequest map = SmallMap(method, samples);
  {
    client::Client warm({.address = server_address, .deadline = std::chrono::minutes(5),
                         .stream_deadline = std::chrono::milliseconds(0)});
    auto first_map = warm.ComputeHiddenSampleMap(map);
    if (!first_map.ok()) {
      std::fprintf(stderr, "map: %s\n", std::string(first_map.status().message()).c_str());
      return 1;
    }
    std::printf("map: 8x8 texels, %u samples, method %s\n", samples, first_map->figures.accuracy().method().c_str());
    auto first_bake = warm.ComputeObscurances(SponzaBake(bake_resolution, 1));
    if (!first_bake.ok()) {
      std::fprintf(stderr, "bake: %s\n", std::string(first_bake.status().message()).c_str());
      return 1;
    }
    std::printf("bake: Sponza, %u^2 atlas, depth peeling, one direction %.0f ms alone\n", bake_resolution,
                first_bake->figures.timing().compute_ms());
  }
  // The bake's GL jobs last about this long (the server's default step): the
  // longest a map should wait for the GL thread.
  const double bake_job_ms = gpu::ObscuranceBakeOptions{}.step_target_ms;
  std::printf("bake GL job (step) target: %.0f ms; phases of %.1f s\n\n", bake_job_ms, seconds);

  std::printf("%7s  %-10s %6s %9s %9s %9s %9s\n", "clients", "phase", "maps", "p50 ms", "p99 ms", "max ms", "maps/s");
  struct Pair {
    int clients;
    Phase alone, under;
    bool under_valid = false;
  };
  std::vector<Pair> pairs;
  for (int clients : client_counts) {
    Pair pair{clients};
    pair.alone = RunMaps(server_address, clients, seconds, map);
    PrintPhase(clients, "alone", pair.alone);

    // One bake, far longer than the phase, cut by its own deadline just
    // after the phase: the figures hold only if it ran all through it.
    const auto bake_deadline = std::chrono::milliseconds(static_cast<int64_t>((bake_lead_s + seconds + 1.0) * 1000));
    Status bake_status;
    Clock::time_point bake_end;
    std::thread bake([&] {
      client::Client baker({.address = server_address, .stream_deadline = bake_deadline});
      bake_status = baker.ComputeObscurances(SponzaBake(bake_resolution, 4096)).status();
      bake_end = Clock::now();
    });
    std::this_thread::sleep_for(std::chrono::duration<double>(bake_lead_s));
    pair.under = RunMaps(server_address, clients, seconds, map);
    const auto phase_end = Clock::now();
    bake.join();
    pair.under_valid = bake_status.code() == absl::StatusCode::kDeadlineExceeded && bake_end >= phase_end;
    PrintPhase(clients, "with bake", pair.under,
               pair.under_valid ? "" : "  VOID: the bake was not running all through the phase");
    if (!pair.under_valid) std::printf("         bake: %s\n", bake_status.ToString().c_str());
    pairs.push_back(pair);
  }

  std::printf("\n%7s %22s %12s %26s %12s\n", "clients", "p99 bake / (job+own)", "goal <= 3", "throughput bake / alone",
              "goal >= 0.25");
  for (const Pair& p : pairs) {
    const bench::LatencyFigures alone = bench::Figures(p.alone.ms), under = bench::Figures(p.under.ms);
    const double p99_ratio = under.p99 / (bake_job_ms + alone.p50);
    const double throughput_ratio = p.alone.Throughput() > 0 ? p.under.Throughput() / p.alone.Throughput() : 0.0;
    std::printf("%7d %22.2f %12s %26.2f %12s%s\n", p.clients, p99_ratio, p99_ratio <= 3.0 ? "met" : "NOT met",
                throughput_ratio, throughput_ratio >= 0.25 ? "met" : "NOT met",
                p.under_valid ? "" : "  (void: see above)");
  }
  return 0;
}
