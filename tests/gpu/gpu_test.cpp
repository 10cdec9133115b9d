// The GPU layer on a real EGL context (Mesa llvmpipe here): context, RAII
// owners, shader builds and their errors, the GL thread's queue semantics,
// and scene upload.
#include <atomic>
#include <cmath>
#include <cstdio>
#include <future>
#include <thread>
#include <type_traits>

#include <epoxy/egl.h>
#include <gtest/gtest.h>

#include "gl_check.h"
#include "gl_object.h"
#include "shader_program.h"
#include "scene/sample_scenes.h"
#include "gpu_test_support.h"
#include "test_support.h"
#include "visq/gpu/camera.h"
#include "visq/gpu/gpu_scene.h"

namespace visq::gpu {
namespace {

// The shared pinhole camera, without a context: each bad field is named,
// and the clip transform puts what the camera looks at in the image center.
TEST(PinholeCamera, ValidationNamesTheField) {
  PinholeCamera camera;
  EXPECT_TRUE(ValidatePinholeCamera(camera, 4096).ok());
  auto message_of = [](const PinholeCamera& c, uint32_t cap = 4096) {
    return std::string(ValidatePinholeCamera(c, cap).message());
  };
  PinholeCamera bad = camera;
  bad.position.y = std::nan("");
  EXPECT_EQ(ValidatePinholeCamera(bad, 4096).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(message_of(bad).find("camera.position"), std::string::npos) << message_of(bad);
  bad = camera;
  bad.vertical_fov_deg = 0;
  EXPECT_EQ(ValidatePinholeCamera(bad, 4096).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(message_of(bad).find("camera.vertical_fov_deg"), std::string::npos) << message_of(bad);
  bad = camera;
  bad.up = bad.forward * 2.0;
  EXPECT_NE(message_of(bad).find("camera.up"), std::string::npos) << message_of(bad);
  bad = camera;
  bad.forward = glm::dvec3(0.0);
  EXPECT_NE(message_of(bad).find("camera.forward"), std::string::npos) << message_of(bad);
  bad = camera;
  bad.height = 0;
  EXPECT_EQ(ValidatePinholeCamera(bad, 4096).code(), absl::StatusCode::kInvalidArgument);
  bad = camera;
  bad.width = 5000;
  EXPECT_EQ(ValidatePinholeCamera(bad, 4096).code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(message_of(bad).find("4096"), std::string::npos) << message_of(bad);
}

TEST(PinholeCamera, ClipLooksAlongForwardFromTheAnchor) {
  PinholeCamera camera;
  camera.position = {100.0, 5.0, 10.0};
  camera.forward = {0.0, 0.0, -1.0};
  Bounds bounds;
  bounds.Extend({99.0, 4.0, -1.0});
  bounds.Extend({101.0, 6.0, 1.0});
  const glm::dvec3 anchor(100.0, 5.0, 0.0);
  const glm::dmat4 clip = PinholeClipFromAnchor(camera, anchor, bounds);
  // The box's center lies straight ahead: clip x, y = 0, depth inside (-1, 1).
  const glm::dvec4 c = clip * glm::dvec4(glm::dvec3(100.0, 5.0, 0.0) - anchor, 1.0);
  EXPECT_NEAR(c.x / c.w, 0.0, 1e-12);
  EXPECT_NEAR(c.y / c.w, 0.0, 1e-12);
  EXPECT_GT(c.z / c.w, -1.0);
  EXPECT_LT(c.z / c.w, 1.0);
  // A point up and to the right lands up (+y) and right (+x).
  const glm::dvec4 q = clip * glm::dvec4(glm::dvec3(100.5, 5.5, 0.0) - anchor, 1.0);
  EXPECT_GT(q.x / q.w, 0.0);
  EXPECT_GT(q.y / q.w, 0.0);
  // The farthest corner stays in front of the far plane.
  const glm::dvec4 far = clip * glm::dvec4(glm::dvec3(99.0, 4.0, -1.0) - anchor, 1.0);
  EXPECT_LT(far.z / far.w, 1.0);
}

using testing::SharedGpuWorker;

// --- RAII owners: type traits need no context ------------------------------

static_assert(!std::is_copy_constructible_v<GlBuffer>);
static_assert(!std::is_copy_assignable_v<GlBuffer>);
static_assert(std::is_nothrow_move_constructible_v<GlBuffer>);
static_assert(std::is_nothrow_move_assignable_v<GlBuffer>);
static_assert(std::is_nothrow_move_constructible_v<GlTexture2D>);
static_assert(!std::is_copy_constructible_v<GlProgramObject>);

TEST(GlObject, NoCreateIsEmptyAndNeedsNoContext) {
  GlBuffer empty(NoCreate);
  EXPECT_FALSE(empty);
  EXPECT_EQ(empty.id(), 0u);
  GlBuffer moved(std::move(empty));
  EXPECT_FALSE(moved);
  EXPECT_EQ(moved.Release(), 0u);
}

TEST(GlObject, CreatesMovesAndDeletesOnTheGlThread) {
  Status status = SharedGpuWorker().Run({}, []() -> Status {
    GlBuffer a;
    EXPECT_NE(a.id(), 0u);
    const GLuint id = a.id();
    GlBuffer b(std::move(a));
    EXPECT_EQ(b.id(), id);
    EXPECT_FALSE(a);  // NOLINT: moved-from state is defined: empty
    EXPECT_TRUE(glIsBuffer(id));
    {
      GlBuffer c(std::move(b));
    }
    EXPECT_FALSE(glIsBuffer(id));  // deleted with its owner
    return absl::OkStatus();
  });
  EXPECT_TRUE(status.ok()) << status;
}

// --- Context and self-test -------------------------------------------------

TEST(GpuContext, IsOpenGl45Core) {
  const DeviceInfo& device = SharedGpuWorker().device();
  EXPECT_NE(device.gl_version.find("4.5"), std::string::npos) << device.gl_version;
  EXPECT_FALSE(device.gl_renderer.empty());
  EXPECT_FALSE(device.egl_platform.empty());
  // tests/bench/gpu-check.sh reads this line to show which device ran.
  std::printf("gpu-context: renderer \"%s\", %s, EGL platform %s\n", device.gl_renderer.c_str(),
              device.gl_version.c_str(), device.egl_platform.c_str());
}

TEST(GpuContext, SelfTestDrawsAndReadsBackWithLogicOpOr) {
  const Status status = RunSelfTest(SharedGpuWorker());
  EXPECT_TRUE(status.ok()) << status;
}

// Workers share their device's EGL display: one that stops must leave the
// others their contexts (the display is terminated with its last context).
TEST(GpuContext, AWorkerThatStopsLeavesTheOthersTheirContexts) {
  auto first = GpuWorker::Start({});
  auto second = GpuWorker::Start({});
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_TRUE(second.ok()) << second.status();
  first->reset();
  Status current = (*second)->Run({}, [] {
    return eglGetCurrentContext() == EGL_NO_CONTEXT ? absl::InternalError("no current EGL context")
                                                     : absl::OkStatus();
  });
  EXPECT_TRUE(current.ok()) << current;
  EXPECT_TRUE(RunSelfTest(**second).ok());
}

TEST(GpuContext, UnknownDeviceChoiceIsAClearError) {
  GpuOptions options;
  options.device = "device:999";
  auto worker = GpuWorker::Start(options);
  ASSERT_FALSE(worker.ok());
  EXPECT_EQ(worker.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(worker.status().message()).find("device:999"), std::string::npos) << worker.status();
}

// --- Shaders ----------------------------------------------------------------

TEST(Shaders, EmbeddedFilesBuild) {
  Status status = SharedGpuWorker().Run({}, []() -> Status {
    return BuildProgram(CoreShaderFiles, {{GL_VERTEX_SHADER, "self_test.vert"}, {GL_FRAGMENT_SHADER, "self_test.frag"}}).status();
  });
  EXPECT_TRUE(status.ok()) << status;
}

TEST(Shaders, CompileErrorNamesTheFileAndCarriesTheDriverLog) {
  Status status = SharedGpuWorker().Run({}, []() -> Status {
    // A define that breaks the fragment shader's syntax.
    return BuildProgram(CoreShaderFiles, {{GL_VERTEX_SHADER, "self_test.vert"}, {GL_FRAGMENT_SHADER, "self_test.frag"}},
                        {{"out_bits", "= ="}})
        .status();
  });
  ASSERT_FALSE(status.ok());
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  const std::string message(status.message());
  EXPECT_NE(message.find("self_test.frag"), std::string::npos) << message;
  EXPECT_NE(message.find("compiling fragment shader"), std::string::npos) << message;
  EXPECT_GT(message.size(), std::string("compiling fragment shader self_test.frag: ").size()) << "no driver log";
}

TEST(Shaders, MissingFileIsNotFound) {
  Status status = SharedGpuWorker().Run({}, []() -> Status {
    return BuildProgram(CoreShaderFiles, {{GL_VERTEX_SHADER, "no_such_shader.vert"}}).status();
  });
  EXPECT_EQ(status.code(), absl::StatusCode::kNotFound) << status;
}

// --- The program layer ------------------------------------------------------

const std::vector<ShaderSource> kSelfTestSources = {{GL_VERTEX_SHADER, "self_test.vert"},
                                                    {GL_FRAGMENT_SHADER, "self_test.frag"}};

TEST(ProgramCache, BuildsEachVariantOncePerContext) {
  const GlProgram* first = nullptr;
  const GlProgram* again = nullptr;
  const GlProgram* variant = nullptr;
  Status status = SharedGpuWorker().Run({}, [&]() -> Status {
    VISQ_ASSIGN_OR_RETURN(first, CachedProgram(CoreShaderFiles, kSelfTestSources));
    VISQ_ASSIGN_OR_RETURN(again, CachedProgram(CoreShaderFiles, kSelfTestSources));
    VISQ_ASSIGN_OR_RETURN(variant, CachedProgram(CoreShaderFiles, kSelfTestSources, {{"UNUSED_VARIANT", "1"}}));
    return absl::OkStatus();
  });
  ASSERT_TRUE(status.ok()) << status;
  EXPECT_EQ(first, again);
  EXPECT_NE(first, variant);
  EXPECT_EQ(first->name(), "self_test.vert+self_test.frag");
  EXPECT_GE(first->Location("u_pattern").value_or(-1), 0);
  EXPECT_FALSE(first->Location("u_patern").has_value()) << "declared by no shader";
}

TEST(ProgramCache, IsOnlyReachableOnTheGlThread) {
  StatusOr<const GlProgram*> off_thread = CachedProgram(CoreShaderFiles, kSelfTestSources);
  EXPECT_EQ(off_thread.status().code(), absl::StatusCode::kInternal);
}

// A program's uniforms are typed members located once: a name that no
// shader declares fails the program's first use, naming it, with GPU
// debugging on or off; a declared one sets its value with one call.
struct SelfTestUniforms {
  explicit SelfTestUniforms(UniformLocator& at) : pattern(at.Find<unsigned>("u_pattern")) {}
  Uniform<unsigned> pattern;
};
struct MisspeltUniforms {
  explicit MisspeltUniforms(UniformLocator& at) : pattern(at.Find<unsigned>("u_patern")) {}
  Uniform<unsigned> pattern;
};

TEST(ProgramCache, TypedUniformsAreLocatedOnceAndAMisspeltOneFailsTheFirstUse) {
  Status typed = SharedGpuWorker().Run({}, [&]() -> Status {
    VISQ_ASSIGN_OR_RETURN(const TypedProgram<SelfTestUniforms>* program,
                          CachedProgram<SelfTestUniforms>(CoreShaderFiles, kSelfTestSources));
    VISQ_ASSIGN_OR_RETURN(const TypedProgram<SelfTestUniforms>* again,
                          CachedProgram<SelfTestUniforms>(CoreShaderFiles, kSelfTestSources));
    EXPECT_EQ(program, again) << "located once per program";
    EXPECT_GE(program->uniforms.pattern.location(), 0);
    program->uniforms.pattern.Set(5u);
    GLuint value = 0;
    glGetUniformuiv(program->id(), program->uniforms.pattern.location(), &value);
    EXPECT_EQ(value, 5u);
    return CollectGlErrors("setting a typed uniform");
  });
  EXPECT_TRUE(typed.ok()) << typed;
  Status status = SharedGpuWorker().Run({}, [&]() -> Status {
    return CachedProgram<MisspeltUniforms>(CoreShaderFiles, kSelfTestSources).status();
  });
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal) << status;
  EXPECT_NE(std::string(status.message()).find("u_patern"), std::string::npos) << status;
  EXPECT_NE(std::string(status.message()).find("self_test.frag"), std::string::npos) << status;
  Status next = SharedGpuWorker().Run({}, [] { return CollectGlErrors("after the misspelling"); });
  EXPECT_TRUE(next.ok()) << next;
}

// After a GPU reset the cache starts empty: the new context builds its own
// programs (the old ids mean nothing there).
TEST(ProgramCache, ANewContextBuildsItsOwnPrograms) {
  GpuOptions options;
  options.lose_context_at_job = 2;
  auto worker = GpuWorker::Start(options);
  ASSERT_TRUE(worker.ok()) << worker.status();
  GLuint before = 0;
  ASSERT_TRUE((*worker)->Run({}, [&]() -> Status {  // job 1
    VISQ_ASSIGN_OR_RETURN(const GlProgram* program, CachedProgram(CoreShaderFiles, kSelfTestSources));
    before = program->id();
    return absl::OkStatus();
  }).ok());
  EXPECT_FALSE((*worker)->Run({}, [] { return absl::OkStatus(); }).ok());  // job 2: the reset
  Status after = (*worker)->Run({}, [&]() -> Status {
    EXPECT_FALSE(glIsProgram(before));
    VISQ_ASSIGN_OR_RETURN(const GlProgram* program, CachedProgram(CoreShaderFiles, kSelfTestSources));
    EXPECT_TRUE(glIsProgram(program->id()));
    return absl::OkStatus();
  });
  EXPECT_TRUE(after.ok()) << after;
  EXPECT_TRUE(RunSelfTest(**worker).ok());
}

// --- The GL thread's queue -------------------------------------------------

TEST(GpuWorkerQueue, JobsRunOnOneThreadThatIsNotTheCaller) {
  std::thread::id first, second;
  ASSERT_TRUE(SharedGpuWorker().Run({}, [&] { first = std::this_thread::get_id(); return absl::OkStatus(); }).ok());
  ASSERT_TRUE(SharedGpuWorker().Run({}, [&] { second = std::this_thread::get_id(); return absl::OkStatus(); }).ok());
  EXPECT_EQ(first, second);
  EXPECT_NE(first, std::this_thread::get_id());
}

TEST(GpuWorkerQueue, ExpiredDeadlineIsNotRun) {
  bool ran = false;
  JobOptions options;
  options.stop.deadline = std::chrono::steady_clock::now() - std::chrono::milliseconds(1);
  Status status = SharedGpuWorker().Run(options, [&] { ran = true; return absl::OkStatus(); });
  EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
  EXPECT_FALSE(ran);
}

TEST(GpuWorkerQueue, CancelledJobIsNotRun) {
  std::atomic<bool> cancelled{true};
  bool ran = false;
  JobOptions options;
  options.stop.cancelled = &cancelled;
  Status status = SharedGpuWorker().Run(options, [&] { ran = true; return absl::OkStatus(); });
  EXPECT_EQ(status.code(), absl::StatusCode::kCancelled) << status;
  EXPECT_FALSE(ran);
}

TEST(GpuWorkerQueue, GlErrorFailsThatJobOnlyAndTheNextJobWorks) {
  Status failing = SharedGpuWorker().Run({}, [] {
    glBindBuffer(GL_ARRAY_BUFFER, 0xFFFFFFu);  // not a buffer name: GL_INVALID_OPERATION
    return absl::OkStatus();
  });
  EXPECT_EQ(failing.code(), absl::StatusCode::kInternal) << failing;
  EXPECT_NE(std::string(failing.message()).find("GL_INVALID_OPERATION"), std::string::npos) << failing;
  Status next = SharedGpuWorker().Run({}, [] { return CollectGlErrors("after a failed job"); });
  EXPECT_TRUE(next.ok()) << next;
}

// A GPU reset, injected at the worker's third job (the recovery path is the
// real one: the context is destroyed and a new one made).
TEST(GpuWorkerQueue, LostContextFailsThatJobAndTheNextJobGetsANewContext) {
  GpuOptions options;
  options.lose_context_at_job = 3;
  auto worker = GpuWorker::Start(options);
  ASSERT_TRUE(worker.ok()) << worker.status();
  EXPECT_EQ((*worker)->context_generation(), 1u);
  ASSERT_TRUE(RunSelfTest(**worker).ok());  // job 1

  // Job 2 makes a buffer that outlives the context it was made in.
  GlBuffer survivor(NoCreate);
  GLuint survivor_id = 0;
  ASSERT_TRUE((*worker)->Run({}, [&] {
    survivor = GlBuffer();
    survivor_id = survivor.id();
    glNamedBufferStorage(survivor.id(), 16, nullptr, 0);
    return absl::OkStatus();
  }).ok());

  Status lost = (*worker)->Run({}, [] { return absl::OkStatus(); });  // job 3
  EXPECT_EQ(lost.code(), absl::StatusCode::kInternal) << lost;
  EXPECT_NE(std::string(lost.message()).find("context lost"), std::string::npos) << lost;
  EXPECT_EQ((*worker)->context_generation(), 2u);
  EXPECT_EQ((*worker)->contexts_lost(), 1u);

  // The new context draws, and the old buffer's name means nothing in it.
  EXPECT_TRUE(RunSelfTest(**worker).ok());
  Status fresh = (*worker)->Run({}, [&] {
    EXPECT_FALSE(glIsBuffer(survivor_id));
    GlBuffer reused;  // very likely the same name as the survivor's
    glNamedBufferStorage(reused.id(), 16, nullptr, 0);
    const GLuint reused_id = reused.id();
    survivor = GlBuffer(NoCreate);  // the stale owner must not delete `reused`
    EXPECT_TRUE(glIsBuffer(reused_id));
    return absl::OkStatus();
  });
  EXPECT_TRUE(fresh.ok()) << fresh;
}

TEST(GpuSceneUpload, SceneFromALostContextIsNotCurrentAndSaysSo) {
  GpuOptions options;
  options.lose_context_at_job = 2;
  auto worker = GpuWorker::Start(options);
  ASSERT_TRUE(worker.ok()) << worker.status();
  const Scene scene = MakeCornellBox();
  auto uploaded = GpuScene::Upload(**worker, scene);  // job 1
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  EXPECT_TRUE((*uploaded)->IsCurrent());
  EXPECT_EQ((*worker)->Run({}, [] { return absl::OkStatus(); }).code(), absl::StatusCode::kInternal);  // job 2
  EXPECT_FALSE((*uploaded)->IsCurrent());
  Status stale = (*worker)->Run({}, [&]() -> Status { return (*uploaded)->CurrentResources().status(); });
  EXPECT_EQ(stale.code(), absl::StatusCode::kInternal) << stale;
  auto again = GpuScene::Upload(**worker, scene);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE((*again)->IsCurrent());
}

// Holds the GL thread busy so that jobs queue up behind it, then records the
// order in which they run.
class QueueRecorder {
 public:
  explicit QueueRecorder(GpuWorker& worker) : worker_(worker) {
    blocker_ = std::async(std::launch::async, [this] {
      return worker_.Run({}, [this] {
        started_ = true;
        released_.wait();
        return absl::OkStatus();
      });
    });
    while (!started_) std::this_thread::yield();
  }

  // Queues a job tagged `tag` and returns once it is in the queue.
  void Queue(int priority, int tag) {
    const size_t depth = worker_.queue_depth();
    jobs_.push_back(std::async(std::launch::async, [this, priority, tag] {
      JobOptions options;
      options.priority = priority;
      return worker_.Run(options, [this, tag] {
        std::lock_guard lock(mutex_);
        order_.push_back(tag);
        return absl::OkStatus();
      });
    }));
    while (worker_.queue_depth() < depth + 1) std::this_thread::yield();
  }

  // Lets the GL thread go; the tags in the order their jobs ran.
  std::vector<int> Release() {
    release_.set_value();
    EXPECT_TRUE(blocker_.get().ok());
    for (auto& job : jobs_) EXPECT_TRUE(job.get().ok());
    return order_;
  }

 private:
  GpuWorker& worker_;
  std::promise<void> release_;
  std::shared_future<void> released_ = release_.get_future().share();
  std::atomic<bool> started_{false};
  std::future<Status> blocker_;
  std::vector<std::future<Status>> jobs_;
  std::mutex mutex_;
  std::vector<int> order_;
};

TEST(GpuWorkerQueue, InteractiveJobsOvertakeQueuedBatchJobs) {
  QueueRecorder queue(SharedGpuWorker());
  queue.Queue(kBatch, 1);
  queue.Queue(kInteractive, 2);
  EXPECT_EQ(queue.Release(), (std::vector<int>{2, 1}));
}

TEST(GpuWorkerQueue, AWaitingBatchJobRunsAfterEightOvertakes) {
  QueueRecorder queue(SharedGpuWorker());
  queue.Queue(kBatch, 0);  // one step of a bake
  for (int tag = 1; tag <= 12; ++tag) queue.Queue(kInteractive, tag);
  // Eight small jobs overtake the batch step, then it runs, then the rest.
  EXPECT_EQ(queue.Release(), (std::vector<int>{1, 2, 3, 4, 5, 6, 7, 8, 0, 9, 10, 11, 12}));
}

TEST(GpuWorkerQueue, TimingReportsQueueAndRunTime) {
  JobTiming timing;
  Status status = SharedGpuWorker().Run({}, [] {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    return absl::OkStatus();
  }, &timing);
  ASSERT_TRUE(status.ok());
  EXPECT_GE(timing.run_ms, 19.0);
  EXPECT_GE(timing.queue_ms, 0.0);
}

// --- Scene upload ----------------------------------------------------------

TEST(GpuSceneUpload, UploadsRelativeToTheBoundsCenter) {
  Scene scene = MakeCornellBox();
  // Far from the origin: the anchor absorbs the offset.
  for (auto& p : scene.positions) p += glm::dvec3(1e6, -2e6, 3e6);
  UpdateBounds(scene);
  auto gpu_scene = GpuScene::Upload(SharedGpuWorker(), scene);
  ASSERT_TRUE(gpu_scene.ok()) << gpu_scene.status();
  EXPECT_EQ((*gpu_scene)->triangle_count(), scene.TriangleCount());
  // 3 float32 corners, a material index and 3 element indices (the cluster
  // order) a triangle; the identity record and one run's record and draw.
  EXPECT_EQ((*gpu_scene)->gpu_bytes(),
            scene.TriangleCount() * (3 * sizeof(glm::vec3) + 4 * sizeof(uint32_t)) + 2 * 64 + 16);
  EXPECT_EQ((*gpu_scene)->gpu_bytes(), GpuScene::EstimateBytes(scene));
  EXPECT_EQ((*gpu_scene)->held_triangle_count(), scene.TriangleCount());
  EXPECT_EQ((*gpu_scene)->instance_count(), 0u);
  EXPECT_NEAR((*gpu_scene)->anchor().x, 1e6, 1.0);
  EXPECT_NEAR((*gpu_scene)->anchor().y, -2e6 + 1.0, 1.0);
}

}  // namespace
}  // namespace visq::gpu
