// Slicemap voxelization (gpu/slicemap) vs the CPU reference voxelizer
// (lib/voxel_reference) on Sponza and the veach-ajar interior. Prints a
// table; not a test. Usage:
//   visq_bench_slicemap [shared-scenes-dir] [repeats] [number of grid sizes, 1..3]
// GPU figures are the median of `repeats` runs after one warm-up (which
// builds the shader programs); the CPU reference runs once per size.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>
#include <bit>

#include "scene/gltf_loader.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/slicemap.h"
#include "voxel_reference/voxel_reference.h"

namespace {

using namespace visq;

struct Size {
  uint32_t w, h, s;
};

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  std::filesystem::path scenes = argc > 1 ? argv[1] : "../shared/scenes";
  const int repeats = argc > 2 ? std::max(1, std::atoi(argv[2])) : 5;
  auto worker_or = gpu::GpuWorker::Start({});
  if (!worker_or.ok()) {
    std::fprintf(stderr, "no GL context: %s\n", std::string(worker_or.status().message()).c_str());
    return 1;
  }
  gpu::GpuWorker& worker = **worker_or;
  std::printf("device: %s (%s)\n", worker.device().gl_renderer.c_str(), worker.device().gl_version.c_str());
  std::printf("GPU: median of %d runs (total = queue + setup + passes + readback [+ resolve]); CPU reference: exact "
              "triangle-box voxelization, %u threads, one run\n\n",
              repeats, std::max(1u, std::thread::hardware_concurrency()));
  std::printf("%-12s %-16s %-13s %9s %9s %9s %9s %9s %11s %11s %9s %12s %8s\n", "scene", "grid", "mode", "total_ms",
              "setup_ms", "depth_ms", "pass_ms", "read_ms", "occupied", "cpu_ref_ms", "ref_occ", "cpu/gpu", "missing");

  const std::vector<std::pair<std::string, std::filesystem::path>> inputs = {
      {"sponza", scenes / "sponza_dabrovic" / "sponza.gltf"},
      {"veach_ajar", scenes / "interior_veach_ajar" / "veach_ajar.gltf"}};
  std::vector<Size> sizes = {{512, 512, 128}, {1024, 1024, 128}, {1024, 1024, 1024}};
  if (argc > 3) sizes.resize(std::clamp<size_t>(std::atoi(argv[3]), 1, sizes.size()));
  for (const auto& [name, path] : inputs) {
    auto scene = LoadGltfFile(path);
    if (!scene.ok()) {
      std::printf("%-12s skipped: %s\n", name.c_str(), std::string(scene.status().message()).c_str());
      continue;
    }
    auto gpu_scene = gpu::GpuScene::Upload(worker, *scene);
    if (!gpu_scene.ok()) {
      std::printf("%-12s upload failed: %s\n", name.c_str(), std::string(gpu_scene.status().message()).c_str());
      continue;
    }
    std::printf("%s: %zu triangles, depth along y (up)\n", name.c_str(), scene->TriangleCount());
    for (const Size& size : sizes) {
      gpu::VoxelizeParams params;
      params.box = gpu::AxisAlignedSlicemapBox(scene->bounds, 1, 1e-3 * glm::length(scene->bounds.Extent()));
      params.width = size.w;
      params.height = size.h;
      params.slices = size.s;
      params.max_bytes = uint64_t{4} << 30;
      const voxel_reference::GridBox box{params.box, size.w, size.h, size.s};
      // The CPU reference once per grid (it does not depend on the GPU mode).
      voxel_reference::SurfaceStats stats;
      auto reference = voxel_reference::VoxelizeSurface(*scene, box, {}, &stats);
      const char* grid_name_fmt = "%ux%ux%u";
      char grid_name[64];
      std::snprintf(grid_name, sizeof grid_name, grid_name_fmt, size.w, size.h, size.s);
      struct Mode {
        const char* label;
        gpu::VoxelizeMode mode;
        gpu::SlicePrecision precision;
        gpu::Rasterization raster;
      };
      const Mode modes[] = {
          {"surface", gpu::VoxelizeMode::kSurface, gpu::SlicePrecision::kUniform, gpu::Rasterization::kStandard},
          {"surf+local", gpu::VoxelizeMode::kSurface, gpu::SlicePrecision::kLocal, gpu::Rasterization::kStandard},
          {"conservative", gpu::VoxelizeMode::kSurface, gpu::SlicePrecision::kUniform,
           gpu::Rasterization::kConservative},
          {"solid", gpu::VoxelizeMode::kSolid, gpu::SlicePrecision::kUniform, gpu::Rasterization::kStandard},
      };
      for (const Mode& mode : modes) {
        params.mode = mode.mode;
        params.precision = mode.precision;
        params.rasterization = mode.raster;
        std::vector<double> total, setup, depth, pass, read;
        gpu::VoxelizeResult last;
        bool failed = false;
        for (int r = 0; r <= repeats; ++r) {
          auto result = gpu::Voxelize(worker, **gpu_scene, params);
          if (!result.ok()) {
            std::printf("%-12s %-16s %-13s failed: %s\n", name.c_str(), grid_name, mode.label,
                        std::string(result.status().message()).c_str());
            failed = true;
            break;
          }
          if (r == 0) continue;  // warm-up: program builds
          total.push_back(result->timings.total_ms);
          setup.push_back(result->timings.setup_ms + result->timings.queue_ms);
          depth.push_back(result->timings.depth_ms);
          pass.push_back(result->timings.voxelize_ms);
          read.push_back(result->timings.readback_ms + result->timings.resolve_ms);
          last = std::move(*result);
        }
        if (failed) continue;
        // Conservative must contain the reference: report voxels it misses.
        std::string missing = "-";
        if (reference.ok() && mode.raster == gpu::Rasterization::kConservative) {
          uint64_t n = 0;
          for (size_t i = 0; i < last.grid.bits.size(); ++i)
            n += std::popcount(reference->bits[i] & ~last.grid.bits[i]);
          missing = std::to_string(n);
        }
        const double gpu_ms = Median(total);
        std::printf("%-12s %-16s %-13s %9.1f %9.1f %9.1f %9.1f %9.1f %11llu %11.1f %9llu %11.1fx %8s\n", name.c_str(),
                    grid_name, mode.label, gpu_ms, Median(setup), Median(depth), Median(pass), Median(read),
                    (unsigned long long)last.occupied_voxels, stats.milliseconds,
                    reference.ok() ? (unsigned long long)reference->CountOccupied() : 0ull,
                    stats.milliseconds / gpu_ms, missing.c_str());
      }
    }
  }
  std::printf("\nGoal: Sponza 512x512x128 (surface) under 50 ms on llvmpipe.\n");
  return 0;
}
