// visq obscurance, move, obscurance-update, obscurance-preview: bake,
// move nodes, bring the bake up to date, look at it.
#include <algorithm>
#include <cstdio>
#include <cstdlib>

#include <fmt/format.h>

#include "cli_common.h"

namespace visq::cli {
namespace {

struct BakeOptions {
  std::string scene, png, npy;
  uint32_t resolution = 256, directions = 256, rays = 0;
  uint64_t seed = 1;
  double d_max = 0;
  bool bleeding = false, built_atlas = false;
  TargetFlags target;
};

Status RunBake(const BakeOptions& o, Cli& cli) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name(o.scene);
  request.set_d_max(o.d_max);
  request.set_resolution(o.resolution);
  if (o.target.set()) {
    o.target.Fill(request.mutable_target());
  } else if (o.rays > 0) {
    request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
    request.set_rays_per_patch(o.rays);
  } else {
    request.set_direction_count(o.directions);
  }
  request.set_seed(o.seed);
  request.set_color_bleeding(o.bleeding);
  request.set_force_built_atlas(o.built_atlas);
  auto client = MakeClient(cli.flags);
  // A progress bar on stderr, rewritten in place.
  bool progress_shown = false;
  auto progress = [&progress_shown](const v1::ObscuranceProgress& p) {
    progress_shown = true;
    const int width = 30;
    const int done =
        p.directions_total() ? static_cast<int>(int64_t{width} * p.directions_done() / p.directions_total()) : 0;
    fmt::print(stderr, "\r[{}{}] {}/{} directions, {:.1f} s, ~{:.1f} s left ", std::string(done, '='),
               std::string(width - done, ' '), p.directions_done(), p.directions_total(), p.elapsed_s(),
               p.estimated_s_left());
    std::fflush(stderr);
  };
  auto bake = client.ComputeObscurances(request, progress);
  if (progress_shown) fmt::print(stderr, "\n");
  VISQ_RETURN_IF_ERROR(bake.status());
  const auto& f = bake->figures;
  double mean = 0;
  size_t estimated = 0;
  for (size_t t = 0; t < bake->estimated.size(); ++t)
    if (bake->estimated[t]) {
      mean += (bake->w[3 * t] + bake->w[3 * t + 1] + bake->w[3 * t + 2]) / 3.0;
      ++estimated;
    }
  mean /= std::max<size_t>(1, estimated);
  if (!o.png.empty()) VISQ_RETURN_IF_ERROR(WritePng(o.png, f.atlas().width(), f.atlas().height(), 3, bake->w));
  // Row y of the array is atlas row y, as in the Python client.
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.atlas().height(), f.atlas().width(), 3}, bake->w));
  if (cli.flags.json) {
    fmt::print("{{\"mean_w\": {}, \"estimated_texels\": {}, \"figures\": {}}}\n", mean, estimated, ToJson(f));
    return absl::OkStatus();
  }
  const auto& parameters = f.accuracy().parameters();
  const std::string how =
      f.accuracy().method() == "obscurance-raycast" && parameters.count("rays_per_patch")
          ? fmt::format("{} rays per patch (Embree)", parameters.at("rays_per_patch"))
          : fmt::format("{} directions, {} layers", bake->partial.DirectionCount(), f.layers());
  fmt::print("{}x{} atlas ({}), {}: mean W {:.4f} over {} estimated texels\n", f.atlas().width(), f.atlas().height(),
             f.atlas().from_lightmap_uvs() ? "TEXCOORD_1" : "built", how, mean, estimated);
  fmt::print("I_A ({:.4g}, {:.4g}, {:.4g}){}; {:.1f} samples per patch\n", f.ambient_intensity().x(),
             f.ambient_intensity().y(), f.ambient_intensity().z(), f.ambient_clamped() ? " (R_ave clamped)" : "",
             f.mean_samples_per_patch());
  fmt::print("error +-{:.4f} at confidence {} ({})\n", f.accuracy().error_bound(), f.accuracy().confidence(),
             f.accuracy().note());
  PrintChosenPlan(f.accuracy());
  fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", f.timing().queue_ms(),
             f.timing().compute_ms(), f.timing().transfer_ms(), f.timing().total_ms());
  if (!o.png.empty()) fmt::print("wrote {}\n", o.png);
  if (!o.npy.empty()) fmt::print("wrote {}\n", o.npy);
  return absl::OkStatus();
}

struct MoveOptions {
  std::string node, scene, matrix;
  bool index = false;
};

Status RunMove(const MoveOptions& o, Cli& cli) {
  v1::SetNodeTransformRequest request;
  request.mutable_scene()->set_name(o.scene);
  if (o.index) {
    char* end = nullptr;
    const unsigned long index = std::strtoul(o.node.c_str(), &end, 10);
    if (end == o.node.c_str() || *end != '\0' || index > UINT32_MAX)
      return absl::InvalidArgumentError("NODE: '" + o.node + "' is not an index");
    request.set_node_index(static_cast<uint32_t>(index));
  } else {
    request.set_node_name(o.node);
  }
  for (size_t start = 0; start <= o.matrix.size();) {
    size_t end = o.matrix.find(',', start);
    if (end == std::string::npos) end = o.matrix.size();
    const std::string item = o.matrix.substr(start, end - start);
    char* tail = nullptr;
    const double v = std::strtod(item.c_str(), &tail);
    if (item.empty() || *tail != '\0') return absl::InvalidArgumentError("--matrix: '" + item + "' is not a number");
    request.add_world_matrix(v);
    start = end + 1;
  }
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::SceneInfo info, client.SetNodeTransform(request));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(info));
    return absl::OkStatus();
  }
  fmt::print("moved {}: ", o.node);
  PrintScene(info, false);
  return absl::OkStatus();
}

struct UpdateOptions {
  std::string scene;
};

Status RunUpdate(const UpdateOptions& o, Cli& cli) {
  v1::UpdateObscurancesRequest request;
  request.mutable_scene()->set_name(o.scene);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::UpdateObscurancesResponse r, client.UpdateObscurances(request));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(r));
    return absl::OkStatus();
  }
  fmt::print("version {} -> {}: {} move(s), {} texels, {} triangles, {} vertices changed\n", r.from_version(),
             r.scene_version(), r.moves_applied(), r.texels_size(), r.triangles_size(), r.vertices_size());
  fmt::print("influenced patches {} -> {}, own {}, candidates {}, recomputed {}, {} rays ({} per patch)\n",
             r.influenced_before(), r.influenced_after(), r.own_patches(), r.candidates(), r.recomputed(), r.rays(),
             r.rays_per_patch());
  fmt::print("time: compute {:.1f} ms, total {:.1f} ms\n", r.timing().compute_ms(), r.timing().total_ms());
  return absl::OkStatus();
}

struct PreviewOptions {
  std::string scene, png, npy, quantity = "w";
  CameraFlags camera;
};

Status RunPreview(const PreviewOptions& o, Cli& cli) {
  if (o.png.empty() && o.npy.empty()) return absl::InvalidArgumentError("--png, --npy: give at least one");
  v1::ObscurancePreviewRequest request;
  request.mutable_scene()->set_name(o.scene);
  VISQ_RETURN_IF_ERROR(FillCamera(o.camera, &request));
  const bool intensity = o.quantity != "w" && o.quantity != "W";
  request.set_quantity(intensity ? v1::ObscurancePreviewRequest::INTENSITY : v1::ObscurancePreviewRequest::W);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const client::ObscurancePreview preview, client.RenderObscurancePreview(request));
  const auto& f = preview.figures;
  float peak = 1e-20f;
  for (float v : preview.rgb) peak = std::max(peak, v);
  if (!o.png.empty())
    VISQ_RETURN_IF_ERROR(WriteTopFirstPng(o.png, f.width(), f.height(), preview.rgb, intensity ? 1.0f / peak : 1.0f));
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width(), 3}, preview.rgb));
  size_t covered = 0;
  for (uint8_t c : preview.covered) covered += c;
  if (cli.flags.json) {
    fmt::print("{{\"png\": \"{}\", \"covered_pixels\": {}, \"peak\": {}, \"figures\": {}}}\n", o.png, covered, peak,
               ToJson(f));
    return absl::OkStatus();
  }
  fmt::print("{}x{} {} of solution version {}: {} of {} pixels covered, peak {:.4g}\n", f.width(), f.height(),
             intensity ? "I" : "W", f.solution_version(), covered, preview.covered.size(), peak);
  fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", f.timing().queue_ms(),
             f.timing().compute_ms(), f.timing().transfer_ms(), f.timing().total_ms());
  if (!o.png.empty()) fmt::print("wrote {}\n", o.png);
  if (!o.npy.empty()) fmt::print("wrote {}\n", o.npy);
  return absl::OkStatus();
}

}  // namespace

void AddObscuranceCommands(Cli& cli) {
  auto ob = std::make_shared<BakeOptions>();
  auto* obscurance = cli.app.add_subcommand("obscurance", "Bake obscurances (W and I per atlas texel) on the GPU");
  obscurance->add_option("--scene", ob->scene, "Scene name")->required();
  obscurance->add_option("--d-max", ob->d_max, "Occlusion distance in scene units (> 0)")->required();
  obscurance->add_option("--resolution", ob->resolution, "Atlas texels across and down")->capture_default_str();
  obscurance->add_option("--directions", ob->directions, "Global directions of the bake")->capture_default_str();
  obscurance->add_option("--seed", ob->seed, "Direction sequence seed")->capture_default_str();
  obscurance->add_flag("--color-bleeding", ob->bleeding, "RGB obscurances weighted by the reflectivity seen");
  obscurance->add_flag("--built-atlas", ob->built_atlas, "Build an atlas even when the scene has TEXCOORD_1");
  obscurance->add_option("--png", ob->png, "Write the W atlas as a PNG");
  obscurance->add_option("--npy", ob->npy, "Write W as a float32 .npy (atlas height, width, 3)");
  AddTargetFlags(obscurance, ob->target);
  obscurance->add_option("--rays-per-patch", ob->rays,
                         "Instead of the GPU bake: the ray-cast estimator (Embree) with this many rays per patch");
  OnRun(obscurance, cli, ob, RunBake);

  auto mv = std::make_shared<MoveOptions>();
  auto* move = cli.app.add_subcommand("move", "Move a node and its subtree (in the server's memory; not stored)");
  move->add_option("NODE", mv->node, "Node name (or index with --index)")->required();
  move->add_option("--scene", mv->scene, "Scene name")->required();
  move->add_option("--matrix", mv->matrix, "New node-to-world matrix: 16 numbers m0,...,m15, column-major like glTF")
      ->required();
  move->add_flag("--index", mv->index, "NODE is an index into the scene's nodes");
  OnRun(move, cli, mv, RunMove);

  auto ou = std::make_shared<UpdateOptions>();
  auto* update = cli.app.add_subcommand("obscurance-update",
                                        "Update the last obscurance bake after node moves (changed patches only)");
  update->add_option("--scene", ou->scene, "Scene name")->required();
  OnRun(update, cli, ou, RunUpdate);

  auto op = std::make_shared<PreviewOptions>();
  auto* preview = cli.app.add_subcommand(
      "obscurance-preview", "Render the scene from a camera with the current obscurance solution (W or I) applied");
  preview->add_option("SCENE,--scene", op->scene, "Scene name")->required();
  AddCameraFlags(preview, op->camera);
  AddChoice(preview, "--quantity", op->quantity, {"w", "i", "W", "I", "intensity"}, "w (obscurance W) or i (intensity I)");
  preview->add_option("--png", op->png,
                      "Write the image: W as is, I tone-mapped to its peak; linear values, background black");
  preview->add_option("--npy", op->npy, "Write the linear RGB image as a float32 .npy (height, width, 3), row 0 on top");
  OnRun(preview, cli, op, RunPreview);
}

}  // namespace visq::cli
