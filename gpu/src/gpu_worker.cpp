#include "visq/gpu/gpu_worker.h"

#include <algorithm>
#include <condition_variable>
#include <deque>
#include <future>
#include <map>
#include <mutex>
#include <optional>
#include <thread>

#include <epoxy/gl.h>
#include <spdlog/spdlog.h>

#include "egl_context.h"
#include "gl_check.h"
#include "gl_object.h"
#include "shader_program.h"

namespace visq::gpu {

namespace {
// Set by the worker on its thread; GlObject reads it (gl_object.h).
thread_local uint64_t current_generation = 0;
}  // namespace

uint64_t CurrentContextGeneration() { return current_generation; }

namespace {

void GLAPIENTRY LogDebugMessage(GLenum, GLenum type, GLuint id, GLenum severity, GLsizei length,
                                const GLchar* message, const void*) {
  const std::string_view text(message, length > 0 ? static_cast<size_t>(length) : std::strlen(message));
  if (severity == GL_DEBUG_SEVERITY_HIGH || type == GL_DEBUG_TYPE_ERROR)
    spdlog::error("GL [{}]: {}", id, text);
  else if (severity == GL_DEBUG_SEVERITY_MEDIUM)
    spdlog::warn("GL [{}]: {}", id, text);
  else
    spdlog::debug("GL [{}]: {}", id, text);
}

struct Job {
  int priority = 0;
  uint64_t sequence = 0;
  JobOptions options;
  SteadyTime submitted;
  std::function<Status()> body;
  std::promise<Status> done;  // unset for fire-and-forget jobs
  bool wants_result = false;
  JobTiming* timing = nullptr;
};

// Lower priorities run first, but not forever: after this many jobs have
// overtaken a waiting job of a later priority, the longest-waiting job runs
// (a bake keeps progressing, one step at a time, under a flood of small
// queries, which still get 8 of every 9 turns).
constexpr int kOvertakesBeforeTheOldestRuns = 8;

// After a job, when only work of a later priority waits (a bake's next
// piece after a small map), the GL thread waits this long for the next job
// of the finished one's priority before it starts the later work. A client
// sending its maps one after another is between two of them for about a
// millisecond; without the wait, each of its maps queued behind a whole
// bake piece: 22.6 maps/s with a Sponza bake running against 997 alone
// (visq_bench_small_under_bake, llvmpipe).
constexpr std::chrono::microseconds kWaitForTheSameCaller{3000};
// The earlier priority keeps the GL thread this way only as long as the
// later work's last job ran (at most kLongestHeldTurn): the two share it
// about equally, and a bake keeps progressing at half its pace or better
// under a stream of small queries.
constexpr std::chrono::milliseconds kLongestHeldTurn{100};

// How often a call waiting in the queue looks at its cancellation and deadline.
constexpr std::chrono::milliseconds kQueuedStopCheck{20};

// A job longer than this is logged (debug): jobs are sized to a few tens of
// ms, and one over this holds other calls and a stop well past that.
constexpr double kLongJobMs = 250.0;

}  // namespace

class GpuWorker::Impl {
 public:
  explicit Impl(GpuOptions options) : options_(std::move(options)) {}

  Status Start() {
    std::promise<Status> ready;
    auto ready_future = ready.get_future();
    thread_ = std::thread([this, &ready] { Loop(ready); });
    Status status = ready_future.get();
    if (!status.ok()) thread_.join();
    return status;
  }

  ~Impl() {
    if (!thread_.joinable()) return;
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    wake_.notify_all();
    thread_.join();
  }

  Status Run(const JobOptions& options, std::function<Status()> body, JobTiming* timing) {
    auto job = std::make_unique<Job>();
    job->options = options;
    job->priority = options.priority;
    job->body = std::move(body);
    job->wants_result = true;
    job->timing = timing;
    auto result = job->done.get_future();
    const SteadyTime submitted = std::chrono::steady_clock::now();
    const uint64_t sequence = Enqueue(std::move(job));
    if (!options.stop.CanStop()) return result.get();
    // A job still queued behind other calls' jobs is answered as soon as its
    // call stops wanting it, not when the GL thread reaches it.
    while (result.wait_for(kQueuedStopCheck) != std::future_status::ready) {
      Status stopped = options.stop.Check("queued for the GPU");
      if (stopped.ok()) continue;
      if (!Withdraw(options.priority, sequence)) continue;  // running: it asks its stop token itself
      if (timing) {
        timing->queue_ms = MillisecondsSince(submitted);
        timing->run_ms = 0.0;
      }
      return stopped;
    }
    return result.get();
  }

  void Post(std::function<void()> body) {
    auto job = std::make_unique<Job>();
    job->priority = -1;  // cleanup first: frees memory for what follows
    job->body = [body = std::move(body)] { body(); return absl::OkStatus(); };
    Enqueue(std::move(job));
  }

  size_t depth() const {
    std::lock_guard lock(mutex_);
    size_t total = 0;
    for (const auto& [priority, jobs] : queues_) total += jobs.size();
    return total;
  }

  DeviceInfo info;

 private:
  uint64_t Enqueue(std::unique_ptr<Job> job) {
    uint64_t sequence = 0;
    {
      std::lock_guard lock(mutex_);
      sequence = job->sequence = next_sequence_++;
      job->submitted = std::chrono::steady_clock::now();
      queues_[job->priority].push_back(std::move(job));
    }
    wake_.notify_one();
    return sequence;
  }

  // Takes a job that has not started out of the queue; false when the GL
  // thread has taken it already.
  bool Withdraw(int priority, uint64_t sequence) {
    std::lock_guard lock(mutex_);
    auto level = queues_.find(priority);
    if (level == queues_.end()) return false;
    auto& jobs = level->second;
    auto it = std::find_if(jobs.begin(), jobs.end(), [&](const auto& job) { return job->sequence == sequence; });
    if (it == jobs.end()) return false;
    jobs.erase(it);
    if (jobs.empty()) queues_.erase(level);
    return true;
  }

  // Makes a context current on this thread (the first, or a replacement
  // after a loss) and starts a new generation.
  Status MakeContext() {
    // The old context's programs go with it (deleted while it is current).
    SetCurrentProgramCache(nullptr);
    programs_.reset();
    context_ = EglContext();  // the old one, if any, is destroyed first
    StatusOr<EglContext> context = EglContext::CreateCurrent(options_);
    if (!context.ok()) return context.status();
    context_ = *std::move(context);
    current_generation = generation_.fetch_add(1) + 1;
    programs_ = std::make_unique<ProgramCache>();
    SetCurrentProgramCache(programs_.get());
    SetGlChecksEnabled(options_.debug);
    if (options_.debug && epoxy_has_gl_extension("GL_KHR_debug")) {
      glEnable(GL_DEBUG_OUTPUT);
      glEnable(GL_DEBUG_OUTPUT_SYNCHRONOUS);
      glDebugMessageCallback(LogDebugMessage, nullptr);
    }
    return absl::OkStatus();
  }

  void Loop(std::promise<Status>& ready) {
    // The context is created on this thread and never leaves it.
    if (Status made = MakeContext(); !made.ok()) {
      ready.set_value(made);
      return;
    }
    info = context_.info();
    ready.set_value(absl::OkStatus());

    for (;;) {
      std::unique_ptr<Job> job;
      {
        std::unique_lock lock(mutex_);
        wake_.wait(lock, [&] { return stopping_ || !queues_.empty(); });
        if (queues_.empty()) break;  // stopping, and everything queued has run
        WaitForTheSameCallerLocked(lock);
        if (queues_.empty()) continue;  // what waited was withdrawn (its call stopped)
        job = PopNext();
      }
      const int priority = job->priority;
      const SteadyTime start = std::chrono::steady_clock::now();
      Execute(*job);
      AccountTurn(priority, start, std::chrono::steady_clock::now());
    }
    // Jobs are done; GL objects they owned were released by Post()ed jobs.
    SetCurrentProgramCache(nullptr);
    programs_.reset();
    context_ = EglContext();
  }

  void Execute(Job& job) {
    const SteadyTime start = std::chrono::steady_clock::now();
    // A call that stopped wanting the job while it waited gets that answer.
    Status status = job.options.stop.Check("queued for the GPU");
    if (status.ok() && !context_usable_) {
      status = absl::InternalError(absl::StrCat("no GPU context: ", lost_reason_));
    } else if (status.ok()) {
      status = job.body();
      ResetPipelineState();
      if (const std::string reset = ContextLossDuringJob(); !reset.empty()) {
        status = absl::InternalError(absl::StrCat("GPU context lost during this job (", reset,
                                                  "); a new context serves the next request"));
        Recover(reset);
      } else {
        // Errors the job did not check are still its errors, not the next job's.
        Status gl_status = CollectGlErrors("GPU job");
        if (status.ok() && !gl_status.ok()) status = gl_status;
      }
    }
    const double run_ms = MillisecondsBetween(start, std::chrono::steady_clock::now());
    if (job.timing) {
      job.timing->queue_ms = MillisecondsBetween(job.submitted, start);
      job.timing->run_ms = run_ms;
    }
    // Long jobs hold every other call's GL work and a stop: visible at debug
    // level, where the call's own lines name it.
    if (run_ms > kLongJobMs) spdlog::debug("a GL job held the GL thread for {:.1f} ms", run_ms);
    if (job.wants_result) job.done.set_value(std::move(status));
    else if (!status.ok()) spdlog::warn("GPU background job failed: {}", status.message());
  }

  // Every job starts from the same pipeline state, whatever the last one
  // left (a job that stops between draws returns before its own clean-up):
  // the switches jobs turn on are off, nothing is bound.
  static void ResetPipelineState() {
    for (GLenum capability : {GL_COLOR_LOGIC_OP, GL_BLEND, GL_DEPTH_TEST, GL_SCISSOR_TEST, GL_CULL_FACE})
      glDisable(capability);
    glBlendEquation(GL_FUNC_ADD);
    glLogicOp(GL_COPY);
    glDepthFunc(GL_LESS);
    glDepthMask(GL_TRUE);
    glFrontFace(GL_CCW);
    glBindFramebuffer(GL_FRAMEBUFFER, 0);
    glUseProgram(0);
    glBindVertexArray(0);
    for (GLuint unit = 0; unit < 4; ++unit) glBindTextureUnit(unit, 0);
  }

  // Whether the GL thread holds its turn for the priority of the job that
  // just ran: only later work waits, and that priority has held the thread
  // less, since the later work last ran, than the later work's last job
  // took (kWaitForTheSameCaller). Queue lock held; waits on it.
  void WaitForTheSameCallerLocked(std::unique_lock<std::mutex>& lock) {
    if (stopping_ || !last_priority_ || queues_.begin()->first <= *last_priority_) return;
    const SteadyTime now = std::chrono::steady_clock::now();
    if (now - last_end_ > kWaitForTheSameCaller ||
        now - turn_start_ >= std::min(later_turn_, SteadyTime::duration(kLongestHeldTurn)))
      return;
    const int priority = *last_priority_;
    wake_.wait_until(lock, last_end_ + kWaitForTheSameCaller,
                     [&] { return stopping_ || queues_.empty() || queues_.begin()->first <= priority; });
  }

  // What WaitForTheSameCallerLocked weighs: when the current priority's
  // turn started, when its last job ended, and how long the later work's
  // last job ran.
  void AccountTurn(int priority, SteadyTime start, SteadyTime end) {
    std::lock_guard lock(mutex_);
    if (!last_priority_ || priority != *last_priority_) {
      if (last_priority_ && priority < *last_priority_) later_turn_ = last_end_ - turn_start_;
      turn_start_ = start;
    }
    last_priority_ = priority;
    last_end_ = end;
  }

  // The front of the lowest priority, unless it has overtaken waiting work
  // of later priorities too often (then the oldest front). Queue lock held.
  std::unique_ptr<Job> PopNext() {
    auto chosen = queues_.begin();
    if (queues_.size() > 1) {
      if (overtakes_ >= kOvertakesBeforeTheOldestRuns) {
        for (auto level = queues_.begin(); level != queues_.end(); ++level)
          if (level->second.front()->sequence < chosen->second.front()->sequence) chosen = level;
        overtakes_ = 0;
      } else {
        ++overtakes_;
      }
    } else {
      overtakes_ = 0;
    }
    std::unique_ptr<Job> job = std::move(chosen->second.front());
    chosen->second.pop_front();
    if (chosen->second.empty()) queues_.erase(chosen);
    return job;
  }

  // Why the context is gone, or "" if it is fine. GL 4.5 core reports
  // resets through glGetGraphicsResetStatus (for contexts created with a
  // reset notification strategy; others report GL_NO_ERROR).
  std::string ContextLossDuringJob() {
    ++jobs_run_;
    if (options_.lose_context_at_job != 0 && jobs_run_ == options_.lose_context_at_job)
      return "simulated reset (lose_context_at_job)";
    switch (glGetGraphicsResetStatus()) {
      case GL_NO_ERROR: return "";
      case GL_GUILTY_CONTEXT_RESET: return "GL_GUILTY_CONTEXT_RESET";
      case GL_INNOCENT_CONTEXT_RESET: return "GL_INNOCENT_CONTEXT_RESET";
      default: return "GL_UNKNOWN_CONTEXT_RESET";
    }
  }

  void Recover(const std::string& reason) {
    lost_.fetch_add(1);
    spdlog::error("GPU context lost ({}); making a new one", reason);
    if (Status made = MakeContext(); !made.ok()) {
      context_usable_ = false;
      lost_reason_ = absl::StrCat("lost (", reason, ") and not recreated: ", made.message());
      spdlog::error("GPU: {}", lost_reason_);
      return;
    }
    spdlog::info("GPU context generation {} ready", current_generation);
  }

 public:
  uint64_t generation() const { return generation_.load(); }
  uint64_t lost() const { return lost_.load(); }

 private:
  GpuOptions options_;
  EglContext context_;
  std::unique_ptr<ProgramCache> programs_;  // the current context's
  std::atomic<uint64_t> generation_{0};
  std::atomic<uint64_t> lost_{0};
  uint64_t jobs_run_ = 0;
  bool context_usable_ = true;
  std::string lost_reason_;
  std::thread thread_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  std::map<int, std::deque<std::unique_ptr<Job>>> queues_;  // by priority, each FIFO
  int overtakes_ = 0;
  std::optional<int> last_priority_;  // of the job that ran last (AccountTurn)
  SteadyTime turn_start_{}, last_end_{};
  SteadyTime::duration later_turn_{};
  uint64_t next_sequence_ = 0;
  bool stopping_ = false;
};

GpuWorker::GpuWorker(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
GpuWorker::~GpuWorker() = default;

StatusOr<std::unique_ptr<GpuWorker>> GpuWorker::Start(const GpuOptions& options) {
  auto impl = std::make_unique<Impl>(options);
  VISQ_RETURN_IF_ERROR(impl->Start());
  return std::unique_ptr<GpuWorker>(new GpuWorker(std::move(impl)));
}

const DeviceInfo& GpuWorker::device() const { return impl_->info; }
size_t GpuWorker::queue_depth() const { return impl_->depth(); }
uint64_t GpuWorker::context_generation() const { return impl_->generation(); }
uint64_t GpuWorker::contexts_lost() const { return impl_->lost(); }

Status GpuWorker::Run(const JobOptions& options, std::function<Status()> body, JobTiming* timing) {
  return impl_->Run(options, std::move(body), timing);
}

void GpuWorker::Post(std::function<void()> body) { impl_->Post(std::move(body)); }

}  // namespace visq::gpu
