#include "cli_common.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <fstream>
#include <mutex>
#include <thread>

#include <fmt/format.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/util/json_util.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfOutputFile.h>
#include <nlohmann/json.hpp>
#include <stb_image_write.h>

namespace visq::cli {

void AddGlobalFlags(Cli& cli) {
  GlobalFlags& flags = cli.flags;
  CLI::App& app = cli.app;
  // On the top-level app, with fallthrough: `visq --server X list` and
  // `visq list --server X` both work.
  app.fallthrough();
  app.add_option("--server", flags.server, "visq-server address HOST[:PORT] (port default 50051)")
      ->envname("VISQ_SERVER")
      ->capture_default_str();
  app.add_flag("--json", flags.json, "Print the response as JSON");
  app.add_option("--timeout", flags.timeout_s,
                 "Deadline in seconds (default: 60 for single calls, none for streams, bakes and uploads)")
      ->check(CLI::PositiveNumber);
  app.add_option("--token-file", flags.token_file, "File whose first line is the bearer token")
      ->envname("VISQ_AUTH_TOKEN_FILE");
  app.add_option("--tls-ca", flags.tls_ca, "PEM roots for a TLS server")->envname("VISQ_TLS_CA");
  app.add_option("--tls-cert", flags.tls_cert, "PEM client certificate (mutual TLS)")->envname("VISQ_TLS_CLIENT_CERT");
  app.add_flag("--progress", flags.progress,
               "Report progress on stderr even when it is not a terminal (bakes, light batches, long calls)");
  app.add_option("--tls-key", flags.tls_key, "PEM client key (mutual TLS)")->envname("VISQ_TLS_CLIENT_KEY");
}

Status ValidateGlobalFlags(const GlobalFlags& flags) {
  if (auto address = client::WithDefaultPort(flags.server); !address.ok())
    return absl::InvalidArgumentError(fmt::format("--server: {}", address.status().message()));
  if (!flags.token_file.empty()) {
    std::ifstream in(flags.token_file);
    std::string token;
    if (!in) return absl::InvalidArgumentError(fmt::format("--token-file: cannot read {}", flags.token_file));
    std::getline(in, token);
    if (token.find_first_not_of(" \t\r\n") == std::string::npos)
      return absl::InvalidArgumentError(fmt::format("--token-file: {} holds no token", flags.token_file));
  }
  return absl::OkStatus();
}

struct Waiting::State {
  std::string what;
  bool terminal = false;
  std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
  std::mutex mutex;
  std::condition_variable done;
  bool finished = false;
  bool shown = false;       // something was printed (a terminal's line then ends with "\n")
  bool last_shown = false;  // the line with everything arrived was printed
  uint64_t parts_done = 0, parts_total = 0;
  const char* unit = "";
  std::chrono::steady_clock::time_point last_draw{};
  std::thread thread;

  double Seconds() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  }
  // One report: the bar once the stream told how far it is, the time worked
  // before. Mutex held.
  void Draw() {
    const double seconds = Seconds();
    std::string text;
    if (parts_total == 0) {
      text = fmt::format("{}: the server has worked {:.0f} s", what, std::floor(seconds));
    } else {
      const int width = 30;
      const int bar = static_cast<int>(int64_t{width} * std::min(parts_done, parts_total) / parts_total);
      text = fmt::format("{}: [{}{}] {}/{} {}, {:.1f} s", what, std::string(bar, '='), std::string(width - bar, ' '),
                         parts_done, parts_total, unit, seconds);
      // The time left at the rate so far; nothing until a part has come.
      if (parts_done > 0 && parts_done < parts_total)
        text += fmt::format(", ~{:.1f} s left", seconds * double(parts_total - parts_done) / double(parts_done));
      last_shown = parts_done >= parts_total;
    }
    if (terminal) fmt::print(stderr, "\r{} ", text);
    else fmt::print(stderr, "{}\n", text);
    std::fflush(stderr);
    shown = true;
    last_draw = std::chrono::steady_clock::now();
  }
};

Waiting::Waiting(const GlobalFlags& flags, std::string what) {
  const bool terminal = ::isatty(STDERR_FILENO) != 0;
  if (!terminal && !flags.progress) return;
  state_ = std::make_unique<State>();
  state_->what = std::move(what);
  state_->terminal = terminal;
  state_->thread = std::thread([state = state_.get()] {
    std::unique_lock lock(state->mutex);
    for (int seconds = 1;; ++seconds) {
      if (state->done.wait_until(lock, state->start + std::chrono::seconds(seconds), [&] { return state->finished; }))
        break;
      state->Draw();
    }
  });
}

void Waiting::Progress(uint64_t done, uint64_t total, const char* unit) {
  if (!state_) return;
  std::lock_guard lock(state_->mutex);
  state_->parts_done = done;
  state_->parts_total = total;
  state_->unit = unit;
  // Only a call past its first second reports at all (as the ticker), so a
  // quick one stays silent; then a terminal's bar follows each part (at
  // most 10 redraws a second), and a log gets the line of completion.
  if (state_->Seconds() < 1.0) return;
  const bool complete = total > 0 && done >= total;
  if (state_->terminal ? (complete || std::chrono::steady_clock::now() - state_->last_draw >
                                          std::chrono::milliseconds(100))
                       : complete && !state_->last_shown)
    state_->Draw();
}

Waiting::~Waiting() {
  if (!state_) return;
  {
    std::lock_guard lock(state_->mutex);
    state_->finished = true;
  }
  state_->done.notify_all();
  state_->thread.join();
  if (state_->shown && state_->terminal) fmt::print(stderr, "\n");
}

client::Client MakeClient(const GlobalFlags& flags) {
  client::ClientOptions options;
  options.address = flags.server;
  const bool given = flags.timeout_s > 0;
  options.deadline = std::chrono::milliseconds(static_cast<int64_t>((given ? flags.timeout_s : kDefaultTimeoutS) * 1000));
  options.stream_deadline = std::chrono::milliseconds(given ? static_cast<int64_t>(flags.timeout_s * 1000) : 0);
  options.tls_ca_file = flags.tls_ca;
  options.client_cert_file = flags.tls_cert;
  options.client_key_file = flags.tls_key;
  if (!flags.token_file.empty()) {
    std::ifstream in(flags.token_file);
    if (in) std::getline(in, options.auth_token);
    // Surrounding whitespace (a Windows line end) is no part of the token.
    const auto first = options.auth_token.find_first_not_of(" \t\r\n");
    const auto last = options.auth_token.find_last_not_of(" \t\r\n");
    options.auth_token = first == std::string::npos ? "" : options.auth_token.substr(first, last - first + 1);
  }
  return client::Client(options);
}

int Fail(const Status& status, const GlobalFlags& flags) {
  std::string hint;
  if (status.code() == absl::StatusCode::kDeadlineExceeded) {
    hint = flags.timeout_s > 0
               ? fmt::format(" (the deadline was --timeout {} s; give a larger --timeout SECONDS)", flags.timeout_s)
               : fmt::format(" (single calls have a {} s deadline by default; give --timeout SECONDS)",
                             kDefaultTimeoutS);
  } else if (status.code() == absl::StatusCode::kUnavailable) {
    auto address = client::WithDefaultPort(flags.server);
    hint = fmt::format(" (server {}; --server HOST[:PORT] names another)", address.ok() ? *address : flags.server);
  }
  fmt::print(stderr, "visq: {}: {}{}\n", absl::StatusCodeToString(status.code()), status.message(), hint);
  return status.code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
}

namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;

void Int64AsNumbers(nlohmann::ordered_json& json, const Descriptor& descriptor);

void Int64ValueAsNumber(nlohmann::ordered_json& value, const FieldDescriptor& field) {
  switch (field.cpp_type()) {
    case FieldDescriptor::CPPTYPE_UINT64:
      if (value.is_string()) value = std::stoull(value.get<std::string>());
      break;
    case FieldDescriptor::CPPTYPE_INT64:
      if (value.is_string()) value = std::stoll(value.get<std::string>());
      break;
    case FieldDescriptor::CPPTYPE_MESSAGE:
      Int64AsNumbers(value, *field.message_type());
      break;
    default:
      break;
  }
}

// proto3 JSON writes 64-bit integers as strings, for JavaScript's doubles;
// the CLI's readers (jq, Python) hold them exactly, and a count should read
// as one. The descriptor says which fields they are.
void Int64AsNumbers(nlohmann::ordered_json& json, const Descriptor& descriptor) {
  if (!json.is_object()) return;
  for (int i = 0; i < descriptor.field_count(); ++i) {
    const FieldDescriptor& field = *descriptor.field(i);
    auto it = json.find(field.name());
    if (it == json.end()) continue;
    if (field.is_map()) {
      for (auto& [key, value] : it->items()) Int64ValueAsNumber(value, *field.message_type()->map_value());
    } else if (field.is_repeated()) {
      for (auto& value : *it) Int64ValueAsNumber(value, field);
    } else {
      Int64ValueAsNumber(*it, field);
    }
  }
}

}  // namespace

std::string ToJson(const google::protobuf::Message& message) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;
  if (!google::protobuf::util::MessageToJsonString(message, &out, options).ok()) return "{}\n";
  // ordered_json keeps the proto's field order.
  nlohmann::ordered_json json = nlohmann::ordered_json::parse(out, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded()) return out + "\n";
  Int64AsNumbers(json, *message.GetDescriptor());
  return json.dump(2) + "\n";
}

std::string Bytes(uint64_t bytes) {
  if (bytes >= (1ull << 30)) return fmt::format("{:.2f} GiB", bytes / double(1ull << 30));
  if (bytes >= (1ull << 20)) return fmt::format("{:.2f} MiB", bytes / double(1ull << 20));
  if (bytes >= (1ull << 10)) return fmt::format("{:.1f} KiB", bytes / 1024.0);
  return fmt::format("{} B", bytes);
}

void PrintScene(const v1::SceneInfo& s, bool nodes) {
  fmt::print("{} (version {})\n", s.name(), s.version());
  fmt::print("  triangles     {}\n  vertices      {}\n", s.triangle_count(), s.vertex_count());
  fmt::print("  bounds        ({:.4g}, {:.4g}, {:.4g}) .. ({:.4g}, {:.4g}, {:.4g})\n", s.bounds_min().x(),
             s.bounds_min().y(), s.bounds_min().z(), s.bounds_max().x(), s.bounds_max().y(), s.bounds_max().z());
  fmt::print("  materials     {} ({} emissive triangles)\n", s.material_count(), s.emissive_triangle_count());
  fmt::print("  lightmap UVs  {}\n", s.has_lightmap_uvs() ? "yes (TEXCOORD_1)" : "no");
  fmt::print("  memory        CPU {}, GPU {}\n", Bytes(s.memory().cpu_bytes()), Bytes(s.memory().gpu_bytes()));
  fmt::print("  content hash  {}\n", s.content_hash());
  fmt::print("  load time     {:.1f} ms{}\n", s.load_ms(), s.persisted() ? ", stored in the repository" : "");
  for (const auto& d : s.dropped()) fmt::print("  dropped       {}\n", d);
  if (nodes) {
    fmt::print("  nodes         {}\n", s.nodes_size());
    for (int i = 0; i < s.nodes_size(); ++i) {
      const auto& n = s.nodes(i);
      fmt::print("    [{}] {} (glTF node {}, parent {}, {} triangles)\n", i, n.name().empty() ? "<unnamed>" : n.name(),
                 n.gltf_index(), n.parent(), n.triangle_count());
    }
  }
}

bool ParseVec3(const std::string& text, v1::Vec3* out) {
  double x, y, z;
  char tail;
  if (std::sscanf(text.c_str(), "%lf,%lf,%lf%c", &x, &y, &z, &tail) != 3) return false;
  if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) return false;
  out->set_x(x);
  out->set_y(y);
  out->set_z(z);
  return true;
}

bool ParsePatch(const std::string& text, v1::Patch* out) {
  const size_t a = text.find(';');
  if (a == std::string::npos) return false;
  const size_t b = text.find(';', a + 1);
  if (b == std::string::npos) return false;
  return ParseVec3(text.substr(0, a), out->mutable_origin()) &&
         ParseVec3(text.substr(a + 1, b - a - 1), out->mutable_edge_u()) &&
         ParseVec3(text.substr(b + 1), out->mutable_edge_v());
}

Status WritePng(const std::string& path, uint32_t width, uint32_t height, int channels,
                const std::vector<float>& values) {
  const size_t row = size_t(width) * channels;
  if (values.size() != row * height)
    return absl::InternalError(fmt::format("{}: {} values for a {} x {} image", path, values.size(), width, height));
  std::vector<unsigned char> pixels(row * height);
  for (uint32_t y = 0; y < height; ++y)
    for (size_t x = 0; x < row; ++x) {
      const float v = values[size_t(height - 1 - y) * row + x];
      pixels[size_t(y) * row + x] =
          static_cast<unsigned char>(std::clamp(std::isfinite(v) ? v : 0.0f, 0.0f, 1.0f) * 255.0f + 0.5f);
    }
  if (stbi_write_png(path.c_str(), static_cast<int>(width), static_cast<int>(height), channels, pixels.data(),
                     static_cast<int>(row)) == 0)
    return absl::PermissionDeniedError(fmt::format("cannot write {}", path));
  return absl::OkStatus();
}

std::vector<float> FlipRows(const std::vector<float>& values, uint32_t height, size_t row) {
  std::vector<float> flipped(values.size());
  for (uint32_t y = 0; y < height && (size_t(y) + 1) * row <= values.size(); ++y)
    std::copy_n(values.begin() + static_cast<std::ptrdiff_t>(size_t(y) * row), row,
                flipped.begin() + static_cast<std::ptrdiff_t>(size_t(height - 1 - y) * row));
  return flipped;
}

Status WriteTopFirstPng(const std::string& path, uint32_t width, uint32_t height, const std::vector<float>& rgb,
                        float scale) {
  std::vector<float> flipped = FlipRows(rgb, height, size_t(width) * 3);
  for (float& v : flipped) v *= scale;
  return WritePng(path, width, height, 3, flipped);
}

Status WriteExr(const std::string& path, uint32_t width, uint32_t height, int channels,
                const std::vector<float>& values, bool top_first) {
  const size_t row = size_t(width) * channels;
  if ((channels != 1 && channels != 3) || values.size() != row * height)
    return absl::InternalError(fmt::format("{}: {} values for a {} x {} x {} image", path, values.size(), width,
                                           height, channels));
  // EXR's first scan line is the top one.
  const std::vector<float> top = top_first ? values : FlipRows(values, height, row);
  const char* names[3] = {channels == 1 ? "Y" : "R", "G", "B"};
  try {
    Imf::Header header(static_cast<int>(width), static_cast<int>(height));
    Imf::FrameBuffer frame;
    for (int c = 0; c < channels; ++c) {
      header.channels().insert(names[c], Imf::Channel(Imf::FLOAT));
      frame.insert(names[c], Imf::Slice(Imf::FLOAT, const_cast<char*>(reinterpret_cast<const char*>(top.data() + c)),
                                        sizeof(float) * channels, sizeof(float) * row));
    }
    Imf::OutputFile file(path.c_str(), header);
    file.setFrameBuffer(frame);
    file.writePixels(static_cast<int>(height));
  } catch (const std::exception& e) {
    // OpenEXR reports by exception; it stops here.
    return absl::PermissionDeniedError(fmt::format("cannot write {}: {}", path, e.what()));
  }
  return absl::OkStatus();
}

Status WriteNpy(const std::string& path, const std::vector<uint64_t>& shape, const std::vector<float>& values) {
  uint64_t count = 1;
  std::string dims;
  for (uint64_t d : shape) {
    count *= d;
    dims += fmt::format("{}, ", d);
  }
  if (shape.size() > 1) dims.resize(dims.size() - 2);  // (3,) keeps its comma, (2, 3) does not
  if (count != values.size())
    return absl::InternalError(fmt::format("{}: {} values for shape ({})", path, values.size(), dims));
  // NPY 1.0: magic, version, header length, then a dict padded with spaces
  // to a multiple of 64 bytes ending in '\n'.
  std::string header = fmt::format("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}), }}", dims);
  const size_t prefix = 10;
  header.append(63 - (prefix + header.size()) % 64, ' ');
  header.push_back('\n');
  std::ofstream out(path, std::ios::binary);
  if (!out) return absl::PermissionDeniedError(fmt::format("cannot write {}", path));
  const uint16_t length = static_cast<uint16_t>(header.size());
  out.write("\x93NUMPY\x01\x00", 8);
  const char length_bytes[2] = {static_cast<char>(length & 0xff), static_cast<char>(length >> 8)};
  out.write(length_bytes, 2);
  out.write(header.data(), static_cast<std::streamsize>(header.size()));
  // x86 and arm64 are little-endian, which '<f4' says.
  out.write(reinterpret_cast<const char*>(values.data()), static_cast<std::streamsize>(values.size() * sizeof(float)));
  if (!out) return absl::PermissionDeniedError(fmt::format("cannot write {}", path));
  return absl::OkStatus();
}

void AddCameraFlags(CLI::App* command, CameraFlags& camera) {
  command->add_option("--camera-position,--camera", camera.position, "Camera position 'x,y,z'")->required();
  command->add_option("--camera-forward,--forward", camera.forward, "Viewing direction 'x,y,z'")->required();
  command->add_option("--camera-up,--up", camera.up, "Camera up 'x,y,z' (default 0,1,0)");
  command->add_option("--width", camera.width, "Image width")->capture_default_str();
  command->add_option("--height", camera.height, "Image height")->capture_default_str();
  command->add_option("--fov", camera.fov, "Vertical field of view, degrees")->capture_default_str();
}

void TargetFlags::Fill(v1::AccuracyTarget* out) const {
  out->set_max_error(max_error);
  out->set_confidence(confidence);
  out->set_time_budget_ms(time_budget_ms);
  if (guarantee == "rigorous") out->set_guarantee(v1::AccuracyTarget::RIGOROUS);
  if (guarantee == "estimate") out->set_guarantee(v1::AccuracyTarget::ESTIMATE);
}

void AddTargetFlags(CLI::App* command, TargetFlags& target) {
  command->add_option("--max-error", target.max_error,
                      "Instead of a count: the error the answer may have; the server picks method and count");
  command->add_option("--confidence", target.confidence, "Confidence of --max-error (default 0.95; 1: worst case)");
  command->add_option("--time-budget-ms", target.time_budget_ms,
                      "Instead of a count: as accurate as possible within this many milliseconds");
  command
      ->add_option("--guarantee", target.guarantee,
                   "What --max-error is on: 'rigorous' (the stated bound, the default) or 'estimate' (the normal "
                   "approximation beside it: cheaper, not a bound)")
      ->check(CLI::IsMember({"rigorous", "estimate"}));
}

void PrintTiming(const v1::Timing& timing) {
  fmt::print("time: queue {:.1f} ms, compute {:.1f} ms, transfer {:.1f} ms, total {:.1f} ms\n", timing.queue_ms(),
             timing.compute_ms(), timing.transfer_ms(), timing.total_ms());
}

void PrintWritten(const std::string& png, const std::string& npy, const std::string& exr) {
  for (const std::string* file : {&png, &npy, &exr})
    if (!file->empty()) fmt::print("wrote {}\n", *file);
}

void PrintChosenPlan(const v1::Accuracy& accuracy) {
  if (accuracy.has_estimate() && accuracy.error_bound() != accuracy.estimate())
    fmt::print("estimate +-{:.4f} at confidence {} (an estimate beside the bound, not a bound)\n", accuracy.estimate(),
               accuracy.confidence());
  if (accuracy.plans_size() == 0) return;
  std::string parameters;
  for (const auto& [name, value] : accuracy.parameters())
    parameters += fmt::format("{}{}: {}", parameters.empty() ? "" : ", ", name, value);
  fmt::print("chosen: {} {{{}}}, predicted {:.1f} ms (of {} plans weighed)\n", accuracy.method(), parameters,
             accuracy.predicted_ms(), accuracy.plans_size());
}

CLI::Option* AddChoice(CLI::App* command, const std::string& name, std::string& value,
                       const std::vector<std::string>& allowed, const std::string& help) {
  std::string list;
  for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
  return command->add_option(name, value, help)
      ->check(CLI::Validator(
          [allowed, list](std::string& given) -> std::string {
            if (std::find(allowed.begin(), allowed.end(), given) != allowed.end()) return "";
            return "'" + given + "' is not one of " + list;
          },
          "{" + list + "}"))
      ->capture_default_str();
}

}  // namespace visq::cli
