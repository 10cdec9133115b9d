// visq voxelize, transmittance, volumetric: the slicemap RPCs and the
// volumetric shadows drawn on the same kind of map.
#include <algorithm>
#include <bit>
#include <cmath>

#include <fmt/format.h>

#include "cli_common.h"

namespace visq::cli {
namespace {

struct VoxelizeOptions {
  std::string scene, png, npy, exr;
  uint32_t width = 128, height = 128, slices = 128, axis = 1;
  bool solid = false, local = false, conservative = false;
};

// Occupied voxels per column, [y][x] (y along the box's axis_v).
std::vector<float> ColumnCounts(const client::VoxelGrid& grid) {
  const auto& f = grid.figures;
  std::vector<float> counts(size_t(f.width()) * f.height());
  for (size_t column = 0; column < counts.size(); ++column) {
    uint32_t count = 0;
    for (uint32_t w = 0; w < f.words_per_column(); ++w)
      count += static_cast<uint32_t>(std::popcount(grid.bits[column * f.words_per_column() + w]));
    counts[column] = static_cast<float>(count);
  }
  return counts;
}

// The projection as a picture with square pixels: texels are as wide as the
// box's extent over their count along each axis, which differ for a box that
// is not square or a grid that is not. Each pixel is as large as the coarser
// texel side, so no axis is upsampled, and averages the texels it covers.
Status WriteProjectionPng(const std::string& path, const client::VoxelGrid& grid, const std::vector<float>& counts) {
  const auto& f = grid.figures;
  const double extent_u = 2.0 * f.box().half_extent().x(), extent_v = 2.0 * f.box().half_extent().y();
  const double texel_u = extent_u / f.width(), texel_v = extent_v / f.height();
  const double pixel = std::max(texel_u, texel_v);
  uint32_t width = f.width(), height = f.height();
  if (pixel > 0 && std::isfinite(pixel)) {
    width = std::clamp<uint32_t>(static_cast<uint32_t>(std::lround(extent_u / pixel)), 1, f.width());
    height = std::clamp<uint32_t>(static_cast<uint32_t>(std::lround(extent_v / pixel)), 1, f.height());
  }
  const float peak = std::max(1.0f, *std::max_element(counts.begin(), counts.end()));
  std::vector<float> image(size_t(width) * height);
  for (uint32_t y = 0; y < height; ++y)
    for (uint32_t x = 0; x < width; ++x) {
      const uint32_t x0 = x * f.width() / width, x1 = std::max(x0 + 1, (x + 1) * f.width() / width);
      const uint32_t y0 = y * f.height() / height, y1 = std::max(y0 + 1, (y + 1) * f.height() / height);
      double sum = 0;
      for (uint32_t ty = y0; ty < y1; ++ty)
        for (uint32_t tx = x0; tx < x1; ++tx) sum += counts[size_t(ty) * f.width() + tx];
      image[size_t(y) * width + x] = static_cast<float>(sum / (double(x1 - x0) * (y1 - y0)) / peak);
    }
  return WritePng(path, width, height, 1, image);
}

Status RunVoxelize(const VoxelizeOptions& o, Cli& cli) {
  v1::VoxelizeRequest request;
  request.mutable_scene()->set_name(o.scene);
  request.set_width(o.width);
  request.set_height(o.height);
  request.set_slices(o.slices);
  request.set_depth_axis(o.axis);
  request.set_mode(o.solid ? v1::VoxelizeRequest::SOLID : v1::VoxelizeRequest::SURFACE);
  request.set_local_precision(o.local);
  request.set_conservative(o.conservative);
  auto client = MakeClient(cli.flags);
  // The bands of image rows the grid streams as they are made are its progress.
  StatusOr<client::VoxelGrid> answer;
  {
    Waiting waiting(cli.flags, "voxelize");
    answer = client.Voxelize(request, waiting.Callback("rows"));
  }
  VISQ_ASSIGN_OR_RETURN(const client::VoxelGrid grid, std::move(answer));
  const auto& f = grid.figures;
  if (!o.png.empty() || !o.npy.empty() || !o.exr.empty()) {
    const std::vector<float> counts = ColumnCounts(grid);
    if (!o.png.empty()) VISQ_RETURN_IF_ERROR(WriteProjectionPng(o.png, grid, counts));
    if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width()}, counts));
    if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, f.width(), f.height(), 1, counts));
  }
  if (cli.flags.json) {
    fmt::print("{}", ToJson(f));
    return absl::OkStatus();
  }
  fmt::print("{}x{}x{} ({}, {}): {} occupied voxels, {} ambiguous columns, {} pass(es)\n", f.width(), f.height(),
             f.slices(), f.rasterization(), f.precision(), f.occupied_voxels(), f.ambiguous_columns(), f.passes());
  fmt::print("accuracy: {}\ntime: total {:.1f} ms (compute {:.1f} ms)\n", f.accuracy().note(), f.timing().total_ms(),
             f.timing().compute_ms());
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

struct TransmittanceOptions {
  std::string scene, light, kind = "directional", receiver, png, npy, exr, method = "auto";
  std::vector<std::string> absorbers;
  uint32_t width = 64, height = 64, resolution = 256, slices = 256;
};

Status RunTransmittance(const TransmittanceOptions& o, Cli& cli) {
  v1::TransmittanceRequest request;
  request.mutable_scene()->set_name(o.scene);
  const bool point = o.kind == "point";
  request.set_light_kind(point ? v1::TransmittanceRequest::POINT : v1::TransmittanceRequest::DIRECTIONAL);
  if (!ParseVec3(o.light, point ? request.mutable_light_position() : request.mutable_light_direction()))
    return absl::InvalidArgumentError("--light: expected 'x,y,z'");
  if (!ParsePatch(o.receiver, request.mutable_receiver()))
    return absl::InvalidArgumentError("--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'");
  for (const auto& a : o.absorbers) {
    const size_t eq = a.rfind('=');
    auto* absorber = request.add_absorbers();
    absorber->set_node(a.substr(0, eq));
    double sigma = 1.0;
    if (eq != std::string::npos) {
      char* end = nullptr;
      sigma = std::strtod(a.c_str() + eq + 1, &end);
      if (end == a.c_str() + eq + 1 || *end != '\0' || !std::isfinite(sigma))
        return absl::InvalidArgumentError(fmt::format("--absorber: '{}': expected NODE=SIGMA", a));
    }
    absorber->set_absorption(sigma);
  }
  request.set_receiver_width(o.width);
  request.set_receiver_height(o.height);
  request.set_resolution(o.resolution);
  request.set_slices(o.slices);
  // "auto" leaves it unset: the server runs the faster here.
  if (o.method == "ray-stabbing") request.set_method(v1::TransmittanceRequest::RAY_STABBING);
  if (o.method == "slicemap") request.set_method(v1::TransmittanceRequest::SLICEMAP);
  auto client = MakeClient(cli.flags);
  VISQ_ASSIGN_OR_RETURN(const v1::TransmittanceResponse response, WhileWaiting(cli.flags, "transmittance", [&] { return client.Transmittance(request); }));
  const std::vector<float> image(response.transmittance().begin(), response.transmittance().end());
  if (!o.png.empty()) VISQ_RETURN_IF_ERROR(WritePng(o.png, o.width, o.height, 1, image));
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {o.height, o.width}, image));
  if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, o.width, o.height, 1, image));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(response));
    return absl::OkStatus();
  }
  double mean = 0;
  for (float t : image) mean += t;
  mean /= std::max<size_t>(1, image.size());
  fmt::print("{} texels: mean transmittance {:.4f}; {}\n", image.size(), mean, response.accuracy().note());
  fmt::print("time: total {:.1f} ms\n", response.timing().total_ms());
  if (!o.exr.empty()) fmt::print("wrote {}\n", o.exr);
  return absl::OkStatus();
}

struct VolumetricOptions {
  std::string scene, light = "0.3,-1,0.2", png, npy, exr, method = "min-max", medium_box;
  CameraFlags camera;
  uint32_t shadow_map = 1024;
  double scattering = 0.05, extinction = 0.05, intensity = 1.0;
  bool combined = false, estimate_error = false;
  TargetFlags target;
};

Status RunVolumetric(const VolumetricOptions& o, Cli& cli) {
  v1::VolumetricShadowRequest request;
  request.mutable_scene()->set_name(o.scene);
  VISQ_RETURN_IF_ERROR(FillCamera(o.camera, &request));
  if (!ParseVec3(o.light, request.mutable_light_direction()))
    return absl::InvalidArgumentError("--sun: expected 'x,y,z'");
  if (o.target.set()) o.target.Fill(request.mutable_target());
  else request.set_shadow_map_size(o.shadow_map);
  request.set_estimate_error(o.estimate_error);
  request.set_scattering(o.scattering);
  request.set_extinction(o.extinction);
  request.set_light_intensity(o.intensity);
  request.set_method(o.method == "ray-marching" ? v1::VolumetricShadowRequest::RAY_MARCHING
                                                : v1::VolumetricShadowRequest::MIN_MAX);
  request.set_combined_image(o.combined);
  if (!o.medium_box.empty()) {
    const size_t split = o.medium_box.find(';');
    if (split == std::string::npos ||
        !ParseVec3(o.medium_box.substr(0, split), request.mutable_medium_box()->mutable_min()) ||
        !ParseVec3(o.medium_box.substr(split + 1), request.mutable_medium_box()->mutable_max()))
      return absl::InvalidArgumentError("--medium-box: expected 'minx,miny,minz;maxx,maxy,maxz'");
  }
  auto client = MakeClient(cli.flags);
  StatusOr<client::VolumetricImage> answer;
  {
    Waiting waiting(cli.flags, "volumetric");
    answer = client.VolumetricShadow(request, waiting.Callback("rows"));
  }
  VISQ_ASSIGN_OR_RETURN(const client::VolumetricImage image, std::move(answer));
  const auto& f = image.figures;
  const std::vector<float>& rgb = o.combined ? image.combined : image.inscattering;
  if (!o.png.empty()) {
    float peak = 1e-20f;
    for (float v : rgb) peak = std::max(peak, v);
    VISQ_RETURN_IF_ERROR(WriteTopFirstPng(o.png, f.width(), f.height(), rgb, 1.0f / peak));
  }
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {f.height(), f.width(), 3}, rgb));
  if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, f.width(), f.height(), 3, rgb, /*top_first=*/true));
  if (cli.flags.json) {
    fmt::print("{}", ToJson(f));
    return absl::OkStatus();
  }
  fmt::print("{}x{} {} ({} integrand, {}x{} rectified)\n", f.width(), f.height(), f.method(), f.integrand(),
             f.rectified_rows(), f.rectified_columns());
  for (const auto& [stage, ms] : f.stage_ms()) fmt::print("  {:<14} {:8.1f} ms\n", stage, ms);
  if (f.accuracy().error_bound() >= 0)
    fmt::print("error, estimated: {:.4g} per pixel at most ({} shadow map); {}\n", f.accuracy().error_bound(),
               f.accuracy().parameters().count("shadow_map_size") ? f.accuracy().parameters().at("shadow_map_size") : 0.0,
               f.accuracy().note());
  fmt::print("total {:.1f} ms\n", f.timing().total_ms());
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

}  // namespace

void AddVoxelCommands(Cli& cli) {
  auto vx = std::make_shared<VoxelizeOptions>();
  auto* voxelize = cli.app.add_subcommand("voxelize", "Slicemap voxelization of a scene (bits per voxel)");
  voxelize->add_option("--scene", vx->scene, "Scene name")->required();
  voxelize->add_option("--width", vx->width, "Texels along the box's first axis")->capture_default_str();
  voxelize->add_option("--height", vx->height, "Texels along the box's second axis")->capture_default_str();
  voxelize->add_option("--slices", vx->slices, "Slices along the depth axis")->capture_default_str();
  voxelize->add_option("--axis", vx->axis, "Depth axis: 0 = x, 1 = y, 2 = z")
      ->check(CLI::Range(0, 2))
      ->capture_default_str();
  voxelize->add_flag("--solid", vx->solid, "Solid voxelization (inside of closed meshes)");
  voxelize->add_flag("--local", vx->local, "Local precision: slices between each column's near and far geometry");
  voxelize->add_flag("--conservative", vx->conservative, "Never miss a triangle, even edge-on");
  voxelize->add_option("--png", vx->png,
                       "Write the projection along the depth axis: gray = occupied voxels in the column over the "
                       "fullest column's (white); square pixels, so the box's aspect ratio is kept");
  voxelize->add_option("--npy", vx->npy, "Write the occupied voxels per column as a float32 .npy (height, width)");
  voxelize->add_option("--exr", vx->exr, "Write the occupied voxels per column as a float OpenEXR image, a pixel per column");
  OnRun(voxelize, cli, vx, RunVoxelize);

  auto tr = std::make_shared<TransmittanceOptions>();
  auto* transmittance = cli.app.add_subcommand("transmittance", "Light reaching a receiver through absorbing nodes");
  transmittance->add_option("--scene", tr->scene, "Scene name")->required();
  transmittance->add_option("--light", tr->light, "Light direction (directional) or position (point) 'x,y,z'")
      ->required();
  AddChoice(transmittance, "--light-kind", tr->kind, {"directional", "point"}, "directional or point");
  transmittance->add_option("--absorber", tr->absorbers, "NODE=SIGMA (repeatable)")->required();
  transmittance->add_option("--receiver", tr->receiver, "Receiver patch 'ox,oy,oz;ux,uy,uz;vx,vy,vz'")->required();
  transmittance->add_option("--width", tr->width, "Receiver texels across")->capture_default_str();
  transmittance->add_option("--height", tr->height, "Receiver texels down")->capture_default_str();
  transmittance->add_option("--resolution", tr->resolution, "Light-view resolution")->capture_default_str();
  transmittance->add_option("--slices", tr->slices, "Slices")->capture_default_str();
  AddChoice(transmittance, "--method", tr->method, {"auto", "slicemap", "ray-stabbing"},
            "auto (the server runs the faster here), slicemap (the paper's, on the GPU: each texel's centre ray) or "
            "ray-stabbing (each texel's own ray, Embree on the CPU)");
  transmittance->add_option("--png", tr->png, "Write the transmittance as a PNG");
  transmittance->add_option("--npy", tr->npy, "Write the transmittance as a float32 .npy (height, width)");
  transmittance->add_option("--exr", tr->exr, "Write the transmittance as a float OpenEXR image (as the PNG)");
  OnRun(transmittance, cli, tr, RunTransmittance);

  auto vo = std::make_shared<VolumetricOptions>();
  auto* volumetric = cli.app.add_subcommand("volumetric", "Volumetric shadows (light shafts) from a camera");
  volumetric->add_option("--scene", vo->scene, "Scene name")->required();
  AddCameraFlags(volumetric, vo->camera);
  volumetric->add_option("--sun", vo->light, "Direction the sunlight travels 'x,y,z'")->capture_default_str();
  volumetric->add_option("--shadow-map", vo->shadow_map, "Shadow map size (power of two)")->capture_default_str();
  volumetric->add_option("--scattering", vo->scattering, "sigma_s per world unit")->capture_default_str();
  volumetric->add_option("--extinction", vo->extinction, "sigma_t per world unit")->capture_default_str();
  volumetric->add_option("--intensity", vo->intensity, "Light intensity")->capture_default_str();
  AddChoice(volumetric, "--method", vo->method, {"min-max", "ray-marching"}, "min-max or ray-marching");
  volumetric->add_flag("--combined", vo->combined, "Add the directly lit surfaces");
  volumetric->add_flag("--estimate-error", vo->estimate_error,
                       "Also render with a half and a quarter of the shadow map and state the error estimate "
                       "(Richardson's, from how fast the images converge)");
  AddTargetFlags(volumetric, vo->target);
  volumetric->add_option("--medium-box", vo->medium_box,
                         "Where the medium is, 'minx,miny,minz;maxx,maxy,maxz' (default: the scene's bounds)");
  volumetric->add_option("--png", vo->png, "Write the image (tone-mapped to its peak)");
  volumetric->add_option("--exr", vo->exr, "Write the linear RGB image as a float OpenEXR image");
  volumetric->add_option("--npy", vo->npy, "Write the linear RGB image as a float32 .npy (height, width, 3), row 0 on top");
  OnRun(volumetric, cli, vo, RunVolumetric);
}

}  // namespace visq::cli
