// visq health, load, list, info, unload, stats (list and stats over the fleet: fleet_commands.cpp).
#include <filesystem>

#include <fmt/format.h>

#include "cli_common.h"
#include "fleet.h"

namespace visq::cli {
namespace {

struct NoOptions {};

Status RunHealth(const NoOptions&, Cli& cli) {
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(auto status, client.Health());
  const std::string name = grpc::health::v1::HealthCheckResponse::ServingStatus_Name(status);
  if (cli.flags.json) fmt::print("{{\"status\": \"{}\"}}\n", name);
  else fmt::print("{}\n", name);
  cli.exit_code = status == grpc::health::v1::HealthCheckResponse::SERVING ? 0 : 3;
  return absl::OkStatus();
}

struct LoadOptions {
  std::string target, name;
  bool replace = false;
};

Status RunLoad(const LoadOptions& o, Cli& cli) {
  namespace fs = std::filesystem;
  std::error_code ec;
  const fs::path path(o.target);
  const bool is_file = fs::is_regular_file(path, ec);
  if (!is_file && fs::is_directory(path, ec))
    return absl::InvalidArgumentError(
        fmt::format("FILE_OR_NAME: '{}' is a directory; give its .gltf or .glb file", o.target));
  // A repository name has no folder and no glTF extension; anything else
  // was meant as a local file.
  const std::string extension = path.extension().string();
  const bool looks_like_path = o.target.find('/') != std::string::npos || extension == ".gltf" ||
                               extension == ".glb";
  if (!is_file && looks_like_path)
    return absl::NotFoundError(fmt::format("FILE_OR_NAME: the file '{}' does not exist", o.target));
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::SceneInfo info,
                        WhileWaiting(cli.flags, "load", [&] {
                          return is_file ? client.UploadScene(path, o.name, o.replace)
                                         : client.LoadFromRepository(o.name.empty() ? o.target : o.name, o.replace);
                        }));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(info));
  } else {
    fmt::print("loaded ");
    PrintScene(info, false);
  }
  return absl::OkStatus();
}

// list and stats: one server (--server), or the whole fleet (--fleet).
struct ServerOrFleet {
  FleetFlags fleet;
};

Status RunList(const ServerOrFleet& o, Cli& cli) {
  if (o.fleet.set()) return RunFleetList(o.fleet, cli);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::ListScenesResponse scenes, client.ListScenes());
  if (cli.flags.json) {
    fmt::print("{}", ToJson(scenes));
    return absl::OkStatus();
  }
  fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}\n", "NAME", "VERSION", "TRIANGLES", "CPU", "GPU");
  for (const auto& s : scenes.scenes())
    fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}\n", s.name(), s.version(), s.triangle_count(),
               Bytes(s.memory().cpu_bytes()), Bytes(s.memory().gpu_bytes()));
  return absl::OkStatus();
}

struct InfoOptions {
  std::string name;
  bool nodes = false;
};

Status RunInfo(const InfoOptions& o, Cli& cli) {
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::SceneInfo scene, client.GetScene(o.name, o.nodes));
  if (cli.flags.json) fmt::print("{}", ToJson(scene));
  else PrintScene(scene, o.nodes);
  return absl::OkStatus();
}

struct UnloadOptions {
  std::string name;
  bool delete_stored = false;
};

Status RunUnload(const UnloadOptions& o, Cli& cli) {
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::UnloadSceneResponse response, client.UnloadScene(o.name, o.delete_stored));
  if (cli.flags.json) fmt::print("{}", ToJson(response));
  else fmt::print("unloaded {}{}\n", o.name, response.deleted_from_repository() ? " (deleted from the repository)" : "");
  return absl::OkStatus();
}

Status RunStats(const ServerOrFleet& o, Cli& cli) {
  if (o.fleet.set()) return RunFleetStats(o.fleet, cli);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::ServerStats s, client.GetStats());
  if (cli.flags.json) {
    fmt::print("{}", ToJson(s));
    return absl::OkStatus();
  }
  fmt::print("server {} up {:.0f} s, visq-server {} ({})\n", s.server_id(), s.uptime_s(), s.server_version(),
             s.build_commit());
  fmt::print("GPU    {} / {} / {} ({}{}), contexts lost {}\n", s.gpu_vendor(), s.gpu_renderer(), s.gl_version(),
             s.egl_device(), s.gpu_software() ? ", software" : "", s.gpu_contexts_lost());
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
  return absl::OkStatus();
}

}  // namespace

void AddSceneCommands(Cli& cli) {
  auto none = std::make_shared<NoOptions>();
  OnRun(cli.app.add_subcommand("health", "Report the server's health (exit 3 when not SERVING)"), cli, none,
        RunHealth);

  auto load = std::make_shared<LoadOptions>();
  auto* load_command =
      cli.app.add_subcommand("load", "Upload a .gltf/.glb, or load a scene from the server's repository by name");
  load_command->add_option("FILE_OR_NAME", load->target, "A local .gltf/.glb file, or a repository scene name")
      ->required();
  load_command->add_option("--name", load->name, "Name the scene is known by (default: the file's stem)");
  load_command->add_flag("--replace", load->replace, "Replace a resident scene of that name");
  OnRun(load_command, cli, load, RunLoad);

  auto list = std::make_shared<ServerOrFleet>();
  auto* list_command = cli.app.add_subcommand("list", "List resident scenes (--fleet: on every replica)");
  AddFleetFlags(list_command, list->fleet);
  OnRun(list_command, cli, list, RunList);

  auto info = std::make_shared<InfoOptions>();
  auto* info_command = cli.app.add_subcommand("info", "Describe a resident scene");
  info_command->add_option("NAME", info->name, "Scene name")->required();
  info_command->add_flag("--nodes", info->nodes, "List the scene's nodes");
  OnRun(info_command, cli, info, RunInfo);

  auto unload = std::make_shared<UnloadOptions>();
  auto* unload_command = cli.app.add_subcommand("unload", "Unload a scene");
  unload_command->add_option("NAME", unload->name, "Scene name")->required();
  unload_command->add_flag("--delete", unload->delete_stored, "Also delete it from the server's repository");
  OnRun(unload_command, cli, unload, RunUnload);

  auto stats = std::make_shared<ServerOrFleet>();
  auto* stats_command = cli.app.add_subcommand(
      "stats", "Server statistics: per-RPC latencies, queues, memory, GPU (--fleet: every replica and the totals)");
  AddFleetFlags(stats_command, stats->fleet);
  OnRun(stats_command, cli, stats, RunStats);
}

}  // namespace visq::cli
