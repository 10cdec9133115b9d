// visq hidden-map, patch-visibility: sampled visibility between patches.
#include <algorithm>

#include <fmt/format.h>

#include "cli_common.h"

namespace visq::cli {
namespace {

// "auto": the server runs the fastest here of the methods giving the same bits.
const std::vector<std::string> kMethods = {"auto", "raster", "raycast", "exact", "gpu-raycast"};
// "fast" was the Hough lookup's first name, kept for scripts that use it.
const std::vector<std::string> kLookups = {"exact", "hough", "fast"};

v1::VisibilityMethod Method(const std::string& name) {
  if (name == "auto") return v1::METHOD_UNSPECIFIED;
  if (name == "gpu-raycast") return v1::GPU_RAYCAST;
  return name == "raycast" ? v1::RAYCAST : name == "exact" ? v1::PLUCKER_EXACT : v1::RASTER;
}

struct HiddenMapOptions {
  std::string scene, source, receiver, method = "auto", lookup = "exact", png, npy, exr;
  uint32_t samples = 256, width = 128, height = 128;
  uint64_t seed = 1;
  bool decorrelate = false, watertight = false, bitmasks = false;
  TargetFlags target;
};

Status RunHiddenMap(const HiddenMapOptions& o, Cli& cli) {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name(o.scene);
  if (!ParsePatch(o.source, request.mutable_source()) || !ParsePatch(o.receiver, request.mutable_receiver()))
    return absl::InvalidArgumentError("--source/--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'");
  request.mutable_samples()->set_seed(o.seed);
  request.set_width(o.width);
  request.set_height(o.height);
  if (o.target.set()) {
    o.target.Fill(request.mutable_target());
  } else {
    request.mutable_samples()->set_count(o.samples);
    request.set_method(Method(o.method));
  }
  request.set_lookup(o.lookup == "exact" ? v1::EXACT : v1::HOUGH);
  request.set_decorrelate(o.decorrelate);
  request.set_watertight(o.watertight);
  request.set_want_bitmasks(o.bitmasks);
  auto client = MakeClient(cli.flags);
  // The bands of rows the map streams as they are made are its progress.
  StatusOr<client::HiddenSampleMap> answer;
  {
    Waiting waiting(cli.flags, "hidden-map");
    answer = client.ComputeHiddenSampleMap(request, waiting.Callback("texels"));
  }
  VISQ_ASSIGN_OR_RETURN(const client::HiddenSampleMap map, std::move(answer));
  const auto& f = map.figures;
  double mean = 0;
  for (float v : map.visible_fraction) mean += v;
  mean /= std::max<size_t>(1, map.visible_fraction.size());
  const bool rgb = !map.visible_rgb.empty();
  if (!o.png.empty())
    VISQ_RETURN_IF_ERROR(WritePng(o.png, f.width(), f.height(), rgb ? 3 : 1, rgb ? map.visible_rgb : map.visible_fraction));
  if (!o.exr.empty())
    VISQ_RETURN_IF_ERROR(WriteExr(o.exr, f.width(), f.height(), rgb ? 3 : 1, rgb ? map.visible_rgb : map.visible_fraction));
  // Row y of the array is texel row y (along the receiver's edge_v), as in
  // the Python client.
  if (!o.npy.empty()) {
    if (rgb) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width(), 3}, map.visible_rgb));
    else VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width()}, map.visible_fraction));
  }
  if (cli.flags.json) {
    v1::HiddenSampleMapResponse figures = f;
    figures.clear_source_samples();
    fmt::print("{{\"mean_visible_fraction\": {}, \"texels\": {}, \"bitmask_words\": {}, \"figures\": {}}}\n", mean,
               map.visible_fraction.size(), map.blocked_bits.size(), ToJson(figures));
    return absl::OkStatus();
  }
  fmt::print("{}x{} texels, {} samples, {}: mean visible fraction {:.4f}\n", f.width(), f.height(), f.sample_count(),
             f.accuracy().method(), mean);
  fmt::print("error bound +-{:.4f} at confidence {} ({})\n", f.accuracy().error_bound(), f.accuracy().confidence(),
             f.accuracy().note());
  PrintChosenPlan(f.accuracy());
  PrintTiming(f.timing());
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

struct PatchVisibilityOptions {
  std::string scene, source, receiver, method = "auto", lookup = "exact";
  uint32_t source_grid = 32, receiver_grid = 32, limit = 0;
  TargetFlags target;
};

Status RunPatchVisibility(const PatchVisibilityOptions& o, Cli& cli) {
  v1::PatchVisibilityRequest request;
  request.mutable_scene()->set_name(o.scene);
  if (!ParsePatch(o.source, request.mutable_source()) || !ParsePatch(o.receiver, request.mutable_receiver()))
    return absl::InvalidArgumentError("--source/--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'");
  request.set_receiver_columns(o.receiver_grid);
  request.set_receiver_rows(o.receiver_grid);
  if (o.target.set()) {
    o.target.Fill(request.mutable_target());
  } else {
    request.set_source_columns(o.source_grid);
    request.set_source_rows(o.source_grid);
    request.set_method(Method(o.method));
  }
  request.set_lookup(o.lookup == "exact" ? v1::EXACT : v1::HOUGH);
  request.set_unblocked_limit(o.limit);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::PatchVisibilityResponse response, WhileWaiting(cli.flags, "patch-visibility", [&] { return client.PatchVisibility(request); }));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(response));
    return absl::OkStatus();
  }
  fmt::print("mutual visible fraction {:.5f} ({} unblocked rays), +-{:.4f} ({})\n", response.mutual_visible_fraction(),
             response.unblocked_total(), response.accuracy().error_bound(), response.accuracy().method());
  PrintChosenPlan(response.accuracy());
  fmt::print("time: total {:.1f} ms (compute {:.1f} ms)\n", response.timing().total_ms(),
             response.timing().compute_ms());
  return absl::OkStatus();
}

}  // namespace

void AddSamplingCommands(Cli& cli) {
  auto hm = std::make_shared<HiddenMapOptions>();
  auto* hidden_map =
      cli.app.add_subcommand("hidden-map", "Hidden-sample map: per receiver texel, the source samples hidden");
  hidden_map->add_option("--scene", hm->scene, "Scene name")->required();
  hidden_map->add_option("--source", hm->source, "Source patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  hidden_map->add_option("--receiver", hm->receiver, "Receiver patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  hidden_map->add_option("--samples", hm->samples, "Source samples (1..4096; up to 65536 for jittered visible fractions, as several maps)")->capture_default_str();
  hidden_map->add_option("--seed", hm->seed, "Jitter seed")->capture_default_str();
  hidden_map->add_option("--width", hm->width, "Receiver texels across")->capture_default_str();
  hidden_map->add_option("--height", hm->height, "Receiver texels down")->capture_default_str();
  AddChoice(hidden_map, "--method", hm->method, kMethods, "auto (the server picks the fastest of raster, raycast and gpu-raycast), raster, raycast, exact (the Plücker method) or gpu-raycast (raycast's rays on the GPU)");
  AddChoice(hidden_map, "--lookup", hm->lookup, kLookups, "RASTER's lookup: exact (the ray-cast bits) or hough");
  hidden_map->add_flag("--decorrelate", hm->decorrelate, "Per-texel sample offsets (noise instead of aliasing)");
  hidden_map->add_flag("--watertight", hm->watertight, "Front-face culling for closed casters");
  hidden_map->add_flag("--bitmasks", hm->bitmasks, "Also fetch the raw bitmasks (counted in --json)");
  hidden_map->add_option("--png", hm->png, "Write the visible fraction as an 8-bit PNG (the receiver's v = 1 edge on top)");
  hidden_map->add_option("--npy", hm->npy,
                         "Write the visible fractions as a float32 .npy (height, width); RGB (height, width, 3) "
                         "for coloured lights; row y is texel row y");
  hidden_map->add_option("--exr", hm->exr, "Write the visible fractions as a float OpenEXR image (laid out as the PNG)");
  AddTargetFlags(hidden_map, hm->target);
  OnRun(hidden_map, cli, hm, RunHiddenMap);

  auto pv = std::make_shared<PatchVisibilityOptions>();
  auto* patch_visibility = cli.app.add_subcommand("patch-visibility", "Mutual visibility of two patches, both sampled");
  patch_visibility->add_option("--scene", pv->scene, "Scene name")->required();
  patch_visibility->add_option("--source", pv->source, "Source patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  patch_visibility->add_option("--receiver", pv->receiver, "Receiver patch")->required();
  patch_visibility->add_option("--source-grid", pv->source_grid, "Samples per side on the source")->capture_default_str();
  patch_visibility->add_option("--receiver-grid", pv->receiver_grid, "Samples per side on the receiver")
      ->capture_default_str();
  AddChoice(patch_visibility, "--method", pv->method, kMethods, "auto (the server picks the fastest of raster, raycast and gpu-raycast), raster, raycast, exact (the Plücker method) or gpu-raycast (raycast's rays on the GPU)");
  AddChoice(patch_visibility, "--lookup", pv->lookup, kLookups, "RASTER's lookup: exact (the ray-cast bits) or hough");
  patch_visibility->add_option("--unblocked-limit", pv->limit, "Return up to this many unblocked rays");
  AddTargetFlags(patch_visibility, pv->target);
  OnRun(patch_visibility, cli, pv, RunPatchVisibility);
}

}  // namespace visq::cli
