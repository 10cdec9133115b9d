// visq: the command-line client. Each subcommand is a thin wrapper over
// visq::client::Client; --json prints the response message as JSON.
#include <algorithm>
#include <bit>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>

#include <CLI/CLI.hpp>
#include <fmt/format.h>
#include <google/protobuf/util/json_util.h>
#include <stb_image_write.h>

#include <glm/glm.hpp>

#include "common/version.h"
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

// "x,y,z" -> Vec3; false if malformed.
bool ParseVec3(const std::string& text, visq::v1::Vec3* out) {
  double x, y, z;
  char tail;
  if (std::sscanf(text.c_str(), "%lf,%lf,%lf%c", &x, &y, &z, &tail) != 3) return false;
  out->set_x(x);
  out->set_y(y);
  out->set_z(z);
  return true;
}

// "ox,oy,oz;ux,uy,uz;vx,vy,vz" -> Patch.
bool ParsePatch(const std::string& text, visq::v1::Patch* out) {
  const size_t a = text.find(';'), b = text.find(';', a + 1);
  if (a == std::string::npos || b == std::string::npos) return false;
  return ParseVec3(text.substr(0, a), out->mutable_origin()) &&
         ParseVec3(text.substr(a + 1, b - a - 1), out->mutable_edge_u()) &&
         ParseVec3(text.substr(b + 1), out->mutable_edge_v());
}

// Writes a width x height image of values in [0, 1] (1 or 3 channels),
// row 0 at the top (the receiver's v = 1 edge), as an 8-bit PNG.
bool WritePng(const std::string& path, int width, int height, int channels, const std::vector<float>& values) {
  std::vector<unsigned char> pixels(size_t(width) * height * channels);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width * channels; ++x) {
      const float v = values[size_t(height - 1 - y) * width * channels + x];
      pixels[size_t(y) * width * channels + x] = static_cast<unsigned char>(std::clamp(v, 0.0f, 1.0f) * 255.0f + 0.5f);
    }
  return stbi_write_png(path.c_str(), width, height, channels, pixels.data(), width * channels) != 0;
}

// Writes RGB rows that arrive top first (image RPCs) as a PNG, each value
// times `scale` (WritePng expects the last row first).
bool WriteTopFirstPng(const std::string& path, uint32_t width, uint32_t height, const std::vector<float>& rgb,
                      float scale) {
  std::vector<float> flipped(rgb.size());
  const size_t row = size_t(width) * 3;
  for (uint32_t y = 0; y < height; ++y)
    for (size_t i = 0; i < row; ++i) flipped[(height - 1 - y) * row + i] = rgb[y * row + i] * scale;
  return WritePng(path, static_cast<int>(width), static_cast<int>(height), 3, flipped);
}

// The pinhole camera flags of the image subcommands (volumetric,
// obscurance-preview), filled into any request with the camera_* fields.
// The short names (--camera, --forward, --up) are the originals of
// `visq volumetric`.
struct CameraFlags {
  std::string position, forward, up;
  double fov = 60;
  uint32_t width = 320, height = 240;
};

void AddCameraFlags(CLI::App* command, CameraFlags& camera) {
  command->add_option("--camera-position,--camera", camera.position, "Camera position 'x,y,z'")->required();
  command->add_option("--camera-forward,--forward", camera.forward, "Viewing direction 'x,y,z'")->required();
  command->add_option("--camera-up,--up", camera.up, "Camera up 'x,y,z' (default 0,1,0)");
  command->add_option("--width", camera.width, "Image width")->capture_default_str();
  command->add_option("--height", camera.height, "Image height")->capture_default_str();
  command->add_option("--fov", camera.fov, "Vertical field of view, degrees")->capture_default_str();
}

template <typename Request>
visq::Status FillCamera(const CameraFlags& camera, Request* request) {
  if (!ParseVec3(camera.position, request->mutable_camera_position()) ||
      !ParseVec3(camera.forward, request->mutable_camera_forward()) ||
      (!camera.up.empty() && !ParseVec3(camera.up, request->mutable_camera_up())))
    return absl::InvalidArgumentError("--camera-position, --camera-forward, --camera-up: expected 'x,y,z'");
  request->set_width(camera.width);
  request->set_height(camera.height);
  request->set_vertical_fov_deg(camera.fov);
  return absl::OkStatus();
}

// Ask by error instead of by count (--max-error, --time-budget-ms).
struct TargetFlags {
  double max_error = 0.0;
  double confidence = 0.0;
  double time_budget_ms = 0.0;
  bool set() const { return max_error > 0.0 || time_budget_ms > 0.0; }
  void Fill(visq::v1::AccuracyTarget* out) const {
    out->set_max_error(max_error);
    out->set_confidence(confidence);
    out->set_time_budget_ms(time_budget_ms);
  }
};

void AddTargetFlags(CLI::App* command, TargetFlags& target) {
  command->add_option("--max-error", target.max_error,
                      "Instead of a count: the error the answer may have; the server picks method and count");
  command->add_option("--confidence", target.confidence, "Confidence of --max-error (default 0.95; 1: worst case)");
  command->add_option("--time-budget-ms", target.time_budget_ms,
                      "Instead of a count: as accurate as possible within this many milliseconds");
}

// "chosen: raycast {samples: 2048}, predicted 12.3 ms (of 17 plans)" for a
// target's answer; nothing otherwise.
void PrintChosenPlan(const visq::v1::Accuracy& accuracy) {
  if (accuracy.plans_size() == 0) return;
  std::string parameters;
  for (const auto& [name, value] : accuracy.parameters())
    parameters += fmt::format("{}{}: {}", parameters.empty() ? "" : ", ", name, value);
  fmt::print("chosen: {} {{{}}}, predicted {:.1f} ms (of {} plans weighed)\n", accuracy.method(), parameters,
             accuracy.predicted_ms(), accuracy.plans_size());
}

int Fail(const visq::Status& status) {
  std::cerr << "visq: " << absl::StatusCodeToString(status.code()) << ": " << status.message() << "\n";
  return status.code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"visq: visibility queries against a visq-server"};
  app.set_version_flag("--version", std::string("visq ") + visq::kVersion + " (" + visq::kBuildCommit + ")");
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

  // --- hidden-map --------------------------------------------------------
  std::string hm_scene, hm_source, hm_receiver, hm_method = "raster", hm_lookup = "exact", hm_png;
  uint32_t hm_samples = 256, hm_width = 128, hm_height = 128;
  uint64_t hm_seed = 1;
  bool hm_decorrelate = false, hm_watertight = false, hm_bits = false;
  auto* hidden_map = app.add_subcommand("hidden-map", "Hidden-sample map: per receiver texel, the source samples hidden");
  hidden_map->add_option("--scene", hm_scene, "Scene name")->required();
  hidden_map->add_option("--source", hm_source, "Source patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  hidden_map->add_option("--receiver", hm_receiver, "Receiver patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  hidden_map->add_option("--samples", hm_samples, "Source samples (1..4096)")->capture_default_str();
  hidden_map->add_option("--seed", hm_seed, "Jitter seed")->capture_default_str();
  hidden_map->add_option("--width", hm_width, "Receiver texels across")->capture_default_str();
  hidden_map->add_option("--height", hm_height, "Receiver texels down")->capture_default_str();
  hidden_map->add_option("--method", hm_method, "raster, raycast or exact (the Plücker method)")->capture_default_str();
  hidden_map->add_option("--lookup", hm_lookup, "exact or fast")->capture_default_str();
  hidden_map->add_flag("--decorrelate", hm_decorrelate, "Per-texel sample offsets (noise instead of aliasing)");
  hidden_map->add_flag("--watertight", hm_watertight, "Front-face culling for closed casters");
  hidden_map->add_flag("--bitmasks", hm_bits, "Also fetch the raw bitmasks (counted in --json)");
  hidden_map->add_option("--png", hm_png, "Write the visible fraction as a PNG");
  TargetFlags hm_target;
  AddTargetFlags(hidden_map, hm_target);
  AddCommonFlags(hidden_map, flags);
  hidden_map->callback([&] {
    visq::v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name(hm_scene);
    if (!ParsePatch(hm_source, request.mutable_source()) || !ParsePatch(hm_receiver, request.mutable_receiver())) {
      exit_code = Fail(absl::InvalidArgumentError("--source/--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'"));
      return;
    }
    request.mutable_samples()->set_seed(hm_seed);
    request.set_width(hm_width);
    request.set_height(hm_height);
    if (hm_target.set()) {
      hm_target.Fill(request.mutable_target());
    } else {
      request.mutable_samples()->set_count(hm_samples);
      request.set_method(hm_method == "raycast" ? visq::v1::RAYCAST
                         : hm_method == "exact" ? visq::v1::PLUCKER_EXACT
                                                : visq::v1::RASTER);
    }
    request.set_lookup(hm_lookup == "fast" ? visq::v1::FAST : visq::v1::EXACT);
    request.set_decorrelate(hm_decorrelate);
    request.set_watertight(hm_watertight);
    request.set_want_bitmasks(hm_bits);
    auto client = MakeClient(flags);
    auto map = client.ComputeHiddenSampleMap(request);
    if (!map.ok()) { exit_code = Fail(map.status()); return; }
    double mean = 0;
    for (float v : map->visible_fraction) mean += v;
    mean /= std::max<size_t>(1, map->visible_fraction.size());
    if (!hm_png.empty()) {
      const bool rgb = !map->visible_rgb.empty();
      if (!WritePng(hm_png, map->figures.width(), map->figures.height(), rgb ? 3 : 1,
                    rgb ? map->visible_rgb : map->visible_fraction)) {
        exit_code = Fail(absl::InternalError("cannot write " + hm_png));
        return;
      }
    }
    if (flags.json) {
      visq::v1::HiddenSampleMapResponse figures = map->figures;
      figures.clear_source_samples();
      fmt::print("{{\"mean_visible_fraction\": {}, \"texels\": {}, \"bitmask_words\": {}, \"figures\": {}}}\n",
                 mean, map->visible_fraction.size(), map->blocked_bits.size(), ToJson(figures));
      return;
    }
    const auto& f = map->figures;
    fmt::print("{}x{} texels, {} samples, {}: mean visible fraction {:.4f}\n", f.width(), f.height(),
               f.sample_count(), f.accuracy().method(), mean);
    fmt::print("error bound +-{:.4f} at confidence {} ({})\n", f.accuracy().error_bound(), f.accuracy().confidence(),
               f.accuracy().note());
    PrintChosenPlan(f.accuracy());
    fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", f.timing().queue_ms(),
               f.timing().compute_ms(), f.timing().transfer_ms(), f.timing().total_ms());
    if (!hm_png.empty()) fmt::print("wrote {}\n", hm_png);
  });

  // --- patch-visibility ----------------------------------------------------
  std::string pv_scene, pv_source, pv_receiver, pv_method = "raster", pv_lookup = "exact";
  uint32_t pv_source_grid = 32, pv_receiver_grid = 32, pv_limit = 0;
  auto* patch_visibility = app.add_subcommand("patch-visibility", "Mutual visibility of two patches, both sampled");
  patch_visibility->add_option("--scene", pv_scene, "Scene name")->required();
  patch_visibility->add_option("--source", pv_source, "Source patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  patch_visibility->add_option("--receiver", pv_receiver, "Receiver patch")->required();
  patch_visibility->add_option("--source-grid", pv_source_grid, "Samples per side on the source")->capture_default_str();
  patch_visibility->add_option("--receiver-grid", pv_receiver_grid, "Samples per side on the receiver")
      ->capture_default_str();
  patch_visibility->add_option("--method", pv_method, "raster, raycast or exact (the Plücker method)")
      ->capture_default_str();
  patch_visibility->add_option("--lookup", pv_lookup, "exact or fast")->capture_default_str();
  patch_visibility->add_option("--unblocked-limit", pv_limit, "Return up to this many unblocked rays");
  TargetFlags pv_target;
  AddTargetFlags(patch_visibility, pv_target);
  AddCommonFlags(patch_visibility, flags);
  patch_visibility->callback([&] {
    visq::v1::PatchVisibilityRequest request;
    request.mutable_scene()->set_name(pv_scene);
    if (!ParsePatch(pv_source, request.mutable_source()) || !ParsePatch(pv_receiver, request.mutable_receiver())) {
      exit_code = Fail(absl::InvalidArgumentError("--source/--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'"));
      return;
    }
    request.set_receiver_columns(pv_receiver_grid);
    request.set_receiver_rows(pv_receiver_grid);
    if (pv_target.set()) {
      pv_target.Fill(request.mutable_target());
    } else {
      request.set_source_columns(pv_source_grid);
      request.set_source_rows(pv_source_grid);
      request.set_method(pv_method == "raycast" ? visq::v1::RAYCAST
                         : pv_method == "exact" ? visq::v1::PLUCKER_EXACT
                                                : visq::v1::RASTER);
    }
    request.set_lookup(pv_lookup == "fast" ? visq::v1::FAST : visq::v1::EXACT);
    request.set_unblocked_limit(pv_limit);
    auto client = MakeClient(flags);
    auto response = client.PatchVisibility(request);
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (flags.json) { fmt::print("{}", ToJson(*response)); return; }
    fmt::print("mutual visible fraction {:.5f} ({} unblocked rays), +-{:.4f} ({})\n",
               response->mutual_visible_fraction(), response->unblocked_total(), response->accuracy().error_bound(),
               response->accuracy().method());
    PrintChosenPlan(response->accuracy());
    fmt::print("time: total {:.1f} ms (compute {:.1f} ms)\n", response->timing().total_ms(),
               response->timing().compute_ms());
  });

  // --- light-visibility ------------------------------------------------------
  std::string lv_scene, lv_light, lv_points_file, lv_receiver, lv_png;
  double lv_radiance = 1.0;
  uint32_t lv_width = 64, lv_height = 64;
  bool lv_polygons = false;
  auto* light_visibility = app.add_subcommand("light-visibility",
                                              "Exact visibility of an area light from points (or a receiver patch)");
  light_visibility->add_option("--scene", lv_scene, "Scene name")->required();
  light_visibility->add_option("--light", lv_light, "Light polygon 'x,y,z;x,y,z;...' (front: counter-clockwise)")
      ->required();
  light_visibility->add_option("--radiance", lv_radiance, "Emitted radiance")->capture_default_str();
  light_visibility->add_option("--points", lv_points_file, "File of points, one 'x y z [nx ny nz]' per line");
  light_visibility->add_option("--receiver", lv_receiver, "Or: a receiver patch sampled at texel centers");
  light_visibility->add_option("--width", lv_width, "Receiver texels across")->capture_default_str();
  light_visibility->add_option("--height", lv_height, "Receiver texels down")->capture_default_str();
  light_visibility->add_option("--png", lv_png, "Write the receiver's exact soft shadow (visible fraction) as a PNG");
  light_visibility->add_flag("--polygons", lv_polygons, "Return the visible parts of the light (with --json)");
  AddCommonFlags(light_visibility, flags);
  light_visibility->callback([&] {
    visq::v1::LightVisibilityRequest request;
    request.mutable_scene()->set_name(lv_scene);
    request.set_radiance(lv_radiance);
    request.set_want_polygons(lv_polygons);
    for (size_t start = 0; start < lv_light.size();) {
      size_t end = lv_light.find(';', start);
      if (end == std::string::npos) end = lv_light.size();
      if (!ParseVec3(lv_light.substr(start, end - start), request.mutable_light()->add_vertices())) {
        exit_code = Fail(absl::InvalidArgumentError("--light: expected 'x,y,z;x,y,z;...'"));
        return;
      }
      start = end + 1;
    }
    if (!lv_receiver.empty()) {
      visq::v1::Patch patch;
      if (!ParsePatch(lv_receiver, &patch)) {
        exit_code = Fail(absl::InvalidArgumentError("--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'"));
        return;
      }
      const glm::dvec3 o(patch.origin().x(), patch.origin().y(), patch.origin().z());
      const glm::dvec3 u(patch.edge_u().x(), patch.edge_u().y(), patch.edge_u().z());
      const glm::dvec3 v(patch.edge_v().x(), patch.edge_v().y(), patch.edge_v().z());
      const glm::dvec3 n = glm::normalize(glm::cross(u, v));
      for (uint32_t y = 0; y < lv_height; ++y)
        for (uint32_t x = 0; x < lv_width; ++x) {
          const glm::dvec3 p = o + u * ((x + 0.5) / lv_width) + v * ((y + 0.5) / lv_height);
          auto* point = request.add_points();
          point->mutable_position()->set_x(p.x);
          point->mutable_position()->set_y(p.y);
          point->mutable_position()->set_z(p.z);
          point->mutable_normal()->set_x(n.x);
          point->mutable_normal()->set_y(n.y);
          point->mutable_normal()->set_z(n.z);
        }
    } else if (!lv_points_file.empty()) {
      std::ifstream in(lv_points_file);
      if (!in) { exit_code = Fail(absl::NotFoundError("cannot read " + lv_points_file)); return; }
      std::string line;
      while (std::getline(in, line)) {
        double values[6];
        const int n = std::sscanf(line.c_str(), "%lf %lf %lf %lf %lf %lf", &values[0], &values[1], &values[2],
                                  &values[3], &values[4], &values[5]);
        if (n < 3) continue;
        auto* point = request.add_points();
        point->mutable_position()->set_x(values[0]);
        point->mutable_position()->set_y(values[1]);
        point->mutable_position()->set_z(values[2]);
        if (n == 6) {
          point->mutable_normal()->set_x(values[3]);
          point->mutable_normal()->set_y(values[4]);
          point->mutable_normal()->set_z(values[5]);
        }
      }
    } else {
      exit_code = Fail(absl::InvalidArgumentError("give --points FILE or --receiver PATCH"));
      return;
    }
    auto client = MakeClient(flags);
    auto response = client.LightVisibility(request);
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (!lv_png.empty() && !lv_receiver.empty()) {
      std::vector<float> image;
      for (const auto& p : response->points()) image.push_back(static_cast<float>(p.visible_fraction()));
      if (!WritePng(lv_png, lv_width, lv_height, 1, image)) {
        exit_code = Fail(absl::InternalError("cannot write " + lv_png));
        return;
      }
    }
    if (flags.json) { fmt::print("{}", ToJson(*response)); return; }
    if (lv_receiver.empty())
      for (const auto& p : response->points())
        fmt::print("{:.9f} {:.9g}\n", p.visible_fraction(), p.irradiance());
    const auto& t = response->tree();
    fmt::print("{} points, exact; {} tree(s), {} built ({} nodes, {} refinements, {} bytes; {} of their {} "
               "queries answered before them: {} wholly visible, {} wholly hidden, {} subtracted directly); {:.1f} ms\n",
               response->points_size(), t.trees(), t.trees_created(), t.nodes(), t.refinements(), t.memory_bytes(),
               t.wholly_visible() + t.wholly_hidden() + t.subtracted_directly(), t.queries(), t.wholly_visible(),
               t.wholly_hidden(), t.subtracted_directly(),
               response->timing().total_ms());
    if (!lv_png.empty()) fmt::print("wrote {}\n", lv_png);
  });

  // --- voxelize ----------------------------------------------------------------
  std::string vx_scene, vx_png;
  uint32_t vx_width = 128, vx_height = 128, vx_slices = 128, vx_axis = 1;
  bool vx_solid = false, vx_local = false, vx_conservative = false;
  auto* voxelize = app.add_subcommand("voxelize", "Slicemap voxelization of a scene (bits per voxel)");
  voxelize->add_option("--scene", vx_scene, "Scene name")->required();
  voxelize->add_option("--width", vx_width, "Texels along the first axis")->capture_default_str();
  voxelize->add_option("--height", vx_height, "Texels along the second axis")->capture_default_str();
  voxelize->add_option("--slices", vx_slices, "Slices along the depth axis")->capture_default_str();
  voxelize->add_option("--axis", vx_axis, "Depth axis: 0 = x, 1 = y, 2 = z")->capture_default_str();
  voxelize->add_flag("--solid", vx_solid, "Solid voxelization (inside of closed meshes)");
  voxelize->add_flag("--local", vx_local, "Local precision: slices between each column's near and far geometry");
  voxelize->add_flag("--conservative", vx_conservative, "Never miss a triangle, even edge-on");
  voxelize->add_option("--png", vx_png, "Write the occupancy projected along the depth axis (fraction of slices)");
  AddCommonFlags(voxelize, flags);
  voxelize->callback([&] {
    visq::v1::VoxelizeRequest request;
    request.mutable_scene()->set_name(vx_scene);
    request.set_width(vx_width);
    request.set_height(vx_height);
    request.set_slices(vx_slices);
    request.set_depth_axis(vx_axis);
    request.set_mode(vx_solid ? visq::v1::VoxelizeRequest::SOLID : visq::v1::VoxelizeRequest::SURFACE);
    request.set_local_precision(vx_local);
    request.set_conservative(vx_conservative);
    auto client = MakeClient(flags);
    auto grid = client.Voxelize(request);
    if (!grid.ok()) { exit_code = Fail(grid.status()); return; }
    const auto& f = grid->figures;
    if (!vx_png.empty()) {
      std::vector<float> image(size_t(f.width()) * f.height());
      for (uint32_t y = 0; y < f.height(); ++y)
        for (uint32_t x = 0; x < f.width(); ++x) {
          uint32_t count = 0;
          for (uint32_t w = 0; w < f.words_per_column(); ++w)
            count += std::popcount(grid->bits[(size_t(y) * f.width() + x) * f.words_per_column() + w]);
          image[size_t(y) * f.width() + x] = std::min(1.0f, 8.0f * count / float(f.slices()));
        }
      if (!WritePng(vx_png, f.width(), f.height(), 1, image)) {
        exit_code = Fail(absl::InternalError("cannot write " + vx_png));
        return;
      }
    }
    if (flags.json) { fmt::print("{}", ToJson(f)); return; }
    fmt::print("{}x{}x{} ({}, {}): {} occupied voxels, {} ambiguous columns, {} pass(es)\n", f.width(), f.height(),
               f.slices(), f.rasterization(), f.precision(), f.occupied_voxels(), f.ambiguous_columns(), f.passes());
    fmt::print("accuracy: {}\ntime: total {:.1f} ms (compute {:.1f} ms)\n", f.accuracy().note(),
               f.timing().total_ms(), f.timing().compute_ms());
    if (!vx_png.empty()) fmt::print("wrote {}\n", vx_png);
  });

  // --- transmittance -------------------------------------------------------------
  std::string tr_scene, tr_light, tr_kind = "directional", tr_receiver, tr_png;
  std::vector<std::string> tr_absorbers;
  uint32_t tr_width = 64, tr_height = 64, tr_resolution = 256, tr_slices = 256;
  auto* transmittance = app.add_subcommand("transmittance", "Light reaching a receiver through absorbing nodes");
  transmittance->add_option("--scene", tr_scene, "Scene name")->required();
  transmittance->add_option("--light", tr_light, "Light direction (directional) or position (point) 'x,y,z'")->required();
  transmittance->add_option("--light-kind", tr_kind, "directional or point")->capture_default_str();
  transmittance->add_option("--absorber", tr_absorbers, "NODE=SIGMA (repeatable)")->required();
  transmittance->add_option("--receiver", tr_receiver, "Receiver patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  transmittance->add_option("--width", tr_width, "Receiver texels across")->capture_default_str();
  transmittance->add_option("--height", tr_height, "Receiver texels down")->capture_default_str();
  transmittance->add_option("--resolution", tr_resolution, "Light-view resolution")->capture_default_str();
  transmittance->add_option("--slices", tr_slices, "Slices")->capture_default_str();
  transmittance->add_option("--png", tr_png, "Write the transmittance as a PNG");
  AddCommonFlags(transmittance, flags);
  transmittance->callback([&] {
    visq::v1::TransmittanceRequest request;
    request.mutable_scene()->set_name(tr_scene);
    const bool point = tr_kind == "point";
    request.set_light_kind(point ? visq::v1::TransmittanceRequest::POINT : visq::v1::TransmittanceRequest::DIRECTIONAL);
    if (!ParseVec3(tr_light, point ? request.mutable_light_position() : request.mutable_light_direction()) ||
        !ParsePatch(tr_receiver, request.mutable_receiver())) {
      exit_code = Fail(absl::InvalidArgumentError("--light 'x,y,z' and --receiver 'o;u;v' expected"));
      return;
    }
    for (const auto& a : tr_absorbers) {
      const size_t eq = a.rfind('=');
      auto* absorber = request.add_absorbers();
      absorber->set_node(a.substr(0, eq));
      absorber->set_absorption(eq == std::string::npos ? 1.0 : std::atof(a.c_str() + eq + 1));
    }
    request.set_receiver_width(tr_width);
    request.set_receiver_height(tr_height);
    request.set_resolution(tr_resolution);
    request.set_slices(tr_slices);
    auto client = MakeClient(flags);
    auto response = client.Transmittance(request);
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (!tr_png.empty()) {
      std::vector<float> image(response->transmittance().begin(), response->transmittance().end());
      if (!WritePng(tr_png, tr_width, tr_height, 1, image)) {
        exit_code = Fail(absl::InternalError("cannot write " + tr_png));
        return;
      }
    }
    if (flags.json) { fmt::print("{}", ToJson(*response)); return; }
    double mean = 0;
    for (float t : response->transmittance()) mean += t;
    mean /= std::max(1, response->transmittance_size());
    fmt::print("{} texels: mean transmittance {:.4f}; {}\n", response->transmittance_size(), mean,
               response->accuracy().note());
    fmt::print("time: total {:.1f} ms\n", response->timing().total_ms());
  });

  // --- volumetric ------------------------------------------------------------------
  std::string vo_scene, vo_light = "0.3,-1,0.2", vo_png, vo_method = "min-max";
  CameraFlags vo_camera;
  uint32_t vo_map = 1024;
  double vo_scattering = 0.05, vo_extinction = 0.05, vo_intensity = 1.0;
  bool vo_combined = false;
  auto* volumetric = app.add_subcommand("volumetric", "Volumetric shadows (light shafts) from a camera");
  volumetric->add_option("--scene", vo_scene, "Scene name")->required();
  AddCameraFlags(volumetric, vo_camera);
  volumetric->add_option("--sun", vo_light, "Direction the sunlight travels 'x,y,z'")->capture_default_str();
  volumetric->add_option("--shadow-map", vo_map, "Shadow map size (power of two)")->capture_default_str();
  volumetric->add_option("--scattering", vo_scattering, "sigma_s per world unit")->capture_default_str();
  volumetric->add_option("--extinction", vo_extinction, "sigma_t per world unit")->capture_default_str();
  volumetric->add_option("--intensity", vo_intensity, "Light intensity")->capture_default_str();
  volumetric->add_option("--method", vo_method, "min-max or ray-marching")->capture_default_str();
  volumetric->add_flag("--combined", vo_combined, "Add the directly lit surfaces");
  volumetric->add_option("--png", vo_png, "Write the image (tone-mapped to its peak)");
  AddCommonFlags(volumetric, flags);
  volumetric->callback([&] {
    visq::v1::VolumetricShadowRequest request;
    request.mutable_scene()->set_name(vo_scene);
    if (visq::Status camera = FillCamera(vo_camera, &request); !camera.ok()) {
      exit_code = Fail(camera);
      return;
    }
    if (!ParseVec3(vo_light, request.mutable_light_direction())) {
      exit_code = Fail(absl::InvalidArgumentError("--sun: expected 'x,y,z'"));
      return;
    }
    request.set_shadow_map_size(vo_map);
    request.set_scattering(vo_scattering);
    request.set_extinction(vo_extinction);
    request.set_light_intensity(vo_intensity);
    request.set_method(vo_method == "ray-marching" ? visq::v1::VolumetricShadowRequest::RAY_MARCHING
                                                   : visq::v1::VolumetricShadowRequest::MIN_MAX);
    request.set_combined_image(vo_combined);
    auto client = MakeClient(flags);
    auto image = client.VolumetricShadow(request);
    if (!image.ok()) { exit_code = Fail(image.status()); return; }
    const auto& f = image->figures;
    if (!vo_png.empty()) {
      std::vector<float> rgb = vo_combined ? image->combined : image->inscattering;
      float peak = 1e-20f;
      for (float v : rgb) peak = std::max(peak, v);
      if (!WriteTopFirstPng(vo_png, f.width(), f.height(), rgb, 1.0f / peak)) {
        exit_code = Fail(absl::InternalError("cannot write " + vo_png));
        return;
      }
    }
    if (flags.json) { fmt::print("{}", ToJson(f)); return; }
    fmt::print("{}x{} {} ({} integrand, {}x{} rectified)\n", f.width(), f.height(), f.method(), f.integrand(),
               f.rectified_rows(), f.rectified_columns());
    for (const auto& [stage, ms] : f.stage_ms()) fmt::print("  {:<14} {:8.1f} ms\n", stage, ms);
    fmt::print("total {:.1f} ms\n", f.timing().total_ms());
    if (!vo_png.empty()) fmt::print("wrote {}\n", vo_png);
  });

  // --- obscurance, move, obscurance-update -----------------------------------
  std::string ob_scene, ob_png;
  uint32_t ob_resolution = 256, ob_directions = 256;
  uint64_t ob_seed = 1;
  double ob_d_max = 0;
  bool ob_bleeding = false, ob_built_atlas = false;
  auto* obscurance = app.add_subcommand("obscurance", "Bake obscurances (W and I per atlas texel) on the GPU");
  obscurance->add_option("--scene", ob_scene, "Scene name")->required();
  obscurance->add_option("--d-max", ob_d_max, "Occlusion distance in scene units (> 0)")->required();
  obscurance->add_option("--resolution", ob_resolution, "Atlas texels across and down")->capture_default_str();
  obscurance->add_option("--directions", ob_directions, "Global directions of the bake")->capture_default_str();
  obscurance->add_option("--seed", ob_seed, "Direction sequence seed")->capture_default_str();
  obscurance->add_flag("--color-bleeding", ob_bleeding, "RGB obscurances weighted by the reflectivity seen");
  obscurance->add_flag("--built-atlas", ob_built_atlas, "Build an atlas even when the scene has TEXCOORD_1");
  obscurance->add_option("--png", ob_png, "Write the W atlas as a PNG");
  TargetFlags ob_target;
  AddTargetFlags(obscurance, ob_target);
  uint32_t ob_rays = 0;
  obscurance->add_option("--rays-per-patch", ob_rays,
                         "Instead of the GPU bake: the ray-cast estimator (Embree) with this many rays per patch");
  AddCommonFlags(obscurance, flags);
  obscurance->callback([&] {
    visq::v1::ComputeObscurancesRequest request;
    request.mutable_scene()->set_name(ob_scene);
    request.set_d_max(ob_d_max);
    request.set_resolution(ob_resolution);
    if (ob_target.set()) {
      ob_target.Fill(request.mutable_target());
    } else if (ob_rays > 0) {
      request.set_method(visq::v1::ComputeObscurancesRequest::RAYCAST);
      request.set_rays_per_patch(ob_rays);
    } else {
      request.set_direction_count(ob_directions);
    }
    request.set_seed(ob_seed);
    request.set_color_bleeding(ob_bleeding);
    request.set_force_built_atlas(ob_built_atlas);
    auto client = MakeClient(flags);
    // A progress bar on stderr, rewritten in place.
    bool progress_shown = false;
    auto progress = [&progress_shown](const visq::v1::ObscuranceProgress& p) {
      progress_shown = true;
      const int width = 30;
      const int done = p.directions_total() ? static_cast<int>(int64_t{width} * p.directions_done() / p.directions_total()) : 0;
      fmt::print(stderr, "\r[{}{}] {}/{} directions, {:.1f} s, ~{:.1f} s left ", std::string(done, '='),
                 std::string(width - done, ' '), p.directions_done(), p.directions_total(), p.elapsed_s(),
                 p.estimated_s_left());
      std::fflush(stderr);
    };
    auto bake = client.ComputeObscurances(request, progress);
    if (progress_shown) fmt::print(stderr, "\n");
    if (!bake.ok()) { exit_code = Fail(bake.status()); return; }
    const auto& f = bake->figures;
    double mean = 0;
    size_t estimated = 0;
    for (size_t t = 0; t < bake->estimated.size(); ++t)
      if (bake->estimated[t]) {
        mean += (bake->w[3 * t] + bake->w[3 * t + 1] + bake->w[3 * t + 2]) / 3.0;
        ++estimated;
      }
    mean /= std::max<size_t>(1, estimated);
    if (!ob_png.empty() &&
        !WritePng(ob_png, static_cast<int>(f.atlas().width()), static_cast<int>(f.atlas().height()), 3, bake->w)) {
      exit_code = Fail(absl::InternalError("cannot write " + ob_png));
      return;
    }
    if (flags.json) {
      fmt::print("{{\"mean_w\": {}, \"estimated_texels\": {}, \"figures\": {}}}\n", mean, estimated, ToJson(f));
      return;
    }
    const std::string how = f.accuracy().method() == "obscurance-raycast"
                                ? fmt::format("{} rays per patch (Embree)", f.accuracy().parameters().at("rays_per_patch"))
                                : fmt::format("{} directions, {} layers", bake->partial.DirectionCount(), f.layers());
    fmt::print("{}x{} atlas ({}), {}: mean W {:.4f} over {} estimated texels\n", f.atlas().width(),
               f.atlas().height(), f.atlas().from_lightmap_uvs() ? "TEXCOORD_1" : "built", how, mean, estimated);
    fmt::print("I_A ({:.4g}, {:.4g}, {:.4g}){}; {:.1f} samples per patch\n", f.ambient_intensity().x(),
               f.ambient_intensity().y(), f.ambient_intensity().z(), f.ambient_clamped() ? " (R_ave clamped)" : "",
               f.mean_samples_per_patch());
    fmt::print("error +-{:.4f} at confidence {} ({})\n", f.accuracy().error_bound(), f.accuracy().confidence(),
               f.accuracy().note());
    PrintChosenPlan(f.accuracy());
    fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", f.timing().queue_ms(),
               f.timing().compute_ms(), f.timing().transfer_ms(), f.timing().total_ms());
    if (!ob_png.empty()) fmt::print("wrote {}\n", ob_png);
  });

  std::string mv_node, mv_scene, mv_matrix;
  bool mv_index = false;
  auto* move = app.add_subcommand("move", "Move a node and its subtree (in the server's memory; not stored)");
  move->add_option("NODE", mv_node, "Node name (or index with --index)")->required();
  move->add_option("--scene", mv_scene, "Scene name")->required();
  move->add_option("--matrix", mv_matrix, "New node-to-world matrix: 16 numbers m0,...,m15, column-major like glTF")
      ->required();
  move->add_flag("--index", mv_index, "NODE is an index into the scene's nodes");
  AddCommonFlags(move, flags);
  move->callback([&] {
    visq::v1::SetNodeTransformRequest request;
    request.mutable_scene()->set_name(mv_scene);
    if (mv_index) {
      char* end = nullptr;
      const unsigned long index = std::strtoul(mv_node.c_str(), &end, 10);
      if (end == mv_node.c_str() || *end != '\0') {
        exit_code = Fail(absl::InvalidArgumentError("NODE: '" + mv_node + "' is not an index"));
        return;
      }
      request.set_node_index(static_cast<uint32_t>(index));
    } else {
      request.set_node_name(mv_node);
    }
    for (size_t start = 0; start <= mv_matrix.size();) {
      size_t end = mv_matrix.find(',', start);
      if (end == std::string::npos) end = mv_matrix.size();
      const std::string item = mv_matrix.substr(start, end - start);
      char* tail = nullptr;
      const double v = std::strtod(item.c_str(), &tail);
      if (item.empty() || *tail != '\0') {
        exit_code = Fail(absl::InvalidArgumentError("--matrix: '" + item + "' is not a number"));
        return;
      }
      request.add_world_matrix(v);
      start = end + 1;
    }
    auto client = MakeClient(flags);
    auto info = client.SetNodeTransform(request);
    if (!info.ok()) { exit_code = Fail(info.status()); return; }
    if (flags.json) { fmt::print("{}", ToJson(*info)); return; }
    fmt::print("moved {}: ", mv_node);
    PrintScene(*info, false);
  });

  std::string ou_scene;
  auto* obscurance_update = app.add_subcommand("obscurance-update",
                                               "Update the last obscurance bake after node moves (changed patches only)");
  obscurance_update->add_option("--scene", ou_scene, "Scene name")->required();
  AddCommonFlags(obscurance_update, flags);
  obscurance_update->callback([&] {
    visq::v1::UpdateObscurancesRequest request;
    request.mutable_scene()->set_name(ou_scene);
    auto client = MakeClient(flags);
    auto response = client.UpdateObscurances(request);
    if (!response.ok()) { exit_code = Fail(response.status()); return; }
    if (flags.json) { fmt::print("{}", ToJson(*response)); return; }
    const auto& r = *response;
    fmt::print("version {} -> {}: {} move(s), {} texels, {} triangles, {} vertices changed\n", r.from_version(),
               r.scene_version(), r.moves_applied(), r.texels_size(), r.triangles_size(), r.vertices_size());
    fmt::print("influenced patches {} -> {}, own {}, candidates {}, recomputed {}, {} rays ({} per patch)\n",
               r.influenced_before(), r.influenced_after(), r.own_patches(), r.candidates(), r.recomputed(), r.rays(),
               r.rays_per_patch());
    fmt::print("time: compute {:.1f} ms, total {:.1f} ms\n", r.timing().compute_ms(), r.timing().total_ms());
  });

  std::string op_scene, op_png, op_quantity = "w";
  CameraFlags op_camera;
  auto* obscurance_preview = app.add_subcommand(
      "obscurance-preview", "Render the scene from a camera with the current obscurance solution (W or I) applied");
  obscurance_preview->add_option("SCENE,--scene", op_scene, "Scene name")->required();
  AddCameraFlags(obscurance_preview, op_camera);
  obscurance_preview->add_option("--quantity", op_quantity, "w (obscurance W) or i (intensity I)")
      ->check(CLI::IsMember({"w", "i", "W", "I", "intensity"}))
      ->capture_default_str();
  obscurance_preview->add_option("--png", op_png,
                                 "Write the image: W as is, I tone-mapped to its peak; linear values, background black")
      ->required();
  AddCommonFlags(obscurance_preview, flags);
  obscurance_preview->callback([&] {
    visq::v1::ObscurancePreviewRequest request;
    request.mutable_scene()->set_name(op_scene);
    if (visq::Status camera = FillCamera(op_camera, &request); !camera.ok()) {
      exit_code = Fail(camera);
      return;
    }
    const bool intensity = op_quantity != "w" && op_quantity != "W";
    request.set_quantity(intensity ? visq::v1::ObscurancePreviewRequest::INTENSITY
                                   : visq::v1::ObscurancePreviewRequest::W);
    auto client = MakeClient(flags);
    auto preview = client.RenderObscurancePreview(request);
    if (!preview.ok()) { exit_code = Fail(preview.status()); return; }
    const auto& f = preview->figures;
    float peak = 1e-20f;
    for (float v : preview->rgb) peak = std::max(peak, v);
    if (!WriteTopFirstPng(op_png, f.width(), f.height(), preview->rgb, intensity ? 1.0f / peak : 1.0f)) {
      exit_code = Fail(absl::InternalError("cannot write " + op_png));
      return;
    }
    size_t covered = 0;
    for (uint8_t c : preview->covered) covered += c;
    if (flags.json) {
      fmt::print("{{\"png\": \"{}\", \"covered_pixels\": {}, \"peak\": {}, \"figures\": {}}}\n", op_png, covered,
                 peak, ToJson(f));
      return;
    }
    fmt::print("{}x{} {} of solution version {}: {} of {} pixels covered, peak {:.4g}\n", f.width(), f.height(),
               intensity ? "I" : "W", f.solution_version(), covered, preview->covered.size(), peak);
    fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", f.timing().queue_ms(),
               f.timing().compute_ms(), f.timing().transfer_ms(), f.timing().total_ms());
    fmt::print("wrote {}\n", op_png);
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
  });

  CLI11_PARSE(app, argc, argv);
  return exit_code;
}
