// What every `visq` subcommand shares: the global flags, the client they
// make, argument parsing, failure messages and the output writers (JSON,
// PNG, .npy). Each subcommand group registers itself with one Add*Commands
// function; main.cpp only calls them and parses.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <google/protobuf/message.h>

#include "common/status.h"  // the tool stands on lib/: fmt prints Status messages
#include "visq_client.h"

namespace visq::cli {

// Flags accepted before or after the subcommand.
struct GlobalFlags {
  std::string server = "127.0.0.1:50051";
  bool json = false;
  double timeout_s = 0;  // 0: 60 s for single calls, none for streams and bakes
  std::string token_file;
  std::string tls_ca, tls_cert, tls_key;
  bool progress = false;  // report progress on stderr even when it is not a terminal
};

// Runs `call` (an RPC); while it lasts more than a second, says on stderr
// how long the server has been working (rewritten in place on a terminal,
// a line a second with --progress otherwise). Once the answer's stream
// tells how far it is (Progress), that is a bar with the time left at the
// rate so far, as the bake's: on a terminal redrawn as each part arrives,
// otherwise in the line of each second and a last line when all is there.
class Waiting {
 public:
  Waiting(const GlobalFlags& flags, std::string what);
  ~Waiting();
  // `done` of `total` `unit` (texels, rows, points) have arrived. Any thread.
  void Progress(uint64_t done, uint64_t total, const char* unit);
  // For the client's StreamProgressCallback.
  client::StreamProgressCallback Callback(const char* unit) {
    return [this, unit](uint64_t done, uint64_t total) { Progress(done, total, unit); };
  }
  Waiting(const Waiting&) = delete;
  Waiting& operator=(const Waiting&) = delete;

 private:
  struct State;
  std::unique_ptr<State> state_;
};

template <typename Call>
auto WhileWaiting(const GlobalFlags& flags, const std::string& what, Call&& call) {
  Waiting waiting(flags, what);
  return call();
}

// The default deadline of a call that is not a stream.
inline constexpr double kDefaultTimeoutS = 60;

// The parsed command line and the exit code the chosen subcommand sets.
struct Cli {
  CLI::App app{"visq: visibility queries against a visq-server"};
  GlobalFlags flags;
  int exit_code = 0;
};

void AddGlobalFlags(Cli& cli);
void AddSceneCommands(Cli& cli);       // health, load, list, info, unload, stats (--fleet: fleet.h)
void AddSamplingCommands(Cli& cli);    // hidden-map, patch-visibility
void AddLightCommands(Cli& cli);       // light-visibility
void AddVoxelCommands(Cli& cli);       // voxelize, transmittance, volumetric
void AddObscuranceCommands(Cli& cli);  // obscurance, move, obscurance-update, obscurance-preview

// Prints "visq: CODE: message" (with a hint for DEADLINE_EXCEEDED and
// UNAVAILABLE) and returns the exit code: 2 for INVALID_ARGUMENT, else 1.
int Fail(const Status& status, const GlobalFlags& flags);

// INVALID_ARGUMENT naming the flag when --server or --token-file is unusable.
[[nodiscard]] Status ValidateGlobalFlags(const GlobalFlags& flags);
// A client for the flags; its init_status() says whether they were usable.
client::Client MakeClient(const GlobalFlags& flags);

// Registers `command`'s work: run(options, cli) after the global flags are
// checked; an error it returns is printed and sets the exit code.
template <typename Options, typename Run>
void OnRun(CLI::App* command, Cli& cli, std::shared_ptr<Options> options, Run run) {
  command->callback([&cli, options, run] {
    Status status = ValidateGlobalFlags(cli.flags);
    if (status.ok()) status = run(*options, cli);
    if (!status.ok()) cli.exit_code = Fail(status, cli.flags);
  });
}


// The message as JSON: field names as in the proto, zero values included,
// 64-bit integers as numbers (not proto3 JSON's strings).
std::string ToJson(const google::protobuf::Message& message);

std::string Bytes(uint64_t bytes);
void PrintScene(const v1::SceneInfo& scene, bool nodes);

// "x,y,z" -> Vec3; false if malformed or not finite.
bool ParseVec3(const std::string& text, v1::Vec3* out);
// "ox,oy,oz;ux,uy,uz;vx,vy,vz" -> Patch.
bool ParsePatch(const std::string& text, v1::Patch* out);

// An 8-bit PNG of values in [0, 1] (1 or 3 channels per pixel), given with
// the image's last row first (a receiver's v = 0 edge at the bottom).
[[nodiscard]] Status WritePng(const std::string& path, uint32_t width, uint32_t height, int channels,
                              const std::vector<float>& values);
// The same for rows that arrive top first (the image RPCs), each value
// times `scale`.
[[nodiscard]] Status WriteTopFirstPng(const std::string& path, uint32_t width, uint32_t height,
                                      const std::vector<float>& rgb, float scale);
// A float OpenEXR image of 1 (Y) or 3 (R, G, B) channels, given with its
// last row first like WritePng (`top_first`: with its first row on top, like
// WriteTopFirstPng); linear values, as they are.
[[nodiscard]] Status WriteExr(const std::string& path, uint32_t width, uint32_t height, int channels,
                              const std::vector<float>& values, bool top_first = false);
// A float32 .npy of the given shape (C order), for numpy.load.
[[nodiscard]] Status WriteNpy(const std::string& path, const std::vector<uint64_t>& shape,
                              const std::vector<float>& values);
// Flips rows: [y][...] -> [height - 1 - y][...], `row` values per row.
std::vector<float> FlipRows(const std::vector<float>& values, uint32_t height, size_t row);

// The pinhole camera flags of the image subcommands (volumetric,
// obscurance-preview).
struct CameraFlags {
  std::string position, forward, up;
  double fov = 60;
  uint32_t width = 320, height = 240;
};
void AddCameraFlags(CLI::App* command, CameraFlags& camera);

template <typename Request>
Status FillCamera(const CameraFlags& camera, Request* request) {
  if (!ParseVec3(camera.position, request->mutable_camera_position()) ||
      !ParseVec3(camera.forward, request->mutable_camera_forward()) ||
      (!camera.up.empty() && !ParseVec3(camera.up, request->mutable_camera_up())))
    return absl::InvalidArgumentError("--camera-position, --camera-forward, --camera-up: expected 'x,y,z'");
  request->set_width(camera.width);
  request->set_height(camera.height);
  request->set_vertical_fov_deg(camera.fov);
  return absl::OkStatus();
}

// Ask by error instead of by count (--max-error, --time-budget-ms).
struct TargetFlags {
  double max_error = 0.0;
  double confidence = 0.0;
  double time_budget_ms = 0.0;
  std::string guarantee;  // "rigorous", "estimate" or empty (the server's default)
  bool set() const { return max_error > 0.0 || time_budget_ms > 0.0; }
  void Fill(v1::AccuracyTarget* out) const;
};
void AddTargetFlags(CLI::App* command, TargetFlags& target);
// "estimate +-0.0012 ..." where the answer states an estimate beside its
// bound, and "chosen: raycast {samples: 2048}, predicted 12.3 ms (of 17
// plans)" for a target's answer.
void PrintChosenPlan(const v1::Accuracy& accuracy);
// "time: queue ... ms, compute ..., transfer ..., total ..." from the answer's timing.
void PrintTiming(const v1::Timing& timing);
// "wrote FILE" for each image file asked for (empty paths: not asked).
void PrintWritten(const std::string& png, const std::string& npy, const std::string& exr);

// An option whose value must be one of `allowed`; a wrong one is refused
// naming them.
CLI::Option* AddChoice(CLI::App* command, const std::string& name, std::string& value,
                       const std::vector<std::string>& allowed, const std::string& help);

}  // namespace visq::cli
