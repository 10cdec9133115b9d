// Obscurance bake: GPU depth peeling vs Embree casting cosine-distributed
// rays from every patch, with the same number of samples per patch and
// again with the ray count that gives the bake's error (a bundle's samples
// of one patch share one direction, so they are worth far fewer than as
// many rays), time and RMS error against a converged Embree reference; and
// the update latency for moving a ~1K-triangle object in Sponza. Prints a
// table; not a test.
//
//   visq_bench_obscurance [--quick] [--update-only [--update-rays N] [--moves N] [--plain-only|--fast-only]] [--scene NAME] [--atlas N] [--directions N]
//                         [--bundle N] [--scenes DIR]
//   visq_bench_obscurance --step-cost [--scene NAME] [--atlas N] [--directions N] [--scenes DIR]
//   visq_bench_obscurance --coverage [--scene bunny|palm|cornell|sponza] [--atlas N] [--reference-rays N]
//                         [--directions-list N,N,...] [--bundles N,N,...] [--scenes DIR]
// --quick: Sponza only, 512^2, 16/64 directions, a 256-ray reference.
// --update-only: only the Sponza update latency, on the plain path and the
// fast one (bit-for-bit comparison and ratios); --update-rays N: only N rays
// per patch (default 16 and 64); --moves N: N moves (default 5; out and back
// in steps of 0.2 d_max); --plain-only / --fast-only: one path (to profile).
// --scene sponza|veach_ajar, --atlas N, --directions N: only this scene,
// atlas resolution, direction count.
// --bundle N: pixels across each direction's bundle (default: 2 x atlas).
// --coverage: W per texel, per triangle and per vertex of a bake of a scene
// whose triangles are smaller than its texels (the Stanford bunny at atlas
// 256 by default), against Embree references per texel (rays from the
// patch) and per triangle (rays from the triangle), for each direction count
// and bundle resolution: RMS error, and the share of elements within the
// bound stated for them, for the triangle W taken from the triangle's own
// samples (the bake's) and from its texels' mean (what the bake gave before).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <glm/gtc/matrix_transform.hpp>

#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "obscurance/obscurance_rays.h"
#include "obscurance/obscurance_update.h"
#include "scene/gltf_loader.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/obscurance.h"

using namespace visq;
using namespace visq::obscurance;

namespace {

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

double Rms(const ObscuranceAtlas& atlas, const ObscuranceResult& x, const ObscuranceResult& y) {
  double s = 0;
  size_t n = 0;
  for (uint32_t t = 0; t < atlas.texel_count(); ++t) {
    if (!atlas.Covered(t) || !x.estimated[t] || !y.estimated[t]) continue;
    for (int c = 0; c < 3; ++c) {
      const double d = static_cast<double>(x.w[t][c]) - y.w[t][c];
      s += d * d;
      ++n;
    }
  }
  return n ? std::sqrt(s / n) : 0;
}

std::vector<uint32_t> ParseList(const char* text) {
  std::vector<uint32_t> out;
  for (const char* p = text; *p;) {
    out.push_back(static_cast<uint32_t>(std::strtoul(p, nullptr, 10)));
    while (*p && *p != ',') ++p;
    if (*p == ',') ++p;
  }
  return out;
}

// Errors of one kind of element against its reference: RMS, the RMS with
// the reference's own noise taken out (reference_variance per element), and
// the shares within `stated` (one figure for all) and within each element's
// own bound.
struct ErrorFigures {
  double rms = 0, rms_less_reference = 0, within_stated = 0, within_own = 0, median_own = 0;
  size_t elements = 0;
};

ErrorFigures Compare(const std::vector<glm::vec3>& estimate, const std::vector<glm::vec3>& reference,
                     const std::vector<uint8_t>& use, double reference_variance, double stated,
                     const std::vector<float>* own_bound) {
  ErrorFigures f;
  double s2 = 0;
  size_t within_stated = 0, within_own = 0;
  std::vector<float> bounds;
  for (size_t i = 0; i < estimate.size(); ++i) {
    if (!use[i]) continue;
    const double e = std::abs(static_cast<double>(estimate[i].x) - reference[i].x);
    s2 += e * e;
    ++f.elements;
    within_stated += e <= stated;
    if (own_bound) {
      within_own += e <= (*own_bound)[i];
      bounds.push_back((*own_bound)[i]);
    }
  }
  if (f.elements == 0) return f;
  f.rms = std::sqrt(s2 / f.elements);
  f.rms_less_reference = std::sqrt(std::max(0.0, s2 / f.elements - reference_variance));
  f.within_stated = static_cast<double>(within_stated) / f.elements;
  f.within_own = own_bound ? static_cast<double>(within_own) / f.elements : std::nan("");
  if (!bounds.empty()) {
    std::nth_element(bounds.begin(), bounds.begin() + bounds.size() / 2, bounds.end());
    f.median_own = bounds[bounds.size() / 2];
  }
  return f;
}

// Two references of N/2 rays each: their mean is the reference, and per
// element (a - b)^2 / 4 estimates its variance, whose mean is returned.
double MeanOfTwo(const std::vector<glm::vec3>& a, const std::vector<glm::vec3>& b, const std::vector<uint8_t>& use,
                 std::vector<glm::vec3>& mean) {
  mean.resize(a.size());
  double v = 0;
  size_t n = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    mean[i] = 0.5f * (a[i] + b[i]);
    if (!use[i]) continue;
    const double d = static_cast<double>(a[i].x) - b[i].x;
    v += d * d / 4;
    ++n;
  }
  return n ? v / n : 0;
}

int RunCoverage(gpu::GpuWorker& worker, const std::filesystem::path& dir, const std::string& scene_name,
                uint32_t atlas_resolution, uint32_t reference_rays, std::vector<uint32_t> directions,
                std::vector<uint32_t> bundles) {
  const std::filesystem::path path = scene_name == "palm"      ? dir / "tree_kenney/tree_palmDetailedTall.glb"
                                     : scene_name == "cornell" ? dir / "cornell_box/cornell_box.gltf"
                                     : scene_name == "sponza"  ? dir / "sponza_dabrovic/sponza.gltf"
                                                               : dir / "bunny/bunny.gltf";
  auto scene = LoadGltfFile(path);
  if (!scene.ok()) { std::printf("%s: %s\n", path.c_str(), std::string(scene.status().message()).c_str()); return 1; }
  auto gpu_scene = gpu::GpuScene::Upload(worker, *scene);
  if (!gpu_scene.ok()) return 1;
  auto atlas = BuildObscuranceAtlas(*scene, atlas_resolution);
  if (!atlas.ok()) { std::printf("atlas: %s\n", std::string(atlas.status().message()).c_str()); return 1; }
  ObscuranceParams params;
  params.d_max = 0.2 * glm::length(scene->bounds.Extent());
  const double confidence = 0.95;
  // How much finer than the atlas the mesh is: triangles per covered texel.
  size_t covered = 0;
  for (uint32_t t = 0; t < atlas->texel_count(); ++t) covered += atlas->Covered(t);
  std::printf("coverage: %s, %zu triangles, extent %.3f, atlas %u (%zu texels with surface, %.2f triangles per texel), "
              "d_max %.4f, W gray (no bleeding), confidence %.2f\n",
              scene_name.c_str(), scene->TriangleCount(), glm::length(scene->bounds.Extent()), atlas_resolution, covered,
              static_cast<double>(scene->TriangleCount()) / covered, params.d_max, confidence);
  auto t0 = std::chrono::steady_clock::now();
  RayEstimateOptions ref_options;
  ref_options.rays_per_patch = std::max<uint32_t>(1, reference_rays / 2);
  ref_options.seed = 999;
  auto texel_a = EstimateObscurancesByRays(*scene, *atlas, params, ref_options);
  auto triangle_a = EstimateTriangleObscuranceByRays(*scene, params, ref_options);
  ref_options.seed = 1999;
  auto texel_b = EstimateObscurancesByRays(*scene, *atlas, params, ref_options);
  auto triangle_b = EstimateTriangleObscuranceByRays(*scene, params, ref_options);
  if (!texel_a.ok() || !triangle_a.ok() || !texel_b.ok() || !triangle_b.ok()) return 1;
  std::printf("references: two of %u rays per texel and per triangle, %.1f s\n", ref_options.rays_per_patch,
              Seconds(t0));
  std::vector<uint8_t> triangle_use(scene->TriangleCount(), 0), vertex_use(scene->positions.size(), 0);
  std::vector<double> varea(scene->positions.size(), 0.0);
  std::vector<glm::dvec3> vsum(scene->positions.size(), glm::dvec3(0.0));
  for (uint32_t t = 0; t < scene->TriangleCount(); ++t) {
    const double a = 0.5 * glm::length(glm::cross(scene->Vertex(t, 1) - scene->Vertex(t, 0),
                                                  scene->Vertex(t, 2) - scene->Vertex(t, 0)));
    if (!(a > 0)) continue;
    triangle_use[t] = 1;
    for (int c = 0; c < 3; ++c) {
      varea[scene->triangles[t][c]] += a;
      vertex_use[scene->triangles[t][c]] = 1;
    }
  }
  std::vector<uint8_t> texel_use(atlas->texel_count(), 0);
  for (uint32_t t = 0; t < atlas->texel_count(); ++t) texel_use[t] = texel_a->estimated[t];
  std::vector<glm::vec3> texel_reference_w, triangle_reference;
  const double texel_ref_var = MeanOfTwo(texel_a->w, texel_b->w, texel_use, texel_reference_w);
  const double triangle_ref_var = MeanOfTwo(*triangle_a, *triangle_b, triangle_use, triangle_reference);
  // Vertices: the reference triangles' area-weighted means, like the bake's.
  for (uint32_t t = 0; t < scene->TriangleCount(); ++t) {
    const double a = 0.5 * glm::length(glm::cross(scene->Vertex(t, 1) - scene->Vertex(t, 0),
                                                  scene->Vertex(t, 2) - scene->Vertex(t, 0)));
    for (int c = 0; c < 3; ++c) vsum[scene->triangles[t][c]] += a * glm::dvec3(triangle_reference[t]);
  }
  std::vector<glm::vec3> vertex_reference(scene->positions.size(), glm::vec3(0.0f));
  for (size_t v = 0; v < vsum.size(); ++v)
    if (varea[v] > 0) vertex_reference[v] = glm::vec3(vsum[v] / varea[v]);
  std::printf("reference noise (rms): texels %.4f, triangles %.4f\n", std::sqrt(texel_ref_var),
              std::sqrt(triangle_ref_var));
  // The triangle reference carried to texels (area-weighted over each
  // texel's fragments): close to the texel reference where triangles are
  // small against the texel's W gradient; a check of the two references.
  std::vector<glm::vec3> texel_from_triangles(atlas->texel_count(), glm::vec3(0.0f));
  for (uint32_t t = 0; t < atlas->texel_count(); ++t) {
    glm::dvec3 sum(0.0);
    double area = 0;
    for (uint32_t f = atlas->texel_begin[t]; f < atlas->texel_begin[t + 1]; ++f) {
      sum += atlas->fragments[f].world_area * glm::dvec3(triangle_reference[atlas->fragments[f].triangle]);
      area += atlas->fragments[f].world_area;
    }
    if (area > 0) texel_from_triangles[t] = glm::vec3(sum / area);
  }
  std::printf("texel reference vs triangle reference carried to texels: rms %.4f\n",
              Compare(texel_reference_w, texel_from_triangles, texel_use, 0, 1, nullptr).rms);

  std::printf("\n%6s %5s | %-31s | %-31s | %-31s | %-22s | %-31s | %-22s | %s\n", "bundle", "dirs",
              "texel: rms (-ref) stated/own", "tri own: rms (-ref) st/own", "  median bound, unsampled",
              "tri texels': rms  stated", "vertex own: rms st/own med", "vert texels': rms st", "bake s");
  for (uint32_t bundle : bundles)
    for (uint32_t d : directions) {
      params.bundle_resolution = bundle;
      params.direction_count = d;
      gpu::ObscuranceBakeStats stats;
      t0 = std::chrono::steady_clock::now();
      auto baked = gpu::BakeObscurances(worker, **gpu_scene, *scene, *atlas, params, {}, &stats);
      if (!baked.ok()) { std::printf("bake: %s\n", std::string(baked.status().message()).c_str()); return 1; }
      const double bake_s = Seconds(t0);
      // The answer's single bound (what ComputeObscurances states) and the
      // elements it covers; Hoeffding over every direction for comparison.
      const ObscuranceBounds bounds = ObscuranceBoundsOf(*scene, *baked, confidence);
      const ObscuranceAnswerBound answer_bound = ObscuranceAnswerBoundOf(*baked, bounds, d, confidence);
      const double stated = answer_bound.error_bound;
      std::vector<uint8_t> use_texels(atlas->texel_count(), 0);
      for (uint32_t t = 0; t < atlas->texel_count(); ++t) use_texels[t] = texel_use[t] && baked->estimated[t];
      {
        std::vector<uint8_t> texel_in(use_texels.size(), 0), triangle_in(triangle_use.size(), 0),
            vertex_in(vertex_use.size(), 0);
        for (size_t t = 0; t < texel_in.size(); ++t) texel_in[t] = use_texels[t] && bounds.texel[t] <= stated;
        for (size_t t = 0; t < triangle_in.size(); ++t) triangle_in[t] = triangle_use[t] && bounds.triangle[t] <= stated;
        for (size_t v = 0; v < vertex_in.size(); ++v) vertex_in[v] = vertex_use[v] && bounds.vertex[v] <= stated;
        const double all_directions = ObscuranceHalfWidth(static_cast<double>(d), confidence);
        auto within = [&](const std::vector<glm::vec3>& estimate, const std::vector<glm::vec3>& reference,
                          const std::vector<uint8_t>& use, double bound) {
          return Compare(estimate, reference, use, 0, bound, nullptr);
        };
        const ErrorFigures tc = within(baked->w, texel_reference_w, texel_in, stated);
        const ErrorFigures ta = within(baked->w, texel_reference_w, use_texels, stated);
        const ErrorFigures th = within(baked->w, texel_reference_w, use_texels, all_directions);
        const ErrorFigures rc = within(baked->triangle_w, triangle_reference, triangle_in, stated);
        const ErrorFigures ra = within(baked->triangle_w, triangle_reference, triangle_use, stated);
        const ErrorFigures rh = within(baked->triangle_w, triangle_reference, triangle_use, all_directions);
        const ErrorFigures vc = within(baked->vertex_w, vertex_reference, vertex_in, stated);
        const ErrorFigures va = within(baked->vertex_w, vertex_reference, vertex_use, stated);
        std::printf("  single bound %.4f (Hoeffding over all %u directions: %.4f): within it, covered / all / all at "
                    "the Hoeffding figure: texels %.4f (%zu) / %.4f (%zu) / %.4f, triangles %.4f (%zu) / %.4f (%zu) / "
                    "%.4f, vertices %.4f (%zu) / %.4f (%zu); outside: %llu texels, %llu triangles, %llu vertices\n",
                    stated, d, all_directions, tc.within_stated, tc.elements, ta.within_stated, ta.elements,
                    th.within_stated, rc.within_stated, rc.elements, ra.within_stated, ra.elements, rh.within_stated,
                    vc.within_stated, vc.elements, va.within_stated, va.elements,
                    static_cast<unsigned long long>(answer_bound.texels.outside),
                    static_cast<unsigned long long>(answer_bound.triangles.outside),
                    static_cast<unsigned long long>(answer_bound.vertices.outside));
      }
      const ErrorFigures texel = Compare(baked->w, texel_reference_w, use_texels, texel_ref_var, stated, &bounds.texel);
      // Texels the surface covers nearly whole (built atlases: a texel's
      // world area is 1 / texels_per_unit^2, up to the chart's tilt): a
      // sliver's few samples make it noisy, not biased.
      std::vector<uint8_t> whole(atlas->texel_count(), 0);
      size_t whole_count = 0;
      if (atlas->texels_per_unit > 0)
        for (uint32_t t = 0; t < atlas->texel_count(); ++t) {
          double area = 0;
          for (uint32_t f = atlas->texel_begin[t]; f < atlas->texel_begin[t + 1]; ++f) area += atlas->fragments[f].world_area;
          whole[t] = use_texels[t] && area * atlas->texels_per_unit * atlas->texels_per_unit >= 0.9;
          whole_count += whole[t];
        }
      const ErrorFigures whole_texels = Compare(baked->w, texel_reference_w, whole, texel_ref_var, stated, &bounds.texel);
      // Texels by what their estimate rests on: at least a quarter of the
      // directions' worth, and the rest (slivers that a few samples reached,
      // more of which become estimated as the directions grow).
      std::vector<uint8_t> many(atlas->texel_count(), 0), few(atlas->texel_count(), 0);
      for (uint32_t t = 0; t < atlas->texel_count(); ++t) {
        many[t] = use_texels[t] && baked->texel_effective_samples[t] >= 0.25 * d;
        few[t] = use_texels[t] && !many[t];
      }
      const ErrorFigures many_texels = Compare(baked->w, texel_reference_w, many, texel_ref_var, stated, &bounds.texel);
      const ErrorFigures few_texels = Compare(baked->w, texel_reference_w, few, texel_ref_var, stated, &bounds.texel);
      std::printf("  texels with >= d/4 effective directions: %zu, rms %.4f, within stated %.4f, own %.4f; the other %zu: "
                  "rms %.4f, within stated %.4f, own %.4f (median own bound %.3f)\n",
                  many_texels.elements, many_texels.rms_less_reference, many_texels.within_stated, many_texels.within_own,
                  few_texels.elements, few_texels.rms_less_reference, few_texels.within_stated, few_texels.within_own,
                  few_texels.median_own);
      std::printf("  texel W vs the triangle reference carried to texels: rms %.4f; %zu nearly whole texels: rms %.4f "
                  "(less reference noise %.4f), within stated %.4f, own %.4f\n",
                  Compare(baked->w, texel_from_triangles, use_texels, 0, 1, nullptr).rms, whole_count, whole_texels.rms,
                  whole_texels.rms_less_reference, whole_texels.within_stated, whole_texels.within_own);
      const ErrorFigures own =
          Compare(baked->triangle_w, triangle_reference, triangle_use, triangle_ref_var, stated, &bounds.triangle);
      // The texels' mean per triangle: the bake's triangle W before.
      std::vector<glm::vec3> texels_mean(scene->TriangleCount());
      for (uint32_t t = 0; t < scene->TriangleCount(); ++t) texels_mean[t] = TriangleAverage(*atlas, *baked, t);
      const ErrorFigures mixed = Compare(texels_mean, triangle_reference, triangle_use, triangle_ref_var, stated, nullptr);
      size_t unsampled = 0;
      for (uint32_t t = 0; t < scene->TriangleCount(); ++t)
        unsampled += triangle_use[t] && baked->triangle_effective_samples[t] == 0;
      const ErrorFigures vertex = Compare(baked->vertex_w, vertex_reference, vertex_use, 0, stated, &bounds.vertex);
      // Vertices from the texels' triangle means.
      std::fill(vsum.begin(), vsum.end(), glm::dvec3(0.0));
      for (uint32_t t = 0; t < scene->TriangleCount(); ++t) {
        const double a = 0.5 * glm::length(glm::cross(scene->Vertex(t, 1) - scene->Vertex(t, 0),
                                                      scene->Vertex(t, 2) - scene->Vertex(t, 0)));
        for (int c = 0; c < 3; ++c) vsum[scene->triangles[t][c]] += a * glm::dvec3(texels_mean[t]);
      }
      std::vector<glm::vec3> vertex_before(scene->positions.size(), glm::vec3(0.0f));
      for (size_t v = 0; v < vsum.size(); ++v)
        if (varea[v] > 0) vertex_before[v] = glm::vec3(vsum[v] / varea[v]);
      const ErrorFigures vertex_mixed = Compare(vertex_before, vertex_reference, vertex_use, 0, stated, nullptr);
      std::printf("%6u %5u | %.4f (%.4f) %.4f %.4f | %.4f (%.4f) %.4f %.4f | %8.4f %6zu | %.4f (%.4f) %.4f | %.4f %.4f "
                  "%.4f %.4f | %.4f %.4f | %.1f (stated %.4f)\n",
                  stats.bundle_resolution, d, texel.rms, texel.rms_less_reference, texel.within_stated, texel.within_own,
                  own.rms, own.rms_less_reference, own.within_stated, own.within_own, own.median_own, unsampled,
                  mixed.rms, mixed.rms_less_reference, mixed.within_stated, vertex.rms, vertex.within_stated,
                  vertex.within_own, vertex.median_own, vertex_mixed.rms, vertex_mixed.within_stated, bake_s, stated);
      std::fflush(stdout);
    }
  return 0;
}

}  // namespace

// What cutting a bake into GL jobs of a step's target costs: the same bake
// with each step target (0: a direction is one job), alternating rounds,
// side by side; the bits must not change.
int RunStepCost(gpu::GpuWorker& worker, const std::filesystem::path& dir, const std::string& scene_name,
                uint32_t atlas_resolution, uint32_t directions, const std::vector<uint32_t>& steps_ms, int rounds) {
  const std::filesystem::path path = scene_name == "veach_ajar" ? dir / "interior_veach_ajar/veach_ajar.gltf"
                                     : scene_name == "bunny"    ? dir / "bunny/bunny.gltf"
                                                                : dir / "sponza_dabrovic/sponza.gltf";
  auto scene = LoadGltfFile(path);
  if (!scene.ok()) { std::printf("%s: %s\n", path.c_str(), std::string(scene.status().message()).c_str()); return 1; }
  auto gpu_scene = gpu::GpuScene::Upload(worker, *scene);
  auto atlas = BuildObscuranceAtlas(*scene, atlas_resolution);
  if (!gpu_scene.ok() || !atlas.ok()) return 1;
  ObscuranceParams params;
  params.d_max = 0.1 * glm::length(scene->bounds.Extent());
  params.direction_count = directions;
  std::map<uint32_t, std::vector<double>> seconds;
  std::optional<std::vector<uint64_t>> first_sums;
  for (int round = 0; round < rounds; ++round) {
    for (uint32_t step : steps_ms) {
      gpu::ObscuranceBakeOptions options;
      options.step_target_ms = step;
      const auto t0 = std::chrono::steady_clock::now();
      auto partial = gpu::BakeObscurancePartial(worker, **gpu_scene, *scene, *atlas, params, options);
      if (!partial.ok()) { std::printf("bake: %s\n", std::string(partial.status().message()).c_str()); return 1; }
      seconds[step].push_back(Seconds(t0));
      if (!first_sums) first_sums = partial->sums;
      else if (*first_sums != partial->sums) { std::printf("step %u ms: the sums differ\n", step); return 1; }
    }
  }
  auto median = [](std::vector<double> v) { std::sort(v.begin(), v.end()); return v[v.size() / 2]; };
  const double whole = median(seconds[steps_ms.front()]);
  std::printf("%s, atlas %u, %u directions, %d rounds (medians; bits equal):\n", scene_name.c_str(), atlas_resolution,
              directions, rounds);
  for (uint32_t step : steps_ms)
    std::printf("  step %4u ms: %8.2f s  %.2fx step %u\n", step, median(seconds[step]), median(seconds[step]) / whole,
                steps_ms.front());
  return 0;
}

int main(int argc, char** argv) {
  bool quick = false, update_only = false, coverage = false, plain_only = false, fast_only = false;
  bool step_cost = false;
  int moves = 5;
  uint32_t update_rays = 0;
  uint32_t reference_rays_option = 0;
  std::vector<uint32_t> direction_list, bundle_list;
  uint32_t bundle = 0, only_directions = 0, only_atlas = 0;
  std::string only_scene;
  std::filesystem::path dir = "../shared/scenes";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--update-only")) update_only = true;
    else if (!std::strcmp(argv[i], "--moves") && i + 1 < argc) moves = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--update-rays") && i + 1 < argc)
      update_rays = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--plain-only")) plain_only = true;
    else if (!std::strcmp(argv[i], "--fast-only")) fast_only = true;
    else if (!std::strcmp(argv[i], "--scene") && i + 1 < argc) only_scene = argv[++i];
    else if (!std::strcmp(argv[i], "--atlas") && i + 1 < argc) only_atlas = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--directions") && i + 1 < argc)
      only_directions = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--bundle") && i + 1 < argc) bundle = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--scenes") && i + 1 < argc) dir = argv[++i];
    else if (!std::strcmp(argv[i], "--coverage")) coverage = true;
    else if (!std::strcmp(argv[i], "--reference-rays") && i + 1 < argc)
      reference_rays_option = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--directions-list") && i + 1 < argc) direction_list = ParseList(argv[++i]);
    else if (!std::strcmp(argv[i], "--bundles") && i + 1 < argc) bundle_list = ParseList(argv[++i]);
    else if (!std::strcmp(argv[i], "--step-cost")) step_cost = true;
  }
  auto worker = gpu::GpuWorker::Start({});
  if (!worker.ok()) { std::fprintf(stderr, "%s\n", std::string(worker.status().message()).c_str()); return 1; }
  std::printf("device: %s\n", (*worker)->device().gl_renderer.c_str());
  if (step_cost)
    return RunStepCost(**worker, dir, only_scene.empty() ? "sponza" : only_scene, only_atlas ? only_atlas : 512,
                       only_directions ? only_directions : 8, {0, 25, 100}, 3);
  if (coverage) {
    if (direction_list.empty()) direction_list = only_directions ? std::vector<uint32_t>{only_directions}
                                                                 : std::vector<uint32_t>{16, 64, 256};
    if (bundle_list.empty()) bundle_list = {bundle};  // 0: 2 x atlas
    return RunCoverage(**worker, dir, only_scene.empty() ? "bunny" : only_scene, only_atlas ? only_atlas : 256,
                       reference_rays_option ? reference_rays_option : 4096, direction_list, bundle_list);
  }
  struct SceneCase { std::string name; std::filesystem::path path; };
  std::vector<SceneCase> scenes = {{"sponza", dir / "sponza_dabrovic/sponza.gltf"}};
  if (!quick || !only_scene.empty()) scenes.push_back({"veach_ajar", dir / "interior_veach_ajar/veach_ajar.gltf"});
  if (!only_scene.empty()) std::erase_if(scenes, [&](const SceneCase& c) { return c.name != only_scene; });
  const std::vector<uint32_t> resolutions = only_atlas ? std::vector<uint32_t>{only_atlas}
                                            : quick    ? std::vector<uint32_t>{512}
                                                       : std::vector<uint32_t>{512, 1024};
  const std::vector<uint32_t> directions = only_directions ? std::vector<uint32_t>{only_directions}
                                          : quick           ? std::vector<uint32_t>{16, 64}
                                                            : std::vector<uint32_t>{64, 256, 1024};
  const uint32_t reference_rays = quick ? 256 : 2048;

  std::printf("%-10s %5s %5s | %9s %8s %8s | %9s %8s %8s | %9s %8s %8s | %s\n", "scene", "atlas", "dirs", "gpu s", "rms",
              "smp/pt", "embree s", "rms", "rays/pt", "eq-err s", "rms", "rays/pt", "reference");
  for (const SceneCase& sc : scenes) {
    auto scene = LoadGltfFile(sc.path);
    if (!scene.ok()) { std::printf("%s: %s\n", sc.name.c_str(), std::string(scene.status().message()).c_str()); continue; }
    auto gpu_scene = gpu::GpuScene::Upload(**worker, *scene);
    if (!gpu_scene.ok()) return 1;
    ObscuranceParams params;
    params.d_max = 0.1 * glm::length(scene->bounds.Extent());
    params.color_bleeding = true;
    params.bundle_resolution = bundle;
    for (uint32_t res : update_only ? std::vector<uint32_t>{} : resolutions) {
      auto t0 = std::chrono::steady_clock::now();
      auto atlas = BuildObscuranceAtlas(*scene, res);
      if (!atlas.ok()) { std::printf("%s %u: %s\n", sc.name.c_str(), res, std::string(atlas.status().message()).c_str()); continue; }
      const double atlas_s = Seconds(t0);
      RayEstimateOptions ref_options;
      ref_options.rays_per_patch = reference_rays;
      ref_options.seed = 999;
      t0 = std::chrono::steady_clock::now();
      auto reference = EstimateObscurancesByRays(*scene, *atlas, params, ref_options);
      if (!reference.ok()) return 1;
      const double ref_s = Seconds(t0);
      for (uint32_t d : directions) {
        params.direction_count = d;
        gpu::ObscuranceBakeStats stats;
        t0 = std::chrono::steady_clock::now();
        auto baked = gpu::BakeObscurances(**worker, **gpu_scene, *scene, *atlas, params, {}, &stats);
        if (!baked.ok()) { std::printf("bake: %s\n", std::string(baked.status().message()).c_str()); return 1; }
        const double gpu_s = Seconds(t0);
        RayEstimateOptions ro;
        ro.rays_per_patch = std::max<uint32_t>(1, static_cast<uint32_t>(std::lround(baked->mean_samples_per_patch)));
        t0 = std::chrono::steady_clock::now();
        auto rays = EstimateObscurancesByRays(*scene, *atlas, params, ro);
        if (!rays.ok()) return 1;
        const double ray_s = Seconds(t0);
        const double gpu_rms = Rms(*atlas, *baked, *reference), ray_rms = Rms(*atlas, *rays, *reference);
        // Equal error: the fewest rays per patch whose error is at most the
        // bake's, by bisection (the error falls with the ray count, but not
        // exactly like 1/sqrt(N): the rays are stratified), timed at the end.
        RayEstimateOptions eq = ro;
        if (ray_rms <= gpu_rms) {
          uint32_t too_few = 0, enough = ro.rays_per_patch;
          while (enough - too_few > 1) {
            RayEstimateOptions trial = ro;
            trial.rays_per_patch = too_few + (enough - too_few) / 2;
            auto estimate = EstimateObscurancesByRays(*scene, *atlas, params, trial);
            if (!estimate.ok()) return 1;
            (Rms(*atlas, *estimate, *reference) <= gpu_rms ? enough : too_few) = trial.rays_per_patch;
          }
          eq.rays_per_patch = enough;
        }
        t0 = std::chrono::steady_clock::now();
        auto rays_eq = EstimateObscurancesByRays(*scene, *atlas, params, eq);
        if (!rays_eq.ok()) return 1;
        const double eq_s = Seconds(t0);
        std::printf("%-10s %5u %5u | %9.2f %8.4f %8.0f | %9.2f %8.4f %8u | %9.2f %8.4f %8u | %u rays/pt %.0f s, atlas %.1f s, "
                    "%u charts, max layers %u\n",
                    sc.name.c_str(), res, d, gpu_s, gpu_rms, baked->mean_samples_per_patch, ray_s, ray_rms,
                    ro.rays_per_patch, eq_s, Rms(*atlas, *rays_eq, *reference), eq.rays_per_patch, reference_rays, ref_s,
                    atlas_s, atlas->chart_count, stats.max_layers);
        std::fflush(stdout);
      }
    }
    // Update latency: the node nearest 1K triangles.
    if (sc.name != "sponza") continue;
    uint32_t node = 0;
    for (uint32_t n = 0; n < scene->nodes.size(); ++n)
      if (std::abs(static_cast<int>(scene->nodes[n].triangle_count) - 1000) <
          std::abs(static_cast<int>(scene->nodes[node].triangle_count) - 1000))
        node = n;
    auto atlas = BuildObscuranceAtlas(*scene, 512);
    if (!atlas.ok()) return 1;
    params.direction_count = 16;
    auto baked = gpu::BakeObscurances(**worker, **gpu_scene, *scene, *atlas, params);
    if (!baked.ok()) return 1;
    // Each ray count on each path: the plain one (every texel scanned, every
    // patch to recompute traced in full, one ray at a time) and the fast one
    // (patch index, only the rays that can meet the object traced), with
    // full traces as ray streams or not. The updaters move in turn, step by
    // step, so that a load on the machine weighs on them alike; after the
    // moves each fast path's W per texel, triangle and vertex is held
    // to the plain one's, bit for bit.
    struct Row {
      const char* path;
      UpdaterOptions options;
      std::unique_ptr<ObscuranceUpdater> updater;
      std::vector<double> ms, candidates_ms, trace_ms, triangles_ms;
      ObscuranceUpdate last;
      double create_s = 0;
    };
    std::printf("\nupdate: sponza node '%s' (%u triangles), 512^2 atlas, d_max %.2f, %d moves of %.2f m; medians over the "
                "moves, figures of the last move; 'differ': elements whose W is not bit for bit the plain path's\n",
                scene->nodes[node].name.c_str(), scene->nodes[node].triangle_count, params.d_max, moves, 0.2 * params.d_max);
    std::printf("%-22s %4s | %8s %6s | %8s %8s %8s | %7s %7s %6s %7s | %8s %8s %8s | %6s %6s %6s\n", "path", "rays",
                "ms", "x", "cand ms", "trace ms", "tri ms", "pooled", "reach", "cand", "recomp", "rays", "tri rays",
                "probed", "texels", "tris", "verts");
    for (uint32_t rays : update_rays ? std::vector<uint32_t>{update_rays} : std::vector<uint32_t>{16u, 64u}) {
      std::vector<Row> rows;
      for (int variant = 0; variant < 3; ++variant) {
        if (variant > 0 && plain_only) continue;
        if (variant != 1 && fast_only) continue;
        Row row;
        row.path = variant == 0 ? "plain (scan, full)" : variant == 1 ? "fast (index, affected)" : "fast, full as streams";
        row.options.rays_per_patch = rays;
        row.options.exhaustive = variant == 0;
        row.options.ray_streams = variant == 2;
        auto t0 = std::chrono::steady_clock::now();
        auto updater = ObscuranceUpdater::Create(*scene, *atlas, params, *baked, {node}, row.options);
        if (!updater.ok()) { std::printf("updater: %s\n", std::string(updater.status().message()).c_str()); return 1; }
        row.create_s = Seconds(t0);
        row.updater = std::move(*updater);
        rows.push_back(std::move(row));
      }
      for (int step = 1; step <= moves; ++step) {
        // Five steps out and back, as often as asked.
        const int out = (step - 1) % 10 < 5 ? (step - 1) % 10 + 1 : 10 - (step - 1) % 10 - 1;
        const glm::dmat4 world = glm::translate(glm::dmat4(1.0), glm::dvec3(0.2 * out * params.d_max, 0, 0)) *
                                 scene->nodes[node].world;
        for (Row& row : rows) {
          auto up = row.updater->MoveNode(node, world);
          if (!up.ok()) { std::printf("update: %s\n", std::string(up.status().message()).c_str()); return 1; }
          row.ms.push_back(up->milliseconds);
          row.candidates_ms.push_back(up->candidates_ms);
          row.trace_ms.push_back(up->trace_ms);
          row.triangles_ms.push_back(up->triangles_ms);
          row.last = *up;
        }
      }
      auto median = [](std::vector<double> v) {
        std::sort(v.begin(), v.end());
        return v[v.size() / 2];
      };
      auto differing = [](const std::vector<glm::vec3>& a, const std::vector<glm::vec3>& b) {
        size_t n = 0;
        for (size_t i = 0; i < a.size(); ++i) n += std::memcmp(&a[i], &b[i], sizeof(glm::vec3)) != 0;
        return n;
      };
      // Without the plain path, the first row stands in (its 'differ' is 0).
      const ObscuranceResult& plain = rows[0].updater->result();
      const double plain_ms = median(rows[0].ms);
      for (const Row& row : rows) {
        const ObscuranceResult& r = row.updater->result();
        const ObscuranceUpdate& u = row.last;
        std::printf("%-22s %4u | %8.1f %6.2f | %8.1f %8.1f %8.1f | %7u %7u %6u %7u | %8llu %8llu %8llu | %6zu %6zu %6zu\n",
                    row.path, rays, median(row.ms), median(row.ms) / plain_ms, median(row.candidates_ms),
                    median(row.trace_ms), median(row.triangles_ms), u.pooled, u.within_reach, u.candidates, u.recomputed,
                    static_cast<unsigned long long>(u.rays), static_cast<unsigned long long>(u.triangle_rays),
                    static_cast<unsigned long long>(u.probed_rays), differing(plain.w, r.w),
                    differing(plain.triangle_w, r.triangle_w), differing(plain.vertex_w, r.vertex_w));
      }
      std::fflush(stdout);
    }
  }
  return 0;
}
