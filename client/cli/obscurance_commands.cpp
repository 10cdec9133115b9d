// visq obscurance, move, obscurance-update, obscurance-preview,
// obscurance-export: bake, move nodes, bring the bake up to date, look at
// it, put it on the game's mesh.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include <fmt/format.h>

#include "cli_common.h"

namespace visq::cli {
namespace {

struct BakeOptions {
  std::string scene, png, npy, exr, partial_out, errors_npy;
  uint32_t resolution = 256, directions = 256, rays = 0, first_direction = 0, total_directions = 0;
  std::string method = "auto";
  uint64_t seed = 1;
  double d_max = 0;
  bool bleeding = false, built_atlas = false;
  TargetFlags target;
};

// A farm bake's shard on disk: the fixed-point partial sums of a direction
// range (obscurance_partial.h), which merge into the whole bake bit for bit.
// Little-endian: "VISQOBP1", fingerprint u64, width, height, channels,
// total_directions, range count u32, the ranges (first, count) as u32 pairs,
// then width * height * channels sums and width * height counts as u64.
constexpr char kPartialMagic[8] = {'V', 'I', 'S', 'Q', 'O', 'B', 'P', '1'};

struct PartialFile {
  obscurance::ObscurancePartial partial;
  uint32_t total_directions = 0;
};

Status WritePartialFile(const std::string& path, const PartialFile& file) {
  const auto& p = file.partial;
  // Written beside the target and renamed, so that a lost machine leaves no
  // half-written shard that a merge could take for a whole one.
  const std::string staging = path + ".partial-tmp";
  {
    std::ofstream out(staging, std::ios::binary | std::ios::trunc);
    if (!out) return absl::PermissionDeniedError(fmt::format("--partial-out: cannot write {}", staging));
    auto u32 = [&](uint32_t v) { out.write(reinterpret_cast<const char*>(&v), sizeof(v)); };
    out.write(kPartialMagic, sizeof(kPartialMagic));
    out.write(reinterpret_cast<const char*>(&p.fingerprint), sizeof(p.fingerprint));
    u32(p.width);
    u32(p.height);
    u32(p.channels);
    u32(file.total_directions);
    u32(static_cast<uint32_t>(p.ranges.size()));
    for (const auto& r : p.ranges) {
      u32(r.first);
      u32(r.count);
    }
    out.write(reinterpret_cast<const char*>(p.sums.data()), static_cast<std::streamsize>(p.sums.size() * 8));
    out.write(reinterpret_cast<const char*>(p.counts.data()), static_cast<std::streamsize>(p.counts.size() * 8));
    out.flush();
    if (!out) return absl::PermissionDeniedError(fmt::format("--partial-out: cannot write {}", staging));
  }
  std::error_code ec;
  std::filesystem::rename(staging, path, ec);
  if (ec) return absl::PermissionDeniedError(fmt::format("--partial-out: cannot rename to {}: {}", path, ec.message()));
  return absl::OkStatus();
}

// Every size is checked against the file's length before anything is
// allocated: a shard file is input like any other.
StatusOr<PartialFile> ReadPartialFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(fmt::format("{}: cannot read", path));
  std::error_code ec;
  const uint64_t size = std::filesystem::file_size(path, ec);
  auto bad = [&](const std::string& why) {
    return absl::InvalidArgumentError(fmt::format("{}: not a visq obscurance partial ({})", path, why));
  };
  char magic[8] = {};
  in.read(magic, sizeof(magic));
  if (!in || std::memcmp(magic, kPartialMagic, sizeof(magic)) != 0) return bad("no VISQOBP1 magic");
  PartialFile file;
  auto& p = file.partial;
  uint32_t header[5] = {};
  in.read(reinterpret_cast<char*>(&p.fingerprint), sizeof(p.fingerprint));
  in.read(reinterpret_cast<char*>(header), sizeof(header));
  if (!in) return bad("truncated header");
  p.width = header[0];
  p.height = header[1];
  p.channels = header[2];
  file.total_directions = header[3];
  const uint64_t ranges = header[4];
  if (p.channels != 1 && p.channels != 3) return bad(fmt::format("{} channels", p.channels));
  // The server's largest atlas; it also keeps the size arithmetic below
  // far from overflow.
  if (p.width > 8192 || p.height > 8192) return bad(fmt::format("a {} x {} atlas", p.width, p.height));
  const uint64_t texels = uint64_t{p.width} * p.height;
  const uint64_t expected = 8 + 8 + 5 * 4 + ranges * 8 + texels * (p.channels + 1) * 8;
  if (texels == 0 || ranges == 0 || expected != size)
    return bad(fmt::format("{} bytes for a {} x {} atlas with {} range(s)", size, p.width, p.height, ranges));
  p.ranges.resize(ranges);
  for (auto& r : p.ranges) {
    in.read(reinterpret_cast<char*>(&r.first), 4);
    in.read(reinterpret_cast<char*>(&r.count), 4);
    if (uint64_t{r.first} + r.count > file.total_directions)
      return bad(fmt::format("range [{}, {}) beyond {} directions", r.first, uint64_t{r.first} + r.count,
                             file.total_directions));
  }
  p.sums.resize(texels * p.channels);
  p.counts.resize(texels);
  in.read(reinterpret_cast<char*>(p.sums.data()), static_cast<std::streamsize>(p.sums.size() * 8));
  in.read(reinterpret_cast<char*>(p.counts.data()), static_cast<std::streamsize>(p.counts.size() * 8));
  if (!in) return bad("truncated sums");
  return file;
}

// W per texel from the sums, as the server computes it (obscurance_model.cpp,
// FinalizeFromPartial); NaN where no direction reached the texel (the server
// fills those from their neighbours, which needs the scene).
std::vector<float> PartialW(const obscurance::ObscurancePartial& p) {
  std::vector<float> w(p.counts.size() * 3, std::numeric_limits<float>::quiet_NaN());
  for (size_t i = 0; i < p.counts.size(); ++i) {
    if (p.counts[i] == 0) continue;
    const double denom = static_cast<double>(p.counts[i]) * obscurance::kObscuranceFixedPointScale;
    for (uint32_t c = 0; c < 3; ++c)
      w[3 * i + c] = static_cast<float>(static_cast<double>(p.sums[p.channels == 1 ? i : 3 * i + c]) / denom);
  }
  return w;
}

std::string Ranges(const obscurance::ObscurancePartial& p) {
  std::string out;
  for (const auto& r : p.ranges) out += fmt::format("{}[{}, {})", out.empty() ? "" : " ", r.first, r.first + r.count);
  return out;
}

// A shard of a farm bake: --partial-out FILE with --first-direction,
// --directions and --total-directions.
Status RunShard(const BakeOptions& o, const v1::ComputeObscurancesRequest& base, Cli& cli) {
  if (o.target.set() || o.rays > 0)
    return absl::InvalidArgumentError("--partial-out: a shard is a GPU bake of a direction range; not with "
                                      "--max-error, --time-budget-ms or --rays-per-patch");
  if (!o.png.empty() || !o.npy.empty() || !o.exr.empty() || !o.errors_npy.empty())
    return absl::InvalidArgumentError(
        "--partial-out: a shard has no W and no errors; merge the shards (obscurance-merge --npy)");
  v1::ComputeObscurancesRequest request = base;
  request.set_first_direction(o.first_direction);
  request.set_direction_count(o.directions);
  request.set_total_directions(o.total_directions);
  request.set_partial_only(true);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const client::ObscuranceBake bake, client.ComputeObscurances(request));
  PartialFile file{bake.partial, bake.figures.total_directions()};
  VISQ_RETURN_IF_ERROR(WritePartialFile(o.partial_out, file));
  if (cli.flags.json) {
    fmt::print("{{\"partial_out\": \"{}\", \"figures\": {}}}\n", o.partial_out, ToJson(bake.figures));
    return absl::OkStatus();
  }
  fmt::print("directions {} of {} ({}x{} atlas, fingerprint {:016x}): wrote {}\n", Ranges(file.partial),
             file.total_directions, file.partial.width, file.partial.height, file.partial.fingerprint, o.partial_out);
  return absl::OkStatus();
}

Status RunBake(const BakeOptions& o, Cli& cli) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name(o.scene);
  request.set_d_max(o.d_max);
  request.set_resolution(o.resolution);
  if (o.target.set()) {
    o.target.Fill(request.mutable_target());
  } else if (o.rays > 0) {
    request.set_method(o.method == "gpu-raycast" ? v1::ComputeObscurancesRequest::GPU_RAYCAST
                                                 : v1::ComputeObscurancesRequest::RAYCAST);
    request.set_rays_per_patch(o.rays);
  } else if (o.method == "gpu-raycast") {
    return absl::InvalidArgumentError("--method gpu-raycast: give --rays-per-patch, the rays each patch casts");
  } else {
    request.set_direction_count(o.directions);
    if (o.method == "depth-peeling") request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  }
  request.set_seed(o.seed);
  request.set_color_bleeding(o.bleeding);
  request.set_force_built_atlas(o.built_atlas);
  request.set_want_errors(!o.errors_npy.empty());
  if (!o.partial_out.empty()) return RunShard(o, request, cli);
  if (o.first_direction != 0 || o.total_directions != 0)
    return absl::InvalidArgumentError("--first-direction, --total-directions: a direction range is a shard; give "
                                      "--partial-out FILE");
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
  if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, f.atlas().width(), f.atlas().height(), 3, bake->w));
  // Each estimated texel's own bound against the answer's single one.
  std::vector<float> own;
  size_t beyond = 0;
  if (!o.errors_npy.empty()) {
    if (bake->w_error.size() != bake->estimated.size())
      return absl::InternalError(fmt::format("--errors-npy: the server sent {} errors for {} texels",
                                             bake->w_error.size(), bake->estimated.size()));
    VISQ_RETURN_IF_ERROR(WriteNpy(o.errors_npy, {f.atlas().height(), f.atlas().width()}, bake->w_error));
    for (size_t t = 0; t < bake->estimated.size(); ++t)
      if (bake->estimated[t]) {
        own.push_back(bake->w_error[t]);
        beyond += bake->w_error[t] > f.accuracy().error_bound();
      }
    std::sort(own.begin(), own.end());
  }
  auto quantile = [&own](double q) {
    return own.empty() ? 0.0 : own[std::min(own.size() - 1, static_cast<size_t>(q * own.size()))];
  };
  if (cli.flags.json) {
    std::string errors;
    if (!o.errors_npy.empty())
      errors = fmt::format(", \"texel_errors\": {{\"npy\": \"{}\", \"median\": {}, \"p95\": {}, \"max\": {}, "
                           "\"beyond_error_bound\": {}}}",
                           o.errors_npy, quantile(0.5), quantile(0.95), quantile(1.0), beyond);
    fmt::print("{{\"mean_w\": {}, \"estimated_texels\": {}{}, \"figures\": {}}}\n", mean, estimated, errors,
               ToJson(f));
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
  if (!o.errors_npy.empty())
    fmt::print("own texel errors: median +-{:.4f}, p95 +-{:.4f}, max +-{:.4f}; {} of {} estimated texels beyond "
               "+-{:.4f}; wrote {}\n",
               quantile(0.5), quantile(0.95), quantile(1.0), beyond, own.size(), f.accuracy().error_bound(),
               o.errors_npy);
  PrintChosenPlan(f.accuracy());
  PrintTiming(f.timing());
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

struct MergeOptions {
  std::vector<std::string> inputs;
  std::string out, npy;
};

Status RunMerge(const MergeOptions& o, Cli& cli) {
  if (o.out.empty() && o.npy.empty()) return absl::InvalidArgumentError("--out, --npy: give at least one");
  PartialFile merged;
  for (const std::string& input : o.inputs) {
    VISQ_ASSIGN_OR_RETURN(const PartialFile file, ReadPartialFile(input));
    if (!merged.partial.ranges.empty() && file.total_directions != merged.total_directions)
      return absl::InvalidArgumentError(fmt::format("{}: a shard of {} directions, the others of {}", input,
                                                    file.total_directions, merged.total_directions));
    if (const Status s = client::MergeObscurancePartials(merged.partial, file.partial); !s.ok())
      return absl::InvalidArgumentError(fmt::format("{}: {}", input, s.message()));
    merged.total_directions = file.total_directions;
  }
  const auto& p = merged.partial;
  const bool complete = p.ranges.size() == 1 && p.ranges[0].first == 0 && p.ranges[0].count == merged.total_directions;
  if (!o.out.empty()) VISQ_RETURN_IF_ERROR(WritePartialFile(o.out, merged));
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {p.height, p.width, 3}, PartialW(p)));
  size_t estimated = 0;
  for (uint64_t c : p.counts) estimated += c > 0;
  if (cli.flags.json) {
    fmt::print("{{\"directions\": {}, \"total_directions\": {}, \"complete\": {}, \"estimated_texels\": {}}}\n",
               p.DirectionCount(), merged.total_directions, complete, estimated);
    return absl::OkStatus();
  }
  fmt::print("{} shard(s): directions {} of {} ({}), {} estimated texels of {}\n", o.inputs.size(), Ranges(p),
             merged.total_directions, complete ? "complete" : "incomplete", estimated, p.counts.size());
  if (!o.out.empty()) fmt::print("wrote {}\n", o.out);
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
  VISQ_ASSIGN_OR_RETURN(const v1::UpdateObscurancesResponse r, WhileWaiting(cli.flags, "obscurance-update", [&] { return client.UpdateObscurances(request); }));
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
  std::string scene, png, npy, exr, quantity = "w";
  CameraFlags camera;
};

Status RunPreview(const PreviewOptions& o, Cli& cli) {
  if (o.png.empty() && o.npy.empty() && o.exr.empty())
    return absl::InvalidArgumentError("--png, --npy, --exr: give at least one");
  v1::ObscurancePreviewRequest request;
  request.mutable_scene()->set_name(o.scene);
  VISQ_RETURN_IF_ERROR(FillCamera(o.camera, &request));
  const bool intensity = o.quantity != "w" && o.quantity != "W";
  request.set_quantity(intensity ? v1::ObscurancePreviewRequest::INTENSITY : v1::ObscurancePreviewRequest::W);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const client::ObscurancePreview preview, WhileWaiting(cli.flags, "obscurance-preview", [&] { return client.RenderObscurancePreview(request); }));
  const auto& f = preview.figures;
  float peak = 1e-20f;
  for (float v : preview.rgb) peak = std::max(peak, v);
  if (!o.png.empty())
    VISQ_RETURN_IF_ERROR(WriteTopFirstPng(o.png, f.width(), f.height(), preview.rgb, intensity ? 1.0f / peak : 1.0f));
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width(), 3}, preview.rgb));
  if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, f.width(), f.height(), 3, preview.rgb, /*top_first=*/true));
  size_t covered = 0;
  for (uint8_t c : preview.covered) covered += c;
  if (cli.flags.json) {
    fmt::print("{{\"png\": \"{}\", \"covered_pixels\": {}, \"peak\": {}, \"figures\": {}}}\n", o.png, covered, peak,
               ToJson(f));
    return absl::OkStatus();
  }
  fmt::print("{}x{} {} of solution version {}: {} of {} pixels covered, peak {:.4g}\n", f.width(), f.height(),
             intensity ? "I" : "W", f.solution_version(), covered, preview.covered.size(), peak);
  PrintTiming(f.timing());
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

struct ExportOptions {
  std::string scene, gltf, uv_npy;
  bool vertex_colors = false;
};

Status RunExport(const ExportOptions& o, Cli& cli) {
  if (o.gltf.empty() && o.uv_npy.empty()) return absl::InvalidArgumentError("--gltf, --uv-npy: give at least one");
  if (o.vertex_colors && o.gltf.empty()) return absl::InvalidArgumentError("--vertex-colors: colours the --gltf file");
  v1::ExportObscurancesRequest request;
  request.mutable_scene()->set_name(o.scene);
  request.set_want_atlas_uvs(!o.uv_npy.empty());
  request.set_want_gltf(!o.gltf.empty());
  request.set_want_vertex_colors(o.vertex_colors);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const client::ObscuranceExport exported,
                        WhileWaiting(cli.flags, "obscurance-export", [&] { return client.ExportObscurances(request); }));
  const auto& f = exported.figures;
  if (!o.gltf.empty()) {
    std::ofstream out(o.gltf, std::ios::binary);
    out.write(reinterpret_cast<const char*>(exported.glb.data()), static_cast<std::streamsize>(exported.glb.size()));
    if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", o.gltf));
  }
  if (!o.uv_npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.uv_npy, {f.triangles(), 3, 2}, exported.atlas_uv));
  if (cli.flags.json) {
    fmt::print("{{\"gltf\": \"{}\", \"uv_npy\": \"{}\", \"figures\": {}}}\n", o.gltf, o.uv_npy, ToJson(f));
    return absl::OkStatus();
  }
  fmt::print("solution version {}: {}x{} atlas ({}), {} triangles, {} glTF bytes\n", f.solution_version(), f.width(),
             f.height(), f.from_lightmap_uvs() ? "the scene's TEXCOORD_1" : "built by the server", f.triangles(),
             exported.glb.size());
  PrintTiming(f.timing());
  PrintWritten(o.gltf, o.uv_npy, "");
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
  obscurance->add_option("--exr", ob->exr, "Write the W atlas as a float OpenEXR image (as the PNG)");
  obscurance->add_option("--errors-npy", ob->errors_npy,
                         "Also get each texel's own error bound (want_errors: its half-width at the answer's "
                         "confidence; 1 for texels filled from neighbours) and write it as a float32 .npy (atlas "
                         "height, width); prints their spread and how many exceed the single bound");
  AddTargetFlags(obscurance, ob->target);
  AddChoice(obscurance, "--method", ob->method, {"auto", "depth-peeling", "gpu-raycast"},
            "auto (the server runs the fastest here of the depth peeling with --directions directions and the "
            "ray-cast estimator with as many rays per patch on Embree or on the GPU, at the same bound), "
            "depth-peeling (the paper's GPU bake) or gpu-raycast (with --rays-per-patch: the ray-cast estimator's "
            "rays traced on the GPU); --rays-per-patch alone names the ray-cast estimator on Embree");
  obscurance->add_option("--rays-per-patch", ob->rays,
                         "Instead of the GPU bake: the ray-cast estimator (Embree) with this many rays per patch");
  obscurance->add_option("--partial-out", ob->partial_out,
                         "Bake a shard of a farm bake: directions [--first-direction, + --directions) of "
                         "--total-directions, written as partial sums to this file (obscurance-merge joins them)");
  obscurance->add_option("--first-direction", ob->first_direction, "With --partial-out: the shard's first direction");
  obscurance->add_option("--total-directions", ob->total_directions,
                         "With --partial-out: the whole bake's directions (default: the shard's end)");
  OnRun(obscurance, cli, ob, RunBake);

  auto merge = std::make_shared<MergeOptions>();
  auto* merge_command = cli.app.add_subcommand(
      "obscurance-merge", "Merge farm-bake shards (obscurance --partial-out): equal, bit for bit, to one bake");
  merge_command->add_option("SHARD", merge->inputs, "Shard files")->required()->check(CLI::ExistingFile);
  merge_command->add_option("--out", merge->out, "Write the merged partial sums (a shard of the merged ranges)");
  merge_command->add_option("--npy", merge->npy,
                            "Write W as a float32 .npy (atlas height, width, 3): the server's W on every texel a "
                            "direction reached, NaN on the others (the server fills those from their neighbours)");
  OnRun(merge_command, cli, merge, RunMerge);

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
  preview->add_option("--exr", op->exr, "Write the linear RGB image as a float OpenEXR image");
  preview->add_option("--npy", op->npy, "Write the linear RGB image as a float32 .npy (height, width, 3), row 0 on top");
  OnRun(preview, cli, op, RunPreview);

  auto oe = std::make_shared<ExportOptions>();
  auto* exporter = cli.app.add_subcommand(
      "obscurance-export", "Write the current obscurance solution so that a game mesh can take it: the atlas UVs, "
                           "and the scene as glTF with the atlas UVs and W as its occlusion texture");
  exporter->add_option("SCENE,--scene", oe->scene, "Scene name")->required();
  exporter->add_option("--gltf", oe->gltf,
                       "Write the baked scene as binary glTF (.glb): the scene's nodes, materials, normals and UV "
                       "sets, indexed, the atlas UVs as the UV set after the scene's own (or its TEXCOORD_1 when "
                       "the bake used it), W as an 8-bit PNG occlusionTexture read through it");
  exporter->add_flag("--vertex-colors", oe->vertex_colors,
                     "Also write W per vertex (area-weighted over its triangles) as COLOR_0 in the --gltf file, "
                     "which DCC viewports show where they ignore glTF's occlusionTexture");
  exporter->add_option("--uv-npy", oe->uv_npy,
                       "Write the atlas UVs as a float32 .npy (triangles, 3, 2) in the scene's triangle order, "
                       "the order of the bake's triangle_w");
  OnRun(exporter, cli, oe, RunExport);
}

}  // namespace visq::cli
