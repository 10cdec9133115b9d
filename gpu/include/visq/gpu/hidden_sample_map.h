// Hidden-sample maps and patch-to-patch visibility on the GPU (Eisemann &
// Décoret 2007, "Visibility Sampling on GPU and Applications"). The
// algorithm lives in gpu/hidden_sample_map/ with its shaders; this header is
// its public face and holds no GL or protobuf type. The model it answers in
// (patches, requests, results, bounds) is lib/sampling.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>

#include "common/status.h"
#include "sampling/visibility_sampling.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

struct HiddenSampleMapperOptions {
  // A map is drawn, read back and counted a band of receiver rows at a time,
  // each band a GL job whose read-back stays under this: a map at the
  // bitmask cap never holds its GL targets' copy whole, and other queries
  // get the GL thread between bands. The bits are those of one full draw.
  size_t band_readback_bytes = size_t{64} << 20;
  // Bands are also sized by what they cost here, so that one GL job lasts
  // about this long: the GL thread's other queries, a cancellation, a
  // deadline and the server's drain wait at most about one job. Each band's
  // measured time sizes the next (doubling or halving its rows, never below
  // the size where the passes' fixed cost takes over), and a scene's last
  // size starts its next map. 0: by bytes alone (one band for most maps).
  double band_target_ms = 100.0;
  // Each pass draws only the scene's triangle clusters (GpuScene::clusters())
  // that are not wholly outside a plane of the shaft, the convex hull of
  // source and receiver: a query costs what lies near it, not the whole
  // scene. The geometry shader drops every triangle of the other clusters
  // anyway, so the bits are those of drawing everything, which `false` does.
  bool cull_clusters = true;
  // Counts the fragments each pass shades, for fragments_shaded(): what
  // the influence regions cost, which the benches print. Off by default
  // (each pass then waits for its query).
  bool count_fragments = false;
};

// Owns a small cache of Hough tables (keyed by the sample
// pattern and resolution) on the GL thread. Thread-safe: every GL step runs
// as a job on the worker.
class HiddenSampleMapper {
 public:
  [[nodiscard]] static StatusOr<std::unique_ptr<HiddenSampleMapper>> Create(GpuWorker& worker,
                                                                            HiddenSampleMapperOptions options = {});
  ~HiddenSampleMapper();  // releases GL objects on the GL thread
  HiddenSampleMapper(const HiddenSampleMapper&) = delete;
  HiddenSampleMapper& operator=(const HiddenSampleMapper&) = delete;

  // Without a sink the result holds the whole map; with one, each band of
  // rows goes to the sink as soon as it is counted and the result holds the
  // figures only (sizes, samples, bound, timing).
  [[nodiscard]] StatusOr<sampling::HiddenSampleMapResult> Compute(const GpuScene& scene,
                                                                  const sampling::HiddenSampleMapRequest& request,
                                                                  const JobOptions& job = {},
                                                                  const sampling::HiddenSampleMapBandSink& sink = {});
  // How many triangles each pass of `request` draws (the whole scene unless
  // the clusters are culled). CPU only.
  [[nodiscard]] StatusOr<uint64_t> TrianglesDrawnPerPass(const GpuScene& scene,
                                                         const sampling::HiddenSampleMapRequest& request) const;
  [[nodiscard]] StatusOr<sampling::PatchVisibilityResult> PatchVisibility(const GpuScene& scene,
                                                                const sampling::PatchVisibilityRequest& request,
                                                                const JobOptions& job = {});

  // The fragments shaded by every pass this mapper has drawn, where
  // options.count_fragments asked for them and the driver counts them
  // (GL_ARB_pipeline_statistics_query); nullopt otherwise.
  [[nodiscard]] std::optional<uint64_t> fragments_shaded() const;

  struct State;      // GL-thread state, defined in gpu/hidden_sample_map/
  struct BandSizes;  // per scene, the band size that met band_target_ms

 private:
  HiddenSampleMapper(GpuWorker& worker, HiddenSampleMapperOptions options);
  GpuWorker* worker_;
  HiddenSampleMapperOptions options_;
  std::shared_ptr<State> state_;
  std::shared_ptr<BandSizes> band_sizes_;
};

}  // namespace visq::gpu
