#include "visq/gpu/ray_scene.h"

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstring>
#include <chrono>
#include <string>

#include "common/parallel.h"
#include "gl_object.h"
#include "raycast/float_segment.h"
#include "shader_program.h"
#include "timed_sizer.h"
#include "visq_gpu_rays_embedded.h"

namespace visq::gpu {

namespace {

// At most this many segments a GL job: 128 MiB of segments and ignores.
constexpr int kMaxJobSegments = 1 << 22;
constexpr GLuint kGroupSize = 64;         // rays_trace.comp's local_size_x

struct TraceUniforms {
  explicit TraceUniforms(UniformLocator& at)
      : segment_count(at.Find<unsigned>("segment_count")), node_count(at.Find<unsigned>("node_count")) {}
  Uniform<unsigned> segment_count;
  Uniform<unsigned> node_count;
};
constexpr GLuint kMaxGroupsAcross = 32768;  // under GL's guaranteed 65535

// A store of at least 16 bytes (GL refuses an empty one): a smaller `data`
// is copied into zeros first, so GL never reads past the caller's bytes.
GlBuffer MakeBuffer(size_t bytes, const void* data) {
  std::array<std::byte, 16> padded{};
  if (bytes < padded.size()) {
    if (data != nullptr && bytes > 0) std::memcpy(padded.data(), data, bytes);
    if (data != nullptr) data = padded.data();
    bytes = padded.size();
  }
  GlBuffer buffer;
  glNamedBufferStorage(buffer.id(), static_cast<GLsizeiptr>(bytes), data, 0);
  return buffer;
}

}  // namespace

// rays_trace.comp's Hit: a miss names kNoTriangle.
struct RayScene::GpuHit {
  float t = 0.0f;
  uint32_t triangle = raycast::kNoTriangle;
  float u = 0.0f;
  float v = 0.0f;
};
struct RayScene::Resources {
  GlBuffer nodes{NoCreate};
  GlBuffer corners{NoCreate};
};

bool RayScene::IsCurrent() const { return worker_ != nullptr && worker_->context_generation() == generation_; }

RayScene::~RayScene() {
  if (resources_ && worker_) worker_->Post([resources = std::move(resources_)]() mutable { resources.reset(); });
}

StatusOr<std::shared_ptr<RayScene>> RayScene::Upload(GpuWorker& worker, const raycast::FlatBvh& bvh,
                                                     const JobOptions& job) {
  std::shared_ptr<RayScene> out(new RayScene());
  out->worker_ = &worker;
  out->origin_ = bvh.origin;
  out->extent_ = bvh.extent;
  out->triangle_count_ = bvh.triangle_count();
  out->node_count_ = static_cast<uint32_t>(bvh.nodes.size());
  out->gpu_bytes_ = bvh.bytes();
  // Owned by the scene from the start: a job that fails after making a
  // buffer releases it on the GL thread like any other.
  out->resources_ = std::make_shared<Resources>();
  VISQ_RETURN_IF_ERROR(worker.Run(job, [&]() -> Status {
    out->resources_->nodes = MakeBuffer(bvh.nodes.size() * sizeof(raycast::FlatBvhNode), bvh.nodes.data());
    out->resources_->corners =
        MakeBuffer(bvh.corners.size() * sizeof(raycast::FlatBvhCorner), bvh.corners.data());
    out->generation_ = CurrentContextGeneration();
    return absl::OkStatus();
  }));
  return out;
}

// Both traces, in GL jobs sized by their time: the segments of each job
// are made on the caller's threads (make(i, segment, ignore)), traced by
// rays_trace.comp, and handed to take(begin, n, bits or hits) as read back.
Status RayScene::Trace(size_t count, const SegmentMaker& make, bool closest, const RayTraceOptions& options,
                       const JobResults& take) const {
  static_assert(sizeof(GpuHit) == 16, "rays_trace.comp's Hit in std430");
  if (count == 0 || node_count_ == 0) return absl::OkStatus();
  TimedSizer sizer(options.target_job_ms, kMaxJobSegments, static_cast<int>(options.first_job_segments));
  std::vector<raycast::FloatSegment> segments;
  std::vector<uint32_t> ignore;
  std::vector<uint32_t> bits;
  std::vector<GpuHit> hits;
  for (size_t begin = 0; begin < count;) {
    VISQ_RETURN_IF_ERROR(options.job.stop.Check("tracing rays on the GPU"));
    const size_t n = std::min<size_t>(static_cast<size_t>(sizer.size()), count - begin);
    segments.resize(n);
    ignore.resize(n);
    ParallelFor(n, 4096, [&](size_t first, size_t end) {
      for (size_t i = first; i < end; ++i) make(begin + i, segments[i], ignore[i]);
    });
    if (closest) hits.assign(n, GpuHit{});
    else bits.assign((n + 31) / 32, 0u);
    JobTiming timing;
    VISQ_RETURN_IF_ERROR(worker_->Run(
        options.job,
        [&]() -> Status {
          if (generation_ != CurrentContextGeneration())
            return absl::UnavailableError("the GPU context was lost since the scene's rays were uploaded; retry");
          ShaderDefines defines = {{"MAX_DEPTH", std::to_string(raycast::kMaxFlatBvhDepth)}};
          if (closest) defines.emplace_back("CLOSEST_HIT", "1");
          VISQ_ASSIGN_OR_RETURN(
              const TypedProgram<TraceUniforms>* program,
              CachedProgram<TraceUniforms>(rays_shaders::Find, {{GL_COMPUTE_SHADER, "rays_trace.comp"}}, defines));
          const GlBuffer segment_buffer = MakeBuffer(n * sizeof(raycast::FloatSegment), segments.data());
          const GlBuffer ignore_buffer = MakeBuffer(n * sizeof(uint32_t), ignore.data());
          const size_t out_bytes = closest ? hits.size() * sizeof(GpuHit) : bits.size() * sizeof(uint32_t);
          void* out_data = closest ? static_cast<void*>(hits.data()) : static_cast<void*>(bits.data());
          const GlBuffer out = MakeBuffer(out_bytes, out_data);
          glUseProgram(program->id());
          program->uniforms.segment_count.Set(static_cast<unsigned>(n));
          program->uniforms.node_count.Set(node_count_);
          const GLuint buffers[] = {resources_->nodes.id(), resources_->corners.id(), segment_buffer.id(),
                                    ignore_buffer.id(), out.id()};
          for (GLuint binding = 0; binding < 5; ++binding)
            glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, buffers[binding]);
          const GLuint groups = static_cast<GLuint>((n + kGroupSize - 1) / kGroupSize);
          const GLuint across = std::min(groups, kMaxGroupsAcross);
          glDispatchCompute(across, (groups + across - 1) / across, 1);
          glMemoryBarrier(GL_BUFFER_UPDATE_BARRIER_BIT);
          glGetNamedBufferSubData(out.id(), 0, static_cast<GLsizeiptr>(out_bytes), out_data);
          for (GLuint binding = 0; binding < 5; ++binding) glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, 0);
          glUseProgram(0);
          return absl::OkStatus();
        },
        &timing));
    sizer.Measured(static_cast<int>(n), timing.run_ms);
    take(begin, n, bits, hits);
    begin += n;
  }
  return absl::OkStatus();
}

StatusOr<std::vector<uint8_t>> RayScene::Occluded(size_t count,
                                                  const std::function<raycast::Segment(size_t)>& segment_at,
                                                  const RayTraceOptions& options) const {
  std::vector<uint8_t> result(count, 0);
  VISQ_RETURN_IF_ERROR(Trace(
      count,
      [&](size_t i, raycast::FloatSegment& segment, uint32_t& ignore) {
        const raycast::Segment s = segment_at(i);
        segment = raycast::ToFloatSegment(s, origin_, extent_);
        ignore = s.ignore_triangle;
      },
      /*closest=*/false, options,
      [&](size_t begin, size_t n, const std::vector<uint32_t>& bits, const std::vector<GpuHit>&) {
        for (size_t i = 0; i < n; ++i) result[begin + i] = static_cast<uint8_t>((bits[i >> 5] >> (i & 31)) & 1u);
      }));
  return result;
}

StatusOr<std::vector<raycast::Hit>> RayScene::Intersect(std::span<const raycast::Ray> rays,
                                                        const RayTraceOptions& options) const {
  std::vector<raycast::Hit> result(rays.size());
  bool corrupt = false;
  VISQ_RETURN_IF_ERROR(Trace(
      rays.size(),
      [&](size_t i, raycast::FloatSegment& segment, uint32_t& ignore) {
        segment = raycast::ToFloatRay(rays[i], origin_, extent_);
        ignore = rays[i].ignore_triangle;
      },
      /*closest=*/true, options,
      [&](size_t begin, size_t n, const std::vector<uint32_t>&, const std::vector<GpuHit>& hits) {
        for (size_t i = 0; i < n; ++i) {
          const uint32_t triangle = hits[i].triangle;
          if (triangle == raycast::kNoTriangle) continue;
          if (triangle >= triangle_count_) {
            corrupt = true;
            continue;
          }
          raycast::Hit& hit = result[begin + i];
          hit.hit = true;
          hit.t = hits[i].t;
          hit.triangle = triangle;
          hit.u = hits[i].u;
          hit.v = hits[i].v;
        }
      }));
  if (corrupt) return absl::InternalError("the GPU's closest hits named a triangle the scene does not have");
  return result;
}

}  // namespace visq::gpu
