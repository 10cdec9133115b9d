// visq-server: flags (each also an environment variable, for containers),
// signals, and the server lifecycle.
#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstring>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include "common/version.h"
#include "core/work_budget.h"
#include "scene/sample_scenes.h"
#include "service/auth.h"
#include "service/log_format.h"
#include "service/server.h"

namespace {

// How long past the drain's end the process may take to exit before the
// watchdog ends it.
constexpr std::chrono::seconds kExitGrace{5};

// Written to a temporary name and renamed: a reader never sees half.
bool WritePortFile(const std::string& path, int port) {
  const std::string temporary = path + ".tmp";
  std::FILE* f = std::fopen(temporary.c_str(), "w");
  if (f == nullptr) return false;
  const bool written = std::fprintf(f, "%d\n", port) >= 0;
  return std::fclose(f) == 0 && written && std::rename(temporary.c_str(), path.c_str()) == 0;
}

// A file of 64 hex digits (256 random bits), readable by this user only.
// Returns false when the file was there already (its token is kept).
visq::StatusOr<bool> CreateTokenFileIfAbsent(const std::string& path) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd < 0 && errno == EEXIST) return false;
  if (fd < 0) return absl::FailedPreconditionError(absl::StrCat("cannot create it: ", std::strerror(errno)));
  unsigned char random[32];
  std::ifstream urandom("/dev/urandom", std::ios::binary);
  urandom.read(reinterpret_cast<char*>(random), sizeof(random));
  std::string hex;
  for (unsigned char b : random) hex += fmt::format("{:02x}", b);
  hex += '\n';
  const bool written = urandom && ::write(fd, hex.data(), hex.size()) == static_cast<ssize_t>(hex.size()) &&
                       ::fsync(fd) == 0;
  ::close(fd);
  if (!written) {
    ::unlink(path.c_str());
    return absl::DataLossError("cannot write a new token");
  }
  return true;
}

// Every flag's value. Most go straight into the server's options; the rest
// are read once at start (files, logging, signals).
struct Flags {
  visq::service::ServerOptions options;
  std::string log_level = "info";
  uint64_t max_upload_bytes = options.engine.max_upload_bytes;
  bool seed_samples = false;
  std::string port_file;
  std::string scene_repo = options.engine.scene_repo.string();
  std::string cost_model_file;
  uint64_t max_scene_bytes = options.engine.max_scene_bytes;
  uint64_t light_cache_bytes = options.engine.light_cache_bytes;
  std::string auth_token_file;
  bool create_auth_token = false;
  bool no_preload = false;
  std::string metrics_port_file;
  std::string log_format = "text";
  int drain_seconds = 10;
  int upload_idle_seconds = static_cast<int>(options.uploads.idle.count() / 1000);
  int stream_stall_seconds = static_cast<int>(options.uploads.stream_stall.count() / 1000);
  int metrics_read_seconds = static_cast<int>(options.metrics_limits.request_timeout.count() / 1000);
};

// Each flag, its environment variable (for containers), its check.
void AddFlags(CLI::App& app, Flags& flags) {
  flags.options.engine.gpu.device = "auto";
  app.set_version_flag("--version", std::string("visq-server ") + visq::kVersion + " (" + visq::kBuildCommit + ")");
  app.add_option("--address", flags.options.address, "HOST:PORT to listen on")->envname("VISQ_ADDRESS")->capture_default_str();
  app.add_option("--scene-repo", flags.scene_repo, "Scene repository directory")->envname("VISQ_SCENE_REPO")->capture_default_str();
  app.add_option("--catalog", flags.options.engine.catalog,
                 "Where the repository's catalog is: 'sqlite' (default, <scene-repo>/.visq/catalog.sqlite3, one "
                 "machine), 'sqlite:<file>', or postgresql://user@host:port/db for replicas on several machines")
      ->envname("VISQ_CATALOG");
  app.add_option("--replica-id", flags.options.engine.replica_id,
                 "This server's name among the replicas sharing --scene-repo (default: the host name); a start "
                 "removes only its own staging")
      ->envname("VISQ_REPLICA_ID");
  app.add_option("--cost-model-file", flags.cost_model_file,
                 "Where the accuracy planner keeps its measured costs across restarts (default: "
                 "<scene-repo>/.visq-cost-model.tsv; '-': not kept)")
      ->envname("VISQ_COST_MODEL_FILE");
  app.add_option("--max-receive-bytes", flags.options.max_receive_message_bytes, "Largest gRPC message accepted")
      ->envname("VISQ_MAX_RECEIVE_BYTES")->check(CLI::Range(1 << 16, 1 << 30))->capture_default_str();
  app.add_option("--max-upload-bytes", flags.max_upload_bytes, "Largest scene upload accepted")
      ->envname("VISQ_MAX_UPLOAD_BYTES")->capture_default_str();
  app.add_option("--max-scene-bytes", flags.max_scene_bytes,
                 "Largest resident scene accepted, by an estimate of its geometry and every structure its queries "
                 "build (Embree BVH, triangle index, GPU buffers)")
      ->envname("VISQ_MAX_SCENE_BYTES")->capture_default_str();
  app.add_option("--gpu-rays-in-choice", flags.options.engine.gpu_rays_in_choice,
                 "Whether a request naming no method (or naming a target) may run GPU_RAYCAST: auto (on a GPU only: "
                 "on a CPU rasterizer its shader costs several times Embree's time on the same cores), always, or "
                 "never; named, it always runs")
      ->envname("VISQ_GPU_RAYS_IN_CHOICE")->check(CLI::IsMember({"auto", "always", "never"}))->capture_default_str();
  app.add_option("--explore-when-idle", flags.options.engine.explore_when_idle,
                 "Whether probes of the server's choice of method that no request's share could pay for run while "
                 "no call is in flight (stopped when one arrives); off, a request probes a new method only with the "
                 "share it can pay or that earlier requests set aside")
      ->envname("VISQ_EXPLORE_WHEN_IDLE")->capture_default_str();
  app.add_option("--idle-quiet-ms", flags.options.engine.idle_exploration.quiet_ms,
                 "How long no call must have been in flight before an idle-time probe starts")
      ->envname("VISQ_IDLE_QUIET_MS")->check(CLI::Range(0.0, 3.6e6))->capture_default_str();
  app.add_flag("--warm-scenes", flags.options.engine.warm_at_load,
               "Build every structure of each scene loaded (at start or later) or uploaded right after the load, in "
               "the background, so that its first query does not wait for them")
      ->envname("VISQ_WARM_SCENES");
  app.add_option("--max-work-bytes", flags.options.engine.max_work_bytes,
                 "Memory that answers in progress may hold together; requests wait for it or are refused "
                 "(0: half of the memory this process may use: physical memory, or its cgroup's limit where that "
                 "is smaller, v2 memory.max or v1 memory.limit_in_bytes; the log says which at start)")
      ->envname("VISQ_MAX_WORK_BYTES")->capture_default_str();
  app.add_option("--map-band-bytes", flags.options.engine.hidden_sample_map.band_readback_bytes,
                 "Largest GPU read-back of one band of a hidden-sample map: each band is its own GL job and is "
                 "sent as soon as it is counted")
      ->envname("VISQ_MAP_BAND_BYTES")->check(CLI::Range(size_t{1} << 10, size_t{1} << 30))->capture_default_str();
  app.add_option("--light-cache-bytes", flags.light_cache_bytes, "Bound on the exact light-visibility trees kept (LRU)")
      ->envname("VISQ_LIGHT_CACHE_BYTES")->capture_default_str();
  app.add_option("--light-receiver-cells", flags.options.engine.light_receiver_cells,
                 "LightVisibility trees per side of the scene (receiver cubes of its extent / N); 0: groups "
                 "that follow the batch and its occluders")
      ->envname("VISQ_LIGHT_RECEIVER_CELLS")->check(CLI::Range(0, 4096))->capture_default_str();
  app.add_option("--light-receiver-min-points", flags.options.engine.light_receiver_min_points,
                 "A receiver cube with fewer points joins its parent cube's tree (1: every cube its own)")
      ->envname("VISQ_LIGHT_RECEIVER_MIN_POINTS")->check(CLI::Range(1, 1 << 20))->capture_default_str();
  app.add_option("--light-shadow-tolerance", flags.options.engine.light_shadow_tolerance,
                 "LightVisibility without a shadow_tolerance: per point, occluders with small shadows are left out "
                 "while their areas sum to at most this share of the light, and stated as the point's error (0: "
                 "every answer exact)")
      ->envname("VISQ_LIGHT_SHADOW_TOLERANCE")->check(CLI::Range(0.0, 1.0))->capture_default_str();
  app.add_option("--worker-threads", flags.options.worker_threads,
                 "Threads for blocking request work (the CPU-parallel loops within it use one thread per CPU the "
                 "process may use: its cgroup's CPU quota, cpu.max or cpu.cfs_quota_us, rounded up, or its affinity "
                 "mask where that is smaller)")
      ->envname("VISQ_WORKER_THREADS")->check(CLI::Range(1, 256))->capture_default_str();
  app.add_option("--log-level", flags.log_level, "trace, debug, info, warn, error")->envname("VISQ_LOG_LEVEL")->capture_default_str();
  app.add_option("--gpu-device", flags.options.engine.gpu.device, "auto, surfaceless, or device:N")
      ->envname("VISQ_EGL_DEVICE")->capture_default_str();
  app.add_flag("--gpu-debug", flags.options.engine.gpu.debug, "KHR_debug to the log, GL error checks")->envname("VISQ_GPU_DEBUG");
  app.add_option("--fault-lose-gpu-context-at-job", flags.options.engine.gpu.lose_context_at_job,
                 "Testing the recovery path: treat the N-th GPU job as if the GPU had reset during it")
      ->envname("VISQ_FAULT_LOSE_GPU_CONTEXT_AT_JOB")->group("Fault injection");
  app.add_flag("--seed-samples", flags.seed_samples, "Write the generated sample scenes into the repository if absent")
      ->envname("VISQ_SEED_SAMPLES");
  app.add_option("--server-id", flags.options.server_id, "Name reported by GetStats (default host:port)")->envname("VISQ_SERVER_ID");
  app.add_option("--auth-token-file", flags.auth_token_file, "File holding the bearer token every call must carry")
      ->envname("VISQ_AUTH_TOKEN_FILE");
  app.add_flag("--auth-token-create", flags.create_auth_token,
               "If --auth-token-file does not exist, write a new random token there (mode 0600) first")
      ->envname("VISQ_AUTH_TOKEN_CREATE");
  app.add_option("--tls-cert", flags.options.tls.cert_file, "PEM certificate chain: serve TLS")->envname("VISQ_TLS_CERT");
  app.add_option("--tls-key", flags.options.tls.key_file, "PEM private key for --tls-cert")->envname("VISQ_TLS_KEY");
  app.add_option("--tls-client-ca", flags.options.tls.client_ca_file, "PEM CA that client certificates must chain to (mutual TLS)")
      ->envname("VISQ_TLS_CLIENT_CA");
  app.add_flag("--allow-insecure-remote", flags.options.allow_insecure_remote,
               "Listen beyond loopback without TLS or a token")->envname("VISQ_ALLOW_INSECURE_REMOTE");
  app.add_flag("--no-preload", flags.no_preload, "Load repository scenes on first use instead of at start (replicas)")
      ->envname("VISQ_NO_PRELOAD");
  app.add_option("--port-file", flags.port_file, "Write the bound port here once listening (for --address HOST:0)")
      ->envname("VISQ_PORT_FILE");
  app.add_option("--metrics-address", flags.options.metrics_address,
                 "HOST:PORT for Prometheus (GET /metrics, plain HTTP); empty: none")
      ->envname("VISQ_METRICS_ADDRESS");
  app.add_flag("--metrics-allow-remote", flags.options.allow_remote_metrics,
               "Let --metrics-address be beyond loopback")->envname("VISQ_METRICS_ALLOW_REMOTE");
  app.add_option("--metrics-port-file", flags.metrics_port_file,
                 "Write the bound /metrics port here (for --metrics-address HOST:0)")
      ->envname("VISQ_METRICS_PORT_FILE");
  app.add_option("--log-format", flags.log_format, "text, or json (one object a line)")
      ->envname("VISQ_LOG_FORMAT")->check(CLI::IsMember({"text", "json"}))->capture_default_str();
  app.add_option("--drain-seconds", flags.drain_seconds,
                 "On SIGTERM, how long calls in progress may take to finish before they are cancelled")
      ->envname("VISQ_DRAIN_SECONDS")->check(CLI::Range(0, 3600))->capture_default_str();

  // What one client may hold, so that no client holds what others need.
  const char* limits = "Connection and upload limits";
  app.add_option("--keepalive-seconds", flags.options.keepalive_seconds,
                 "Ping a connection that has been quiet this long, to find peers that are gone")
      ->envname("VISQ_KEEPALIVE_SECONDS")->check(CLI::Range(1, 86400))->capture_default_str()->group(limits);
  app.add_option("--keepalive-timeout-seconds", flags.options.keepalive_timeout_seconds,
                 "Close a connection whose keepalive ping goes unanswered this long")
      ->envname("VISQ_KEEPALIVE_TIMEOUT_SECONDS")->check(CLI::Range(1, 3600))->capture_default_str()->group(limits);
  app.add_option("--max-connection-idle-seconds", flags.options.max_connection_idle_seconds,
                 "Close a connection that has had no call in progress this long (clients reconnect when they "
                 "need to); 0: never")
      ->envname("VISQ_MAX_CONNECTION_IDLE_SECONDS")->check(CLI::Range(0, 86400 * 7))->capture_default_str()
      ->group(limits);
  app.add_option("--max-streams-per-connection", flags.options.max_streams_per_connection,
                 "Calls one connection may have in progress at once; a client's further calls wait for one to end")
      ->envname("VISQ_MAX_STREAMS_PER_CONNECTION")->check(CLI::Range(1, 1 << 20))->capture_default_str()
      ->group(limits);
  app.add_option("--max-uploads-in-flight", flags.options.uploads.max_in_flight,
                 "Uploads (LoadScene with upload_main_file) in progress at once, from every client together; "
                 "more are refused RESOURCE_EXHAUSTED")
      ->envname("VISQ_MAX_UPLOADS_IN_FLIGHT")->check(CLI::Range(1, 1 << 20))->capture_default_str()->group(limits);
  app.add_option("--max-uploads-per-client", flags.options.uploads.max_per_client,
                 "Uploads in progress at once from one client address (behind a proxy, every client shares its "
                 "address); more are refused RESOURCE_EXHAUSTED")
      ->envname("VISQ_MAX_UPLOADS_PER_CLIENT")->check(CLI::Range(1, 1 << 20))->capture_default_str()->group(limits);
  app.add_option("--upload-idle-seconds", flags.upload_idle_seconds,
                 "Abort a LoadScene stream that sends nothing for this long, and remove what it staged")
      ->envname("VISQ_UPLOAD_IDLE_SECONDS")->check(CLI::Range(1, 86400))->capture_default_str()->group(limits);
  app.add_option("--stream-stall-seconds", flags.stream_stall_seconds,
                 "Cancel a streamed answer whose client reads nothing for this long (a map, a bake, a preview, an "
                 "export: every stream), freeing its memory and its worker")
      ->envname("VISQ_STREAM_STALL_SECONDS")->check(CLI::Range(1, 86400))->capture_default_str()->group(limits);
  app.add_option("--stream-queue-bytes", flags.options.uploads.stream_queue_bytes,
                 "What a streamed answer may hold made but unsent within its own memory reservation; beyond it "
                 "each further message waits for its reader in the spare part of --max-work-bytes (the work ends "
                 "and frees its worker), or, with none spare, the work waits for the reader")
      ->envname("VISQ_STREAM_QUEUE_BYTES")
      ->check(CLI::Range(uint64_t{1} << 16, visq::core::kStreamedAnswerQueueBytes))
      ->capture_default_str()
      ->group(limits);
  app.add_option("--metrics-max-connections", flags.options.metrics_limits.max_connections,
                 "/metrics connections open at once; more are closed as they arrive")
      ->envname("VISQ_METRICS_MAX_CONNECTIONS")->check(CLI::Range(1, 1024))->capture_default_str()->group(limits);
  app.add_option("--metrics-read-seconds", flags.metrics_read_seconds,
                 "A /metrics request must arrive whole within this long, and its answer be taken within it again; "
                 "else the connection is closed")
      ->envname("VISQ_METRICS_READ_SECONDS")->check(CLI::Range(1, 600))->capture_default_str()->group(limits);
}

}  // namespace

int main(int argc, char** argv) {
  Flags flags;
  CLI::App app{"visq-server: visibility queries on GPU-resident scenes"};
  AddFlags(app, flags);
  CLI11_PARSE(app, argc, argv);
  visq::service::ServerOptions& options = flags.options;
  if (!flags.metrics_port_file.empty() && options.metrics_address.empty()) {
    std::cerr << "--metrics-port-file needs --metrics-address\n";
    return EXIT_FAILURE;
  }

  spdlog::set_level(spdlog::level::from_str(flags.log_level));
  if (flags.log_format == "json") visq::service::UseJsonLogFormat();
  else visq::service::UseEscapingLogFormat("%Y-%m-%dT%H:%M:%S.%e %^%l%$ %v");
  visq::service::RouteLibraryLogsToSpdlog();
  options.engine.scene_repo = flags.scene_repo;
  options.engine.cost_model_file = flags.cost_model_file;
  options.engine.max_upload_bytes = flags.max_upload_bytes;
  options.engine.max_scene_bytes = flags.max_scene_bytes;
  options.engine.light_cache_bytes = static_cast<size_t>(flags.light_cache_bytes);
  options.engine.load_repository_at_start = !flags.no_preload;
  options.uploads.idle = std::chrono::seconds(flags.upload_idle_seconds);
  options.uploads.stream_stall = std::chrono::seconds(flags.stream_stall_seconds);
  options.metrics_limits.request_timeout = std::chrono::seconds(flags.metrics_read_seconds);
  if (flags.create_auth_token && flags.auth_token_file.empty()) {
    std::cerr << "--auth-token-create needs --auth-token-file\n";
    return EXIT_FAILURE;
  }
  if (flags.create_auth_token) {
    visq::StatusOr<bool> created = CreateTokenFileIfAbsent(flags.auth_token_file);
    if (!created.ok()) {
      spdlog::critical("--auth-token-create {}: {}", flags.auth_token_file, created.status().message());
      return EXIT_FAILURE;
    }
    // The path only: the token never goes to the log.
    if (*created) spdlog::info("created a new bearer token in {}; clients read it from there", flags.auth_token_file);
  }
  if (!flags.auth_token_file.empty()) {
    std::ifstream in(flags.auth_token_file, std::ios::binary);
    std::stringstream text;
    text << in.rdbuf();
    std::vector<std::string> warnings;
    visq::StatusOr<std::string> token =
        in ? visq::service::ParseAuthToken(text.str(), &warnings)
           : visq::StatusOr<std::string>(absl::NotFoundError("cannot read the file"));
    if (!token.ok()) {
      spdlog::critical("--auth-token-file {}: {}", flags.auth_token_file, token.status().message());
      return EXIT_FAILURE;
    }
    for (const std::string& warning : warnings) spdlog::warn("--auth-token-file {}: {}", flags.auth_token_file, warning);
    options.auth_token = *std::move(token);
  }

  // Signals are taken synchronously by this thread (sigwait), so no handler
  // runs in an arbitrary thread.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  if (flags.seed_samples) {
    std::error_code ec;
    std::filesystem::create_directories(options.engine.scene_repo, ec);
    if (auto status = visq::WriteSampleScenes(options.engine.scene_repo); !status.ok()) {
      spdlog::critical("writing sample scenes: {}", status.message());
      return EXIT_FAILURE;
    }
  }
  auto server = visq::service::Server::Create(options);
  if (!server.ok()) {
    spdlog::critical("start-up failed: {}", server.status().message());
    return EXIT_FAILURE;
  }
  if (!flags.port_file.empty() && !WritePortFile(flags.port_file, (*server)->port())) {
    spdlog::critical("cannot write --port-file {}", flags.port_file);
    return EXIT_FAILURE;
  }
  if (!flags.metrics_port_file.empty() && !WritePortFile(flags.metrics_port_file, (*server)->metrics_port())) {
    spdlog::critical("cannot write --metrics-port-file {}", flags.metrics_port_file);
    return EXIT_FAILURE;
  }
  (*server)->Ready();

  int signal_number = 0;
  sigwait(&signals, &signal_number);
  spdlog::info("received {}", signal_number == SIGINT ? "SIGINT" : "SIGTERM");
  // The last resort: a call told to stop polls between GL jobs, ray streams
  // and points, so it ends within a second of the drain; work that never
  // returns to a poll (a GL draw or an Embree stream that does not end)
  // would hold the process past any grace period. The repository survives
  // an exit at any point (as it survives kill -9), so the process exits
  // without that work, saying so, with a status that says it too.
  std::thread([drain_seconds = flags.drain_seconds] {
    std::this_thread::sleep_for(std::chrono::seconds(drain_seconds) + kExitGrace);
    spdlog::critical("still running {} s after the drain ended: exiting without the work that did not stop",
                     kExitGrace.count());
    spdlog::shutdown();
    std::_Exit(EXIT_FAILURE);
  }).detach();
  visq::service::Server::StopAndExit(*std::move(server), std::chrono::seconds(flags.drain_seconds), EXIT_SUCCESS);
}
