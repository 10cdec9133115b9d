#include "visq/gpu/ray_scene.h"

#include <algorithm>
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
constexpr GLuint kGroupSize = 64;         // rays_occluded.comp's local_size_x
constexpr GLuint kMaxGroupsAcross = 32768;  // under GL's guaranteed 65535

GlBuffer MakeBuffer(size_t bytes, const void* data) {
  GlBuffer buffer;
  glNamedBufferStorage(buffer.id(), static_cast<GLsizeiptr>(std::max<size_t>(bytes, 16)), data, 0);
  return buffer;
}

}  // namespace

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
  auto resources = std::make_shared<Resources>();
  VISQ_RETURN_IF_ERROR(worker.Run(job, [&]() -> Status {
    resources->nodes = MakeBuffer(bvh.nodes.size() * sizeof(raycast::FlatBvhNode), bvh.nodes.data());
    resources->corners = MakeBuffer(bvh.corners.size() * sizeof(glm::vec4), bvh.corners.data());
    out->generation_ = CurrentContextGeneration();
    return absl::OkStatus();
  }));
  out->resources_ = std::move(resources);
  return out;
}

StatusOr<std::vector<uint8_t>> RayScene::Occluded(size_t count,
                                                  const std::function<raycast::Segment(size_t)>& segment_at,
                                                  const RayTraceOptions& options) const {
  std::vector<uint8_t> result(count, 0);
  if (count == 0 || node_count_ == 0) return result;
  TimedSizer sizer(options.target_job_ms, kMaxJobSegments, static_cast<int>(options.first_job_segments));
  std::vector<raycast::FloatSegment> segments;
  std::vector<uint32_t> ignore;
  std::vector<uint32_t> bits;
  for (size_t begin = 0; begin < count;) {
    VISQ_RETURN_IF_ERROR(options.job.stop.Check("tracing rays on the GPU"));
    const size_t n = std::min<size_t>(static_cast<size_t>(sizer.size()), count - begin);
    segments.resize(n);
    ignore.resize(n);
    // Segments are made on the caller's threads, so the GL thread only
    // copies them.
    ParallelFor(n, 4096, [&](size_t first, size_t end) {
      for (size_t i = first; i < end; ++i) {
        const raycast::Segment s = segment_at(begin + i);
        segments[i] = raycast::ToFloatSegment(s, origin_, extent_);
        ignore[i] = s.ignore_triangle;
      }
    });
    bits.assign((n + 31) / 32, 0u);
    JobTiming timing;
    VISQ_RETURN_IF_ERROR(worker_->Run(
        options.job,
        [&]() -> Status {
          if (generation_ != CurrentContextGeneration())
            return absl::UnavailableError("the GPU context was lost since the scene's rays were uploaded; retry");
          VISQ_ASSIGN_OR_RETURN(const GlProgram* program,
                                CachedProgram(rays_shaders::Find, {{GL_COMPUTE_SHADER, "rays_occluded.comp"}},
                                              {{"MAX_DEPTH", std::to_string(raycast::kMaxFlatBvhDepth)}}));
          const GlBuffer segment_buffer = MakeBuffer(n * sizeof(raycast::FloatSegment), segments.data());
          const GlBuffer ignore_buffer = MakeBuffer(n * sizeof(uint32_t), ignore.data());
          const GlBuffer blocked = MakeBuffer(bits.size() * sizeof(uint32_t), bits.data());
          glUseProgram(program->id());
          program->Set("segment_count", static_cast<unsigned>(n));
          program->Set("node_count", node_count_);
          const GLuint buffers[] = {resources_->nodes.id(), resources_->corners.id(), segment_buffer.id(),
                                    ignore_buffer.id(), blocked.id()};
          for (GLuint binding = 0; binding < 5; ++binding)
            glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, buffers[binding]);
          const GLuint groups = static_cast<GLuint>((n + kGroupSize - 1) / kGroupSize);
          const GLuint across = std::min(groups, kMaxGroupsAcross);
          glDispatchCompute(across, (groups + across - 1) / across, 1);
          glMemoryBarrier(GL_BUFFER_UPDATE_BARRIER_BIT);
          glGetNamedBufferSubData(blocked.id(), 0, static_cast<GLsizeiptr>(bits.size() * sizeof(uint32_t)),
                                  bits.data());
          for (GLuint binding = 0; binding < 5; ++binding) glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, 0);
          glUseProgram(0);
          return absl::OkStatus();
        },
        &timing));
    sizer.Measured(static_cast<int>(n), timing.run_ms);
    for (size_t i = 0; i < n; ++i) result[begin + i] = static_cast<uint8_t>((bits[i >> 5] >> (i & 31)) & 1u);
    begin += n;
  }
  return result;
}

}  // namespace visq::gpu
