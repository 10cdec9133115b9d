// visq: the command-line client. Each subcommand is a thin wrapper over
// visq::client::Client; --json prints the response message as JSON.
#include <cstdlib>
#include <fstream>
#include <iostream>

#include <CLI/CLI.hpp>
#include <fmt/format.h>
#include <google/protobuf/util/json_util.h>

#include "visq_client.h"

namespace {

using visq::client::Client;

struct CommonFlags {
  std::string server = "127.0.0.1:50051";
  bool json = false;
  double timeout_s = 60;
  std::string token_file;
  std::string tls_ca, tls_cert, tls_key;
};

void AddCommonFlags(CLI::App* command, CommonFlags& flags) {
  command->add_option("--server", flags.server, "visq-server address HOST:PORT")->envname("VISQ_SERVER")
      ->capture_default_str();
  command->add_flag("--json", flags.json, "Print the response as JSON");
  command->add_option("--timeout", flags.timeout_s, "Deadline in seconds")->capture_default_str();
  command->add_option("--token-file", flags.token_file, "File whose first line is the bearer token")
      ->envname("VISQ_AUTH_TOKEN_FILE");
  command->add_option("--tls-ca", flags.tls_ca, "PEM roots for a TLS server")->envname("VISQ_TLS_CA");
  command->add_option("--tls-cert", flags.tls_cert, "PEM client certificate (mutual TLS)")->envname("VISQ_TLS_CLIENT_CERT");
  command->add_option("--tls-key", flags.tls_key, "PEM client key (mutual TLS)")->envname("VISQ_TLS_CLIENT_KEY");
}

Client MakeClient(const CommonFlags& flags) {
  visq::client::ClientOptions options;
  options.address = flags.server;
  options.deadline = std::chrono::milliseconds(static_cast<int64_t>(flags.timeout_s * 1000));
  options.tls_ca_file = flags.tls_ca;
  options.client_cert_file = flags.tls_cert;
  options.client_key_file = flags.tls_key;
  if (!flags.token_file.empty()) {
    std::ifstream in(flags.token_file);
    std::getline(in, options.auth_token);
  }
  return Client(options);
}

std::string ToJson(const google::protobuf::Message& message) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = true;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(message, &out, options);
  return out;
}

std::string Bytes(uint64_t bytes) {
  if (bytes >= (1ull << 30)) return fmt::format("{:.2f} GiB", bytes / double(1ull << 30));
  if (bytes >= (1ull << 20)) return fmt::format("{:.2f} MiB", bytes / double(1ull << 20));
  if (bytes >= (1ull << 10)) return fmt::format("{:.1f} KiB", bytes / 1024.0);
  return fmt::format("{} B", bytes);
}

void PrintScene(const visq::v1::SceneInfo& s, bool nodes) {
  fmt::print("{} (version {})\n", s.name(), s.version());
  fmt::print("  triangles     {}\n  vertices      {}\n", s.triangle_count(), s.vertex_count());
  fmt::print("  bounds        ({:.4g}, {:.4g}, {:.4g}) .. ({:.4g}, {:.4g}, {:.4g})\n", s.bounds_min().x(),
             s.bounds_min().y(), s.bounds_min().z(), s.bounds_max().x(), s.bounds_max().y(), s.bounds_max().z());
  fmt::print("  materials     {} ({} emissive triangles)\n", s.material_count(), s.emissive_triangle_count());
  fmt::print("  lightmap UVs  {}\n", s.has_lightmap_uvs() ? "yes (TEXCOORD_1)" : "no");
  fmt::print("  memory        CPU {}, GPU {}\n", Bytes(s.memory().cpu_bytes()), Bytes(s.memory().gpu_bytes()));
  fmt::print("  content hash  {}\n", s.content_hash());
  fmt::print("  load time     {:.1f} ms{}\n", s.load_ms(), s.persisted() ? ", stored in the repository" : "");
  for (const auto& d : s.dropped()) fmt::print("  dropped       {}\n", d);
  if (nodes) {
    fmt::print("  nodes         {}\n", s.nodes_size());
    for (int i = 0; i < s.nodes_size(); ++i) {
      const auto& n = s.nodes(i);
      fmt::print("    [{}] {} (glTF node {}, parent {}, {} triangles)\n", i, n.name().empty() ? "<unnamed>" : n.name(),
                 n.gltf_index(), n.parent(), n.triangle_count());
    }
  }
}

int Fail(const visq::Status& status) {
  std::cerr << "visq: " << absl::StatusCodeToString(status.code()) << ": " << status.message() << "\n";
  return status.code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"visq: visibility queries against a visq-server"};
  app.require_subcommand(1);
  CommonFlags flags;
  int exit_code = 0;

  auto* health = app.add_subcommand("health", "Report the server's health");
  AddCommonFlags(health, flags);
  health->callback([&] {
    auto client = MakeClient(flags);
    auto status = client.Health();
    if (!status.ok()) { exit_code = Fail(status.status()); return; }
    const std::string name = grpc::health::v1::HealthCheckResponse::ServingStatus_Name(*status);
    if (flags.json) fmt::print("{{\"status\": \"{}\"}}\n", name);
    else fmt::print("{}\n", name);
    exit_code = *status == grpc::health::v1::HealthCheckResponse::SERVING ? 0 : 3;
  });

  std::string load_target, load_name;
  bool replace = false;
  auto* load = app.add_subcommand("load", "Upload a .gltf/.glb, or load a scene from the server's repository by name");
  load->add_option("FILE_OR_NAME", load_target, "A local .gltf/.glb file, or a repository scene name")->required();
  load->add_option("--name", load_name, "Name the scene is known by (default: the file's stem)");
  load->add_flag("--replace", replace, "Replace a resident scene of that name");
  AddCommonFlags(load, flags);
  load->callback([&] {
    auto client = MakeClient(flags);
    std::error_code ec;
    const bool is_file = std::filesystem::is_regular_file(load_target, ec);
    auto info = is_file ? client.UploadScene(load_target, load_name, replace)
                        : client.LoadFromRepository(load_name.empty() ? load_target : load_name, replace);
    if (!info.ok()) { exit_code = Fail(info.status()); return; }
    if (flags.json) fmt::print("{}", ToJson(*info));
    else {
      fmt::print("loaded ");
      PrintScene(*info, false);
    }
  });

  auto* list = app.add_subcommand("list", "List resident scenes");
  AddCommonFlags(list, flags);
  list->callback([&] {
    auto client = MakeClient(flags);
    auto scenes = client.ListScenes();
    if (!scenes.ok()) { exit_code = Fail(scenes.status()); return; }
    if (flags.json) { fmt::print("{}", ToJson(*scenes)); return; }
    fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}\n", "NAME", "VERSION", "TRIANGLES", "CPU", "GPU");
    for (const auto& s : scenes->scenes())
      fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}\n", s.name(), s.version(), s.triangle_count(),
                 Bytes(s.memory().cpu_bytes()), Bytes(s.memory().gpu_bytes()));
  });

  std::string info_name;
  bool info_nodes = false;
  auto* info = app.add_subcommand("info", "Describe a resident scene");
  info->add_option("NAME", info_name, "Scene name")->required();
  info->add_flag("--nodes", info_nodes, "List the scene's nodes");
  AddCommonFlags(info, flags);
  info->callback([&] {
    auto client = MakeClient(flags);
    auto scene = client.GetScene(info_name, info_nodes);
    if (!scene.ok()) { exit_code = Fail(scene.status()); return; }
    if (flags.json) fmt::print("{}", ToJson(*scene));
    else PrintScene(*scene, info_nodes);
  });

  std::string unload_name;
  bool delete_stored = false;
  auto* unload = app.add_subcommand("unload", "Unload a scene");
  unload->add_option("NAME", unload_name, "Scene name")->required();
  unload->add_flag("--delete", delete_stored, "Also delete it from the server's repository");
  AddCommonFlags(unload, flags);
  unload->callback([&] {
    auto client = MakeClient(flags);
    auto response = client.UnloadScene(unload_name, delete_stored);
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (flags.json) fmt::print("{}", ToJson(*response));
    else fmt::print("unloaded {}{}\n", unload_name, response->deleted_from_repository() ? " (deleted from the repository)" : "");
  });

  auto* stats = app.add_subcommand("stats", "Server statistics: per-RPC latencies, queues, memory, GPU");
  AddCommonFlags(stats, flags);
  stats->callback([&] {
    auto client = MakeClient(flags);
    auto response = client.GetStats();
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (flags.json) { fmt::print("{}", ToJson(*response)); return; }
    const auto& s = *response;
    fmt::print("server {} up {:.0f} s\n", s.server_id(), s.uptime_s());
    fmt::print("GPU    {} / {} / {} ({}{})\n", s.gpu_vendor(), s.gpu_renderer(), s.gl_version(), s.egl_device(),
               s.gpu_software() ? ", software" : "");
    fmt::print("queues GPU {}, workers {}\n", s.gpu_queue_depth(), s.worker_queue_depth());
    fmt::print("scenes {} resident, CPU {}, GPU {}\n", s.scenes_resident(), Bytes(s.scene_memory().cpu_bytes()),
               Bytes(s.scene_memory().gpu_bytes()));
    fmt::print("{:<24} {:>8} {:>7} {:>10} {:>10} {:>10} {:>10}\n", "RPC", "CALLS", "ERRORS", "MEAN ms", "P50 ms",
               "P99 ms", "MAX ms");
    for (const auto& m : s.methods())
      fmt::print("{:<24} {:>8} {:>7} {:>10.2f} {:>10.2f} {:>10.2f} {:>10.2f}\n", m.method(), m.calls(), m.errors(),
                 m.mean_ms(), m.p50_ms(), m.p99_ms(), m.max_ms());
    for (const auto& c : s.caches())
      fmt::print("cache {}: {} entries, {} of {}, {} hits, {} misses, {} evictions\n", c.name(), c.entries(),
                 Bytes(c.bytes()), Bytes(c.capacity_bytes()), c.hits(), c.misses(), c.evictions());
  });

  CLI11_PARSE(app, argc, argv);
  return exit_code;
}
