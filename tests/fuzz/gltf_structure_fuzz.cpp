// libFuzzer target: structure-aware glTF documents.
//
// The byte-level target (gltf_loader_fuzz.cpp) mutates JSON text, which
// almost never turns into a 5,000-deep node chain, a DAG whose paths double
// at every level, an accessor count of 2^62 + 1 or a buffer uri of
// "%2e%2e/x". Here the input bytes are decisions (FuzzedDataProvider): this
// file builds a glTF document from them, usually valid and one decision away
// from the edges:
//   - node graphs: chains up to 25,000 deep, DAGs with `children: [i+1, i+1]`
//     (up to 4 repeats, 48 levels), cycles, self-loops, out-of-range
//     children, meshes and roots;
//   - numbers: accessor count / byteOffset, bufferView byteOffset /
//     byteLength / byteStride, buffer byteLength near 2^31, 2^32, 2^62, 2^63,
//     2^64 and 2^64 / stride (as JSON unsigned numbers), negatives, fractions;
//     componentType / type mismatches; sparse accessors with extreme counts
//     and offsets;
//   - buffer and image uris: in the folder, in a subfolder ("sub%2Fb0.bin"),
//     data:, "../x", "%2e%2e/%2e%2e/x", "..%2Fx", absolute paths, /etc/passwd,
//     bare names that exist only in the working directory, empty, very long,
//     a directory, NUL bytes;
//   - JSON nested 200,000 deep in extras, GLB chunk lengths that lie;
//   - extensions, in gltf_structure_extensions.cpp, decided last (inputs
//     from before they existed keep their meaning): a small mesh of its own
//     in place of every mesh's primitives or beside them, stored plain,
//     through EXT_meshopt_compression or KHR_draco_mesh_compression, with
//     lightmap UVs (TEXCOORD_1) at NaN, ±Inf, ±1e30, FLT_MAX or a denormal;
//   - EXT_meshopt_compression: real streams from meshoptimizer's encoders
//     (vertex, index buffer, index sequence; the EXPONENTIAL and QUATERNION
//     filters), then lies: count × byteStride announcing 1 GiB, 8 GiB,
//     4 GiB + 12 or 64 MiB (under the cap, over what the stream can encode)
//     from a few dozen bytes, a few elements more than encoded, a view
//     length that is not count × byteStride, cut or flipped streams, wrong
//     modes, filters and strides, offsets and lengths past 2^32, a fallback
//     buffer without its flag or with a uri;
//   - KHR_draco_mesh_compression: real sequential and edgebreaker streams
//     from Draco's encoder (quantized or not), then lies: face and point
//     counts in the connectivity header up to 2^32 - 1 (and 2^22, under the
//     cap, so that Draco itself reads them), cut or flipped streams, a point
//     cloud's or a newer version's header, attribute ids that do not exist
//     or name the wrong attribute, accessor counts up to 2^62, no indices,
//     views past the buffer;
//   - EXT_mesh_gpu_instancing on the first node, the last (the deepest of a
//     chain, the most shared of a DAG), a decided one or the first 64:
//     TRANSLATION / ROTATION / SCALE as float, normalized short or byte, or
//     unsigned short, dense, sparse (with or without a view under it) or
//     through meshopt; counts up to 2^62 (2^40 instances of a mesh without
//     triangles, from a sparse accessor of one value), counts that differ
//     between attributes, values at NaN, ±Inf, 1e30, 0, 1e-40.
// It writes the document and its .bin files into a per-process folder and
// loads them with small limits, so that any expansion the limits miss ends at
// libFuzzer's -rss_limit_mb. Besides the sanitizers, it traps when:
//   - a sentinel file outside the document's folder (in its parent, its
//     grandparent, the working directory) is read during a load (inotify
//     IN_ACCESS), whether the load succeeds or not;
//   - a load succeeds although a buffer names an existing file outside the
//     folder, or the scene holds the sentinels' value (their bytes are all
//     0x4B: 13323083.0f however they are sliced; the generator never writes
//     three 0x4B bytes in a row, and skips this check where a compressed
//     stream was cut or flipped, or an encoder wrote three);
//   - a load succeeds with no triangle, or with more than the limit.
//
// The corpus (corpus/structure/) holds one input per interesting case; they
// are written by this binary:
//   VISQ_FUZZ_WRITE_SEEDS=tests/fuzz/corpus build-asan/tests/fuzz/gltf_structure_fuzz
// which also writes the hostile-input cases as plain .gltf files (data: buffers)
// for the byte-level target (corpus/gltf/issue19-*, issue45-structure-*).
// Each seed is a script of named decisions (ScriptChoices, below), encoded
// into the bytes from which FuzzedDataProvider returns exactly those
// decisions, and checked by replaying it. (The seeds written before the
// extensions existed end before the extensions' decisions: they mean the
// same as the writer's longer version of them, which adds zeros.) For
// triage: VISQ_FUZZ_PRINT_DOCUMENT=<n> prints each document's first n bytes;
// VISQ_FUZZ_PRINT_STATUS=1 what each load answered; VISQ_FUZZ_NO_DEEP_JSON=1
// leaves out the deep nesting (to fuzz the rest while it is broken).
#include <fuzzer/FuzzedDataProvider.h>
#include <signal.h>
#include <sys/inotify.h>
#include <unistd.h>

#include <cerrno>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "gltf_structure_extensions.h"
#include "scene/gltf_loader.h"

namespace visq_fuzz {

std::string DataUri(const Bytes& b) {
  static const char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out = "data:application/octet-stream;base64,";
  for (size_t i = 0; i < b.size(); i += 3) {
    uint32_t v = uint32_t{b[i]} << 16;
    if (i + 1 < b.size()) v |= uint32_t{b[i + 1]} << 8;
    if (i + 2 < b.size()) v |= b[i + 2];
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
    out += i + 1 < b.size() ? kAlphabet[(v >> 6) & 63] : '=';
    out += i + 2 < b.size() ? kAlphabet[v & 63] : '=';
  }
  return out;
}

}  // namespace visq_fuzz

namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;
using visq_fuzz::Bytes;
using visq_fuzz::Choices;
using visq_fuzz::DataUri;

constexpr uint64_t kMaxTriangles = uint64_t{1} << 20;
constexpr uint64_t kMaxSceneBytes = uint64_t{256} << 20;
constexpr uint8_t kSentinelByte = 0x4B;
constexpr double kSentinelValue = 13323083.0;  // 0x4B4B4B4B as a float
constexpr size_t kSentinelBytes = 36;          // one triangle of VEC3 floats
constexpr size_t kDecidedNodes = 64;           // nodes past these take defaults

// ---------------------------------------------------------------------------
// Decisions.

// Choices (gltf_structure_extensions.h): a value in a span, or raw bytes.

class FuzzChoices final : public Choices {
 public:
  explicit FuzzChoices(FuzzedDataProvider& fdp) : fdp_(fdp) {}
  uint64_t Span(const std::string&, uint64_t span) override {
    return fdp_.ConsumeIntegralInRange<uint64_t>(0, span);
  }
  Bytes Raw(const std::string&, size_t n) override { return fdp_.ConsumeBytes<uint8_t>(n); }

 private:
  FuzzedDataProvider& fdp_;
};

// Seed writer: answers from a script (a list of values per decision name, in
// the order the generator asks; 0 when unlisted or used up) and records the
// bytes from which FuzzedDataProvider gives the same answers:
// ConsumeIntegralInRange reads ceil(bits(span) / 8) bytes from the end of the
// input, most significant first, and ConsumeBytes reads from the front.
class ScriptChoices final : public Choices {
 public:
  using Script = std::map<std::string, std::vector<uint64_t>>;
  explicit ScriptChoices(const Script& script) {
    for (const auto& [name, values] : script) script_[name] = {values.begin(), values.end()};
  }
  uint64_t Span(const std::string& name, uint64_t span) override {
    uint64_t v = 0;
    auto it = script_.find(name);
    if (it != script_.end()) {
      used_[name] = true;
      if (!it->second.empty()) {
        v = it->second.front();
        it->second.pop_front();
      }
    }
    if (v > span) {
      std::fprintf(stderr, "seed script: %s = %llu is over its span %llu\n", name.c_str(),
                   static_cast<unsigned long long>(v), static_cast<unsigned long long>(span));
      std::exit(2);
    }
    int k = 0;
    while (k < 8 && (span >> (8 * k)) > 0) ++k;
    for (int i = k - 1; i >= 0; --i) tail_.push_back(static_cast<uint8_t>(v >> (8 * i)));
    return v;
  }
  Bytes Raw(const std::string&, size_t n) override {
    Bytes b(n, 0);
    front_.insert(front_.end(), b.begin(), b.end());
    return b;
  }
  Bytes Data() const {
    Bytes d = front_;
    d.insert(d.end(), tail_.rbegin(), tail_.rend());
    return d;
  }
  // Every scripted name must have been asked for (a typo would silently make
  // another seed).
  bool AllUsed(std::string* missing) const {
    for (const auto& [name, values] : script_)
      if (!used_.count(name)) {
        *missing = name;
        return false;
      }
    return true;
  }

 private:
  std::map<std::string, std::deque<uint64_t>> script_;
  std::map<std::string, bool> used_;
  Bytes front_, tail_;
};

// A field tinygltf reads as size_t: usually the truthful value, else one at a
// boundary where unchecked arithmetic wraps.
json U64(Choices& c, const std::string& n, uint64_t sane) {
  auto d = [&] { return static_cast<uint64_t>(static_cast<int64_t>(c.Span(n + ".d", 8)) - 4); };
  switch (c.Span(n + ".kind", 15)) {
    case 1: return json(sane + d());
    case 2: return json(uint64_t{0});
    case 3: return json((uint64_t{1} << 31) + d());
    case 4: return json((uint64_t{1} << 32) + d());
    case 5: return json((uint64_t{1} << 62) + d());
    case 6: return json((uint64_t{1} << 63) + d());
    case 7: return json(~uint64_t{0} - c.Span(n + ".k", 63));  // 2^64 - 1 - k
    case 8: {  // just past 2^64 once multiplied by a stride or element size
      static const uint64_t kDivisors[] = {3, 6, 12, 24, 48, 96, 192, 252};
      return json(~uint64_t{0} / kDivisors[c.Span(n + ".m", 7)] + 1 + d());
    }
    case 9: return json(sane + (uint64_t{1} << 32));
    case 10: return json(sane + (uint64_t{1} << 63));
    case 11: return json(c.Span(n + ".raw", ~uint64_t{0}));
    case 12: return json(c.Span(n + ".small", 65535));
    case 13: return json(static_cast<double>(sane) + 0.5);
    case 14: return json(-static_cast<int64_t>(1 + c.Span(n + ".neg", 15)));
    default: return json(sane);
  }
}

// A field tinygltf reads as int (indices, sparse count and offsets).
json Int(Choices& c, const std::string& n, int64_t sane) {
  switch (c.Span(n + ".kind", 15)) {
    case 1: return json(sane + static_cast<int64_t>(c.Span(n + ".d", 8)) - 4);
    case 2: return json(-1);
    case 3: return json(int64_t{INT32_MIN});
    case 4: return json(int64_t{INT32_MAX});
    case 5: return json((int64_t{1} << 31) + sane);  // negative once cast to int
    case 6: return json((int64_t{1} << 32) + sane);  // sane once truncated to int
    case 7: return json(-static_cast<int64_t>(1 + c.Span(n + ".neg", 255)));
    case 8: return json(c.Span(n + ".small", 255));
    case 9: return json(c.Span(n + ".raw", ~uint64_t{0}));
    case 10: return json(~uint64_t{0});
    case 11: return json(static_cast<double>(sane) + 0.5);
    default: return json(sane);
  }
}

json ComponentType(Choices& c, const std::string& n, int sane) {
  static const int kTypes[] = {5120, 5121, 5122, 5123, 5124, 5125, 5126, 5130, 0, -1, 99999};
  const uint64_t k = c.Span(n, 15);
  if (k >= 1 && k <= 11) return json(kTypes[k - 1]);
  if (k == 12) return Int(c, n + ".value", sane);
  return json(sane);
}

json AccessorType(Choices& c, const std::string& n, const char* sane) {
  static const char* kTypes[] = {"SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4", "vec3", "", "VEC33"};
  const uint64_t k = c.Span(n, 15);
  if (k >= 1 && k <= 10) return json(kTypes[k - 1]);
  if (k == 11) return json(3);  // a number where a string belongs
  return json(sane);
}

// A double from a short list of edges.
double Real(Choices& c, const std::string& n, double sane) {
  static const double kValues[] = {0.0, 1.0, -1.0, 0.5, 2.0, 1e-200, 1e200, -1e308, 1e308, 4.9e-324, 1e6, -1e6};
  const uint64_t k = c.Span(n, 15);
  if (k >= 1 && k <= 12) return kValues[k - 1];
  if (k == 13) return static_cast<double>(c.Span(n + ".int", 2000)) - 1000.0;
  return sane;
}

// ---------------------------------------------------------------------------
// The folders.

struct Env {
  fs::path root;  // per process; holds the sentinel "x"
  fs::path up;    // root/up: holds the sentinel "x" too
  fs::path doc;   // root/up/doc: the document's folder
  std::string cwd_name;  // a sentinel in the working directory
  bool cwd_planted = false;
  bool passwd = false;
  uint64_t passwd_size = 0;
  int inotify = -1;
};

void WriteFile(const fs::path& path, const Bytes& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

Env* g_env = nullptr;

void CleanUp() {
  if (!g_env) return;
  std::error_code ec;
  fs::remove_all(g_env->root, ec);
  if (g_env->cwd_planted) fs::remove(g_env->cwd_name, ec);
}

// A crash skips CleanUp: remove what processes that are gone left behind
// (their folders in the temp folder, their sentinels in the working directory).
void RemoveStale(const fs::path& dir) {
  std::error_code ec;
  const std::string prefix = "visq-structure-fuzz-";
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    std::string name = entry.path().filename().string();
    if (name.rfind(prefix, 0) != 0) continue;
    name = name.substr(prefix.size());
    if (name.size() > 4 && name.compare(name.size() - 4, 4, ".bin") == 0) name.resize(name.size() - 4);
    if (name.empty() || name.find_first_not_of("0123456789") != std::string::npos || name.size() > 9) continue;
    if (::kill(static_cast<pid_t>(std::stol(name)), 0) != 0 && errno == ESRCH) fs::remove_all(entry.path(), ec);
  }
}

Env& TheEnv() {
  if (g_env) return *g_env;
  RemoveStale(fs::temp_directory_path());
  RemoveStale(fs::current_path());
  g_env = new Env;
  Env& env = *g_env;
  const std::string pid = std::to_string(::getpid());
  env.root = fs::temp_directory_path() / ("visq-structure-fuzz-" + pid);
  env.up = env.root / "up";
  env.doc = env.up / "doc";
  fs::create_directories(env.doc / "sub");
  const Bytes sentinel(kSentinelBytes, kSentinelByte);
  std::vector<fs::path> watched = {env.root / "x", env.up / "x"};
  for (const auto& p : watched) WriteFile(p, sentinel);
  env.cwd_name = "visq-structure-fuzz-" + pid + ".bin";
  std::error_code ec;
  if (!fs::exists(env.cwd_name, ec)) {
    WriteFile(env.cwd_name, sentinel);
    env.cwd_planted = fs::file_size(env.cwd_name, ec) == kSentinelBytes && !ec;
    if (env.cwd_planted) watched.push_back(fs::absolute(env.cwd_name));
  }
  env.passwd_size = fs::file_size("/etc/passwd", ec);
  env.passwd = !ec && env.passwd_size > 0;
  env.inotify = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
  if (env.inotify >= 0)
    for (const auto& p : watched) inotify_add_watch(env.inotify, p.c_str(), IN_ACCESS);
  std::atexit(CleanUp);
  return env;
}

// True when a watched sentinel was read since the last call.
bool SentinelRead(const Env& env) {
  if (env.inotify < 0) return false;
  bool read = false;
  alignas(struct inotify_event) char buf[4096];
  for (;;) {
    const ssize_t n = ::read(env.inotify, buf, sizeof buf);
    if (n <= 0) break;
    for (ssize_t off = 0; off < n;) {
      const auto* e = reinterpret_cast<const struct inotify_event*>(buf + off);
      if (e->mask & IN_ACCESS) read = true;
      off += static_cast<ssize_t>(sizeof(struct inotify_event) + e->len);
    }
  }
  return read;
}

// ---------------------------------------------------------------------------
// The document.

struct Document {
  bool glb = false;
  bool explicit_root = false;  // GltfLoadLimits::file_root set to the folder (else empty)
  Bytes main;                  // scene.gltf or scene.glb
  std::vector<std::pair<std::string, Bytes>> files;  // relative to the folder
  bool escapes = false;        // a buffer names an existing file outside the folder
  bool opaque_values = false;  // a compressed stream was garbled (ExtensionCases)
  std::string Name() const { return glb ? "scene.glb" : "scene.gltf"; }
};

// No three sentinel bytes in a row in anything the generator writes, so that
// no float read from the document's own bytes is within 64 of the sentinel.
void Scrub(Bytes& b) {
  for (size_t i = 0; i + 2 < b.size(); ++i)
    if (b[i] == kSentinelByte && b[i + 1] == kSentinelByte && b[i + 2] == kSentinelByte) b[i + 2] ^= 1;
}

std::string PercentEncodeAll(const std::string& s) {
  static const char kHex[] = "0123456789ABCDEF";
  std::string out;
  for (unsigned char ch : s) {
    out += '%';
    out += kHex[ch >> 4];
    out += kHex[ch & 15];
  }
  return out;
}

struct Uri {
  std::string uri;
  uint64_t size = kSentinelBytes;  // the truthful byteLength
  bool escapes = false;            // names an existing file outside the folder
  std::string file;                // a file to write into the folder
  Bytes bytes;
};

// An external uri; `own` is a file name for the kinds that live in the folder.
Uri PickUri(Choices& c, const Env& env, const std::string& n, const std::string& own, Document& d) {
  Uri u;
  auto own_bytes = [&] {
    Bytes b = c.Raw(n + ".bytes", 1 + c.Span(n + ".length", 63));
    if (b.empty()) b.push_back(0);
    Scrub(b);
    u.size = b.size();
    return b;
  };
  const std::string absolute_x = (env.root / "x").string();
  switch (c.Span(n + ".kind", 31)) {
    case 0: u.uri = own; u.file = own; u.bytes = own_bytes(); break;
    case 1: u.uri = DataUri(own_bytes()); break;
    case 2: u.uri = "../x"; u.escapes = true; break;
    case 3: u.uri = "../../x"; u.escapes = true; break;
    case 4: u.uri = "%2e%2e/x"; u.escapes = true; break;
    case 5: u.uri = "%2e%2e/%2e%2e/x"; u.escapes = true; break;
    case 6: u.uri = "..%2Fx"; u.escapes = true; break;
    case 7: u.uri = "%2E%2E%2F%2E%2E%2Fx"; u.escapes = true; break;
    case 8: u.uri = "sub/../../x"; u.escapes = true; break;
    case 9: u.uri = absolute_x; u.escapes = true; break;
    case 10: u.uri = "/etc/passwd"; u.size = env.passwd_size; u.escapes = env.passwd; break;
    case 11: u.uri = env.cwd_name; u.escapes = env.cwd_planted; break;  // only in the working directory
    case 12: u.uri = "/" + env.cwd_name; u.escapes = env.cwd_planted; break;  // tinygltf tries "./" + uri
    case 13: u.uri = "./../x"; u.escapes = true; break;
    case 14: u.uri = "..%5Cx"; break;  // a backslash: a plain (missing) name on Linux
    case 15: u.uri = ""; break;
    case 16: u.uri = std::string(200 + c.Span(n + ".long", 8000), 'a') + ".bin"; break;
    case 17: u.uri = "sub"; break;  // a directory
    case 18: u.uri = "."; break;
    case 19: u.uri = "data:application/octet-stream;base64,!!!!"; break;
    case 20: u.uri = "data:;base64,"; break;
    case 21: u.uri = "file://" + absolute_x; break;
    case 22: u.uri = "x"; break;  // exists in the parent only
    case 23: u.uri = "missing.bin"; break;
    case 24: u.uri = "%zz%"; break;
    case 25: u.uri = "..%2Fx%00.bin"; u.escapes = true; break;  // NUL: "../x" to fopen
    case 26: u.uri = "sub%2F..%2F..%2Fx"; u.escapes = true; break;
    case 27: u.uri = PercentEncodeAll(absolute_x); u.escapes = true; break;
    case 28: u.uri = "sub%2F" + own; u.file = "sub/" + own; u.bytes = own_bytes(); break;
    case 29: u.uri = "./" + own; u.file = own; u.bytes = own_bytes(); break;
    case 30: u.uri = "sub/../" + own; u.file = own; u.bytes = own_bytes(); break;
    default: u.uri = PercentEncodeAll(own); u.file = own; u.bytes = own_bytes(); break;
  }
  if (!u.file.empty()) d.files.emplace_back(u.file, u.bytes);
  return u;
}

json Transform(Choices& c, const std::string& n, json node) {
  auto v = [&](const char* what, double sane) { return Real(c, n + "." + what, sane); };
  switch (c.Span(n, 6)) {
    case 1: node["translation"] = {v("t", 1.0), v("t", 0.0), v("t", 0.0)}; break;
    case 2: node["scale"] = {v("s", 2.0), v("s", 2.0), v("s", 2.0)}; break;
    case 3: node["rotation"] = {v("r", 0.0), v("r", 0.0), v("r", 0.7071067811865476), v("r", 0.7071067811865476)}; break;
    case 4: {
      json m = json::array();
      for (int i = 0; i < 16; ++i) m.push_back(v("m", i % 5 == 0 ? 1.0 : 0.0));
      node["matrix"] = m;
      break;
    }
    case 5: node["scale"] = {-1.0, 1.0, 1.0}; break;  // mirrored
    case 6: node["translation"] = {1e300, -1e300, 1e300}; break;
    default: break;
  }
  return node;
}

struct Section {
  uint64_t offset = 0, length = 0;
};

Document Generate(Choices& c, const Env& env) {
  Document d;
  d.glb = c.Flag("container");
  d.explicit_root = c.Flag("limits.root");
  json g;
  g["asset"] = {{"version", "2.0"}};

  // Buffer 0: [lead][positions][indices][uvs][sparse indices][sparse values][raw].
  Bytes bin(4 * c.Span("buf.lead", 4), 0);
  auto align4 = [&] { while (bin.size() % 4) bin.push_back(0); };
  auto put_float = [&](float f) {
    uint8_t b[4];
    std::memcpy(b, &f, 4);
    bin.insert(bin.end(), b, b + 4);
  };
  auto put_uint = [&](uint64_t v, int bytes) {
    for (int i = 0; i < bytes; ++i) bin.push_back(static_cast<uint8_t>(v >> (8 * i)));
  };
  const uint64_t nverts = 3 + c.Span("geo.verts", 45);
  const Section pos{bin.size(), 12 * nverts};
  for (uint64_t i = 0; i < nverts; ++i)
    for (uint64_t a = 0; a < 3; ++a)
      put_float(float((i % 3 == 1 && a == 0) || (i % 3 == 2 && a == 1)) + float(c.Span("geo.coord", 2000)));

  static const int kIndexBytes[] = {0, 1, 2, 4};
  static const int kIndexTypes[] = {0, 5121, 5123, 5125};
  const int index_kind = static_cast<int>(c.Span("geo.index_type", 3));  // none, u8, u16, u32
  Section idx;
  uint64_t nindices = 0;
  if (index_kind) {
    nindices = 3 * (1 + c.Span("geo.tris", 31));
    idx.offset = bin.size();
    for (uint64_t k = 0; k < nindices; ++k) put_uint((k + c.Span("geo.index", nverts - 1)) % nverts, kIndexBytes[index_kind]);
    idx.length = bin.size() - idx.offset;
    align4();
  }
  const int uv_kind = static_cast<int>(c.Span("geo.uv", 2));  // none, float, normalized u16
  Section uv;
  if (uv_kind) {
    uv.offset = bin.size();
    for (uint64_t i = 0; i < 2 * nverts; ++i) {
      if (uv_kind == 1) put_float(float(c.Span("geo.uv_value", 255)) / 255.0f);
      else put_uint(c.Span("geo.uv_value", 65535), 2);
    }
    uv.length = bin.size() - uv.offset;
  }
  const int sparse_kind = static_cast<int>(c.Span("sparse", 2));  // none, over the view, without a view
  Section sparse_indices, sparse_values;
  uint64_t sparse_count = 0;
  int sparse_index_kind = 1;
  if (sparse_kind) {
    sparse_count = 1 + c.Span("sparse.count", std::min<uint64_t>(nverts, 16) - 1);
    sparse_index_kind = 1 + static_cast<int>(c.Span("sparse.index_type", 2));
    sparse_indices.offset = bin.size();
    for (uint64_t k = 0; k < sparse_count; ++k)
      put_uint((k + c.Span("sparse.index", nverts - 1)) % nverts, kIndexBytes[sparse_index_kind]);
    sparse_indices.length = bin.size() - sparse_indices.offset;
    align4();
    sparse_values.offset = bin.size();
    for (uint64_t k = 0; k < 3 * sparse_count; ++k) put_float(float(c.Span("sparse.value", 2000)) - 1000.0f);
    sparse_values.length = bin.size() - sparse_values.offset;
  }
  {
    const Bytes raw = c.Raw("buf.raw", c.Span("buf.raw_length", 64));
    bin.insert(bin.end(), raw.begin(), raw.end());
  }
  if (bin.empty()) bin.push_back(0);
  Scrub(bin);

  // Buffers.
  json buffers = json::array();
  bool bin_chunk = false;
  {
    json b0 = {{"byteLength", U64(c, "buf0.byteLength", bin.size())}};
    switch (c.Span("buf0.uri", 5)) {
      case 0:
        if (d.glb) {
          bin_chunk = true;
        } else {
          b0["uri"] = "b0.bin";
          d.files.emplace_back("b0.bin", bin);
        }
        break;
      case 1: b0["uri"] = "b0.bin"; d.files.emplace_back("b0.bin", bin); break;
      case 2: b0["uri"] = DataUri(bin); break;
      case 3: b0["uri"] = "sub%2Fb0.bin"; d.files.emplace_back("sub/b0.bin", bin); break;
      case 4: b0["uri"] = "./b0.bin"; d.files.emplace_back("b0.bin", bin); break;
      default: b0["uri"] = "%62%30.bin"; d.files.emplace_back("b0.bin", bin); break;
    }
    buffers.push_back(b0);
  }
  const uint64_t extra_buffers = c.Span("buf.extra", 3);
  for (uint64_t i = 0; i < extra_buffers; ++i) {
    const Uri u = PickUri(c, env, "buf.uri", "e" + std::to_string(i) + ".bin", d);
    json b = {{"byteLength", U64(c, "buf.byteLength", u.size)}};
    if (c.Span("buf.no_uri", 7) != 7) b["uri"] = u.uri;
    else if (u.escapes) continue;  // no uri, nothing read: not an escape
    d.escapes |= u.escapes;
    buffers.push_back(b);
  }
  g["buffers"] = buffers;

  // Buffer views.
  json views = json::array();
  auto view = [&](const std::string& n, Section s, int64_t buffer, int natural_stride) -> int64_t {
    json v = {{"buffer", Int(c, n + ".buffer", buffer)},
              {"byteOffset", U64(c, n + ".byteOffset", s.offset)},
              {"byteLength", U64(c, n + ".byteLength", s.length)}};
    switch (c.Span(n + ".stride", 7)) {
      case 1: if (natural_stride) v["byteStride"] = natural_stride; break;
      case 2: v["byteStride"] = 0; break;
      case 3: v["byteStride"] = 4; break;
      case 4: v["byteStride"] = 252; break;
      case 5: v["byteStride"] = 256; break;
      case 6: v["byteStride"] = (uint64_t{1} << 32) + 12; break;
      case 7: v["byteStride"] = 4 * c.Span(n + ".stride4", 63); break;
      default: break;
    }
    views.push_back(v);
    return static_cast<int64_t>(views.size()) - 1;
  };
  const int64_t view_pos = view("view.pos", pos, 0, 12);
  const int64_t view_idx = index_kind ? view("view.idx", idx, 0, 0) : -1;
  const int64_t view_uv = uv_kind ? view("view.uv", uv, 0, uv_kind == 1 ? 8 : 4) : -1;
  int64_t view_sparse_indices = -1, view_sparse_values = -1;
  if (sparse_kind) {
    view_sparse_indices = view("view.sparse_indices", sparse_indices, 0, 0);
    view_sparse_values = view("view.sparse_values", sparse_values, 0, 12);
  }
  const uint64_t extra_views = c.Span("view.extra", 3);
  for (uint64_t i = 0; i < extra_views; ++i) {
    const Section s{c.Span("view.extra.offset", bin.size()), c.Span("view.extra.length", bin.size())};
    const auto buffer = static_cast<int64_t>(c.Span("view.extra.pick", buffers.size() - 1));
    view("view.extra", s, buffer, 0);
  }
  g["bufferViews"] = views;

  // Accessors.
  json accessors = json::array();
  auto accessor = [&](const std::string& n, int64_t view_index, uint64_t count, int type, const char* shape) {
    json a;
    if (view_index >= 0) a["bufferView"] = Int(c, n + ".view", view_index);
    a["byteOffset"] = U64(c, n + ".byteOffset", 0);
    a["componentType"] = ComponentType(c, n + ".ct", type);
    a["count"] = U64(c, n + ".count", count);
    a["type"] = AccessorType(c, n + ".type", shape);
    if (c.Span(n + ".normalized", 7) == 7) a["normalized"] = true;
    return a;
  };
  json position = accessor("acc.pos", sparse_kind == 2 ? -1 : view_pos, nverts, 5126, "VEC3");
  if (sparse_kind) {
    position["sparse"] = {
        {"count", Int(c, "acc.pos.sparse.count", static_cast<int64_t>(sparse_count))},
        {"indices",
         {{"bufferView", Int(c, "acc.pos.sparse.indices.view", view_sparse_indices)},
          {"byteOffset", Int(c, "acc.pos.sparse.indices.byteOffset", 0)},
          {"componentType", ComponentType(c, "acc.pos.sparse.indices.ct", kIndexTypes[sparse_index_kind])}}},
        {"values",
         {{"bufferView", Int(c, "acc.pos.sparse.values.view", view_sparse_values)},
          {"byteOffset", Int(c, "acc.pos.sparse.values.byteOffset", 0)}}}};
  }
  accessors.push_back(position);
  const int64_t acc_pos = 0;
  int64_t acc_idx = -1, acc_uv = -1;
  if (index_kind) {
    accessors.push_back(accessor("acc.idx", view_idx, nindices, kIndexTypes[index_kind], "SCALAR"));
    acc_idx = static_cast<int64_t>(accessors.size()) - 1;
  }
  if (uv_kind) {
    json a = accessor("acc.uv", view_uv, nverts, uv_kind == 1 ? 5126 : 5123, "VEC2");
    if (uv_kind == 2) a["normalized"] = true;
    accessors.push_back(a);
    acc_uv = static_cast<int64_t>(accessors.size()) - 1;
  }
  const uint64_t extra_accessors = c.Span("acc.extra", 2);
  for (uint64_t i = 0; i < extra_accessors; ++i) {
    const auto view_index = static_cast<int64_t>(c.Span("acc.extra.pick", views.size() - 1));
    const uint64_t count = c.Span("acc.extra.count_pick", 64);
    accessors.push_back(accessor("acc.extra", view_index, count, 5126, "VEC3"));
  }
  g["accessors"] = accessors;

  // Materials.
  const uint64_t materials = c.Span("materials", 2);
  if (materials) {
    json list = json::array();
    for (uint64_t i = 0; i < materials; ++i) {
      json m;
      m["pbrMetallicRoughness"]["baseColorFactor"] = {Real(c, "mat.base", 0.5), 0.5, 0.5, 1.0};
      m["emissiveFactor"] = {Real(c, "mat.emissive", 0.0), 0.0, 0.0};
      if (c.Flag("mat.strength"))
        m["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] = Real(c, "mat.strength_value", 2.0);
      list.push_back(m);
    }
    g["materials"] = list;
  }

  // Meshes: copies of one list of primitives.
  json primitives = json::array();
  const uint64_t nprims = 1 + c.Span("mesh.prims", 2);
  for (uint64_t p = 0; p < nprims; ++p) {
    json prim;
    prim["attributes"]["POSITION"] = Int(c, "prim.pos", acc_pos);
    if (uv_kind) prim["attributes"]["TEXCOORD_1"] = Int(c, "prim.uv", acc_uv);
    if (index_kind) prim["indices"] = Int(c, "prim.indices", acc_idx);
    switch (c.Span("prim.mode", 7)) {
      case 1: prim["mode"] = 4; break;
      case 2: prim["mode"] = 5; break;
      case 3: prim["mode"] = 6; break;
      case 4: prim["mode"] = 0; break;
      case 5: prim["mode"] = 1; break;
      case 6: prim["mode"] = 7; break;
      case 7: prim["mode"] = Int(c, "prim.mode_value", 4); break;
      default: break;
    }
    if (materials) prim["material"] = Int(c, "prim.material", 0);
    primitives.push_back(prim);
  }
  const uint64_t nmeshes = 1 + c.Span("mesh.copies", 2);
  json meshes = json::array();
  for (uint64_t m = 0; m < nmeshes; ++m) meshes.push_back({{"primitives", primitives}});
  g["meshes"] = meshes;

  // Nodes.
  std::vector<json> nodes;
  const uint64_t shape = c.Span("graph.shape", 4);  // simple, chain, DAG, cycle, random
  const uint64_t mesh_at = c.Span("graph.mesh_at", 2);  // the leaf, every node, the first
  auto mesh_of = [&](size_t i) { return i < kDecidedNodes ? Int(c, "node.mesh", 0) : json(0); };
  switch (shape) {
    case 1:
    case 2:
    case 3: {
      uint64_t n = 0, fanout = 1;
      if (shape == 1) n = 1 + c.Span("graph.depth", 24999);
      if (shape == 2) {  // n - 1 levels of `children: [i+1] * fanout`
        n = 2 + c.Span("graph.levels", 47);
        fanout = 2 + c.Span("graph.fanout", 2);
      }
      if (shape == 3) n = 1 + c.Span("graph.n", 63);
      nodes.resize(n, json::object());
      for (uint64_t i = 0; i + 1 < n; ++i) nodes[i]["children"] = std::vector<uint64_t>(fanout, i + 1);
      if (shape == 3) nodes[n - 1]["children"] = {c.Span("graph.back", n - 1)};
      for (uint64_t i = 0; i < n; ++i)
        if (mesh_at == 1 || (mesh_at == 0 && i + 1 == n) || (mesh_at == 2 && i == 0)) nodes[i]["mesh"] = mesh_of(i);
      break;
    }
    case 4: {
      const uint64_t n = 1 + c.Span("graph.n", 63);
      nodes.resize(n, json::object());
      for (uint64_t i = 0; i < n; ++i) {
        const uint64_t children = c.Span("node.children", 3);
        for (uint64_t k = 0; k < children; ++k)
          nodes[i]["children"].push_back(Int(c, "node.child", static_cast<int64_t>(c.Span("node.child_pick", n - 1))));
        if (c.Flag("node.has_mesh")) nodes[i]["mesh"] = mesh_of(i);
      }
      break;
    }
    default: {
      const uint64_t n = 1 + c.Span("graph.n", 3);
      nodes.resize(n, json::object());
      for (uint64_t i = 0; i < n; ++i) {
        if (i > 0) nodes[0]["children"].push_back(i);
        nodes[i]["mesh"] = mesh_of(i);
      }
      break;
    }
  }
  // One child reference out of range, negative or wrapping to 0.
  switch (c.Span("graph.bad_child", 4)) {
    case 1: nodes[c.Span("graph.bad_child_node", nodes.size() - 1)]["children"].push_back(nodes.size()); break;
    case 2: nodes[c.Span("graph.bad_child_node", nodes.size() - 1)]["children"].push_back(-1); break;
    case 3: nodes[c.Span("graph.bad_child_node", nodes.size() - 1)]["children"].push_back(INT32_MAX); break;
    case 4: nodes[c.Span("graph.bad_child_node", nodes.size() - 1)]["children"].push_back(uint64_t{1} << 32); break;
    default: break;
  }
  switch (c.Span("graph.transforms", 2)) {  // none, per node (the first ones), the same on every node
    case 1:
      for (size_t i = 0; i < nodes.size() && i < kDecidedNodes; ++i) nodes[i] = Transform(c, "node.transform", nodes[i]);
      break;
    case 2: {
      const json t = Transform(c, "graph.transform", json::object());
      for (auto& node : nodes) node.update(t);
      break;
    }
    default: break;
  }
  g["nodes"] = nodes;

  // Scenes.
  switch (c.Span("scene.kind", 4)) {
    case 1: break;  // no scenes: every parentless node is a root
    case 2:
      g["scenes"] = {{{"nodes", {0}}}};
      g["scene"] = Int(c, "scene.index", 0);
      break;
    case 3:
      g["scenes"] = {{{"nodes", {0, 0, Int(c, "scene.extra_root", static_cast<int64_t>(nodes.size()))}}}};
      break;
    case 4:
      g["scenes"] = {{{"nodes", {0}}}, {{"nodes", json::array()}}};
      g["scene"] = 1;
      break;
    default:
      g["scenes"] = {{{"nodes", {0}}}};
      g["scene"] = 0;
      break;
  }

  switch (c.Span("ext.required", 3)) {
    case 1: g["extensionsRequired"] = {"KHR_materials_emissive_strength"}; break;
    case 2: g["extensionsRequired"] = {"KHR_draco_mesh_compression"}; break;
    case 3: g["extensionsRequired"] = {"KHR_mesh_quantization"}; break;
    default: break;
  }
  const uint64_t images = c.Span("images", 2);
  for (uint64_t i = 0; i < images; ++i)  // dropped by the loader, but tinygltf reads them
    g["images"].push_back({{"uri", PickUri(c, env, "image.uri", "i" + std::to_string(i) + ".png", d).uri}});

  // JSON nested deep (inserted as text: nlohmann's dump recurses).
  const uint64_t deep_kind = c.Span("extras.kind", 3);  // none, arrays in asset, objects in asset, arrays in node 0
  const uint64_t depth = deep_kind ? 1 + c.Span("extras.depth", 199999) : 0;
  // Triage: VISQ_FUZZ_NO_DEEP_JSON=1 fuzzes the rest while that is broken
  // (the decisions are still read, so inputs mean the same with and without).
  static const bool no_deep_json = std::getenv("VISQ_FUZZ_NO_DEEP_JSON") != nullptr;
  const uint64_t deep = no_deep_json ? 0 : deep_kind;
  const std::string kDeep = "@@visq-deep@@";
  if (deep == 1 || deep == 2) g["asset"]["extras"] = kDeep;
  if (deep == 3) g["nodes"][0]["extras"] = kDeep;
  // GLB: one length that may lie (decided here, before the extensions, so
  // that inputs found before those existed keep their meaning).
  const uint64_t glb_lie = d.glb ? c.Span("glb.lie", 3) : 0;
  uint64_t glb_lie_value = 0;
  if (glb_lie == 1) glb_lie_value = c.Span("glb.lie_value", 255);
  if (glb_lie == 2) glb_lie_value = c.Span("glb.lie_value", 0xFFFFFFFFu);
  if (glb_lie == 3) glb_lie_value = c.Span("glb.lie_value", 255);

  // Instancing, meshopt, Draco and lightmap UVs: the last decisions.
  const visq_fuzz::ExtensionCases extensions = visq_fuzz::AddExtensionCases(c, g, d.files);
  d.opaque_values = extensions.opaque_values;

  std::string text = g.dump(-1, ' ', false, json::error_handler_t::replace);
  if (deep) {
    std::string nested;
    nested.reserve(depth * 6 + 2);
    for (uint64_t i = 0; i < depth; ++i) nested += deep == 2 ? "{\"a\":" : "[";
    nested += "0";
    for (uint64_t i = 0; i < depth; ++i) nested += deep == 2 ? "}" : "]";
    const std::string quoted = "\"" + kDeep + "\"";
    text.replace(text.find(quoted), quoted.size(), nested);
  }

  if (!d.glb) {
    d.main.assign(text.begin(), text.end());
    return d;
  }
  // GLB: header, JSON chunk, BIN chunk; optionally one length that lies.
  while (text.size() % 4) text += ' ';
  Bytes chunk = bin_chunk ? bin : Bytes{};
  while (chunk.size() % 4) chunk.push_back(0);
  uint32_t json_length = static_cast<uint32_t>(text.size());
  uint32_t bin_length = static_cast<uint32_t>(chunk.size());
  uint32_t total = 12 + 8 + json_length + (bin_chunk ? 8 + bin_length : 0);
  switch (glb_lie) {
    case 1: total += static_cast<uint32_t>(glb_lie_value) - 128; break;
    case 2: json_length = static_cast<uint32_t>(glb_lie_value); break;
    case 3: bin_length = 0xFFFFFFFFu - static_cast<uint32_t>(glb_lie_value); break;
    default: break;
  }
  auto put32 = [&](uint32_t v) {
    for (int i = 0; i < 4; ++i) d.main.push_back(static_cast<uint8_t>(v >> (8 * i)));
  };
  d.main = {'g', 'l', 'T', 'F'};
  put32(2);
  put32(total);
  put32(json_length);
  d.main.insert(d.main.end(), {'J', 'S', 'O', 'N'});
  d.main.insert(d.main.end(), text.begin(), text.end());
  if (bin_chunk) {
    put32(bin_length);
    d.main.insert(d.main.end(), {'B', 'I', 'N', 0});
    d.main.insert(d.main.end(), chunk.begin(), chunk.end());
  }
  return d;
}

void Materialize(const Document& d, const Env& env) {
  std::error_code ec;
  fs::remove_all(env.doc, ec);
  fs::create_directories(env.doc / "sub", ec);
  for (const auto& [name, bytes] : d.files) WriteFile(env.doc / name, bytes);
  WriteFile(env.doc / d.Name(), d.main);
}

// ---------------------------------------------------------------------------
// The checks on a loaded scene.

[[noreturn]] void Fail(const char* what) {
  std::fprintf(stderr, "gltf_structure_fuzz: %s\n", what);
  std::fflush(stderr);
  __builtin_trap();
}

bool NearSentinel(const glm::dvec3& p) {
  for (int a = 0; a < 3; ++a)
    if (std::abs(p[a] - kSentinelValue) <= 64.0) return true;
  return false;
}

// The sentinel's value in any triangle's vertices, in its node's space (the
// node's world matrix undone where it is well conditioned), or in any
// position when every node is untransformed.
bool ContainsSentinel(const visq::Scene& s) {
  std::vector<int> state(s.nodes.size(), 0);  // 0 unknown, 1 invertible, -1 not
  std::vector<glm::dmat4> inverse(s.nodes.size());
  bool all_identity = true;
  for (const auto& node : s.nodes) all_identity &= node.world == glm::dmat4(1.0);
  if (all_identity) {
    for (const auto& p : s.Flattened().positions)
      if (NearSentinel(p)) return true;
    return false;
  }
  for (size_t t = 0; t < s.TriangleCount(); ++t) {
    const uint32_t n = s.NodeOf(t);
    if (n >= s.nodes.size()) continue;
    if (state[n] == 0) {
      const glm::dmat4& w = s.nodes[n].world;
      inverse[n] = glm::inverse(w);
      const glm::dmat4 e = inverse[n] * w;
      double err = 0.0;
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) err = std::max(err, std::abs(e[i][j] - (i == j ? 1.0 : 0.0)));
      state[n] = std::isfinite(err) && err < 1e-9 ? 1 : -1;
    }
    if (state[n] < 0) continue;
    for (int corner = 0; corner < 3; ++corner)
      if (NearSentinel(glm::dvec3(inverse[n] * glm::dvec4(s.Vertex(t, corner), 1.0)))) return true;
  }
  return false;
}

void LoadAndCheck(const Document& d, const Env& env) {
  Materialize(d, env);
  // Triage: VISQ_FUZZ_PRINT_DOCUMENT=<n> prints the document's first n bytes.
  static const long print = std::getenv("VISQ_FUZZ_PRINT_DOCUMENT") ? std::atol(std::getenv("VISQ_FUZZ_PRINT_DOCUMENT")) : 0;
  if (print > 0) {
    std::fprintf(stderr, "%s (%zu bytes; %zu more files):\n%.*s\n", d.Name().c_str(), d.main.size(), d.files.size(),
                 static_cast<int>(std::min<size_t>(d.main.size(), static_cast<size_t>(print))),
                 reinterpret_cast<const char*>(d.main.data()));
  }
  SentinelRead(env);  // nothing of ours, but start clean
  visq::GltfLoadLimits limits;
  if (d.explicit_root) limits.file_root = env.doc;
  limits.max_triangles = kMaxTriangles;
  limits.max_scene_bytes = kMaxSceneBytes;
  visq::GltfLoadReport report;
  visq::StatusOr<visq::Scene> scene = visq::LoadGltfFile(env.doc / d.Name(), &report, limits);
  // Triage: VISQ_FUZZ_PRINT_STATUS=1 prints what the load answered.
  static const bool print_status = std::getenv("VISQ_FUZZ_PRINT_STATUS") != nullptr;
  if (print_status)
    std::fprintf(stderr, "load: %s\n",
                 scene.ok() ? ("OK, " + std::to_string(scene->TriangleCount()) + " triangles").c_str()
                            : scene.status().ToString().substr(0, 300).c_str());
  if (SentinelRead(env)) Fail("the load read a file outside the document's folder");
  if (!scene.ok()) return;
  if (scene->TriangleCount() == 0) Fail("a scene loaded with no triangle");
  if (scene->TriangleCount() > kMaxTriangles) Fail("a scene loaded with more triangles than max_triangles");
  if (d.escapes) Fail("a scene loaded although a buffer uri names a file outside the document's folder");
  if (!d.opaque_values && ContainsSentinel(*scene))
    Fail("a scene loaded with the bytes of a file outside the document's folder");
}

// ---------------------------------------------------------------------------
// The seeds.

struct Seed {
  const char* name;       // corpus/structure/<name>
  const char* gltf_name;  // corpus/gltf/<name> (the byte-level target) or nullptr
  ScriptChoices::Script script;
};

constexpr uint64_t kAsBin0DataUri = 2;  // "buf0.uri": buffer 0 as a data: uri (one self-contained file)

std::vector<Seed> Seeds() {
  using S = ScriptChoices::Script;
  return {
      {"minimal", nullptr, S{}},
      {"minimal-glb", nullptr, S{{"container", {1}}}},
      {"file-root-explicit", nullptr, S{{"limits.root", {1}}}},
      {"indexed-uv-sparse", nullptr,
       S{{"geo.verts", {6}}, {"geo.index_type", {2}}, {"geo.tris", {4}}, {"geo.uv", {1}}, {"sparse", {1}},
         {"sparse.count", {3}}, {"materials", {1}}, {"mesh.prims", {1}}, {"graph.transforms", {1}},
         {"node.transform", {1}}}},
      {"strip-fan-u32-glb", nullptr,
       S{{"container", {1}}, {"geo.verts", {9}}, {"geo.index_type", {3}}, {"geo.tris", {3}}, {"mesh.prims", {1}},
         {"prim.mode", {2, 3}}}},
      {"sparse-without-view", nullptr, S{{"sparse", {2}}, {"sparse.count", {2}}}},
      // Node graphs.
      {"chain-1000", nullptr, S{{"graph.shape", {1}}, {"graph.depth", {999}}}},
      {"chain-5000", "issue19-chain-5000", S{{"graph.shape", {1}}, {"graph.depth", {4999}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"chain-25000-mesh-everywhere", nullptr, S{{"graph.shape", {1}}, {"graph.depth", {24999}}, {"graph.mesh_at", {1}}}},
      {"dag-22", "issue19-dag-22", S{{"graph.shape", {2}}, {"graph.levels", {21}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"dag-48-fanout-4-mesh-everywhere", nullptr,
       S{{"graph.shape", {2}}, {"graph.levels", {47}}, {"graph.fanout", {2}}, {"graph.mesh_at", {1}}}},
      {"dag-12-translated", nullptr,
       S{{"graph.shape", {2}}, {"graph.levels", {11}}, {"graph.transforms", {2}}, {"graph.transform", {1}}}},
      {"cycle", nullptr, S{{"graph.shape", {3}}, {"graph.n", {7}}, {"graph.back", {2}}}},
      {"self-cycle", nullptr, S{{"graph.shape", {3}}}},
      {"cycle-no-scene", nullptr, S{{"graph.shape", {3}}, {"graph.n", {3}}, {"scene.kind", {1}}}},
      {"child-out-of-range", nullptr, S{{"graph.shape", {4}}, {"graph.n", {5}}, {"graph.bad_child", {1}}}},
      {"child-wraps-to-root", nullptr, S{{"graph.n", {2}}, {"graph.bad_child", {4}}, {"graph.bad_child_node", {1}}}},
      {"random-graph", nullptr,
       S{{"graph.shape", {4}}, {"graph.n", {5}}, {"node.children", {2, 1, 0, 1, 0, 0}},
         {"node.child_pick", {1, 2, 3, 4}}, {"node.has_mesh", {1, 0, 1, 0, 1, 1}}}},
      {"mesh-out-of-range", nullptr, S{{"node.mesh.kind", {4}}}},
      {"scene-index-out-of-range", nullptr, S{{"scene.kind", {2}}, {"scene.index.kind", {4}}}},
      // Numbers.
      {"count-2p62p1", "issue19-count-2p62p1",
       S{{"acc.pos.count.kind", {5}}, {"acc.pos.count.d", {5}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"count-2p63p1-stride-16", nullptr,
       S{{"acc.pos.count.kind", {6}}, {"acc.pos.count.d", {5}}, {"view.pos.stride", {7}}, {"view.pos.stride4", {4}}}},
      {"count-wraps-by-12", nullptr, S{{"acc.pos.count.kind", {8}}, {"acc.pos.count.m", {2}}, {"acc.pos.count.d", {4}}}},
      {"view-length-2p64m8", "issue19-view-length-2p64m8",
       S{{"buf.lead", {2}}, {"view.pos.byteLength.kind", {7}}, {"view.pos.byteLength.k", {7}},
         {"acc.pos.count.kind", {12}}, {"acc.pos.count.small", {1000}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"accessor-offset-2p64m10", "issue19-accessor-offset-2p64m10",
       S{{"acc.pos.byteOffset.kind", {7}}, {"acc.pos.byteOffset.k", {9}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"view-offset-2p64m4", nullptr, S{{"buf.lead", {1}}, {"view.pos.byteOffset.kind", {7}}, {"view.pos.byteOffset.k", {3}}}},
      {"index-count-2p62p1", nullptr,
       S{{"geo.index_type", {3}}, {"acc.idx.count.kind", {5}}, {"acc.idx.count.d", {5}}}},
      {"buffer-length-2p32", nullptr, S{{"buf0.byteLength.kind", {4}}, {"buf0.byteLength.d", {4}}}},
      {"stride-252", nullptr, S{{"geo.verts", {20}}, {"view.pos.stride", {4}}}},
      {"position-vec2-u16", nullptr, S{{"acc.pos.ct", {4}}, {"acc.pos.type", {2}}}},
      {"position-double", nullptr, S{{"acc.pos.ct", {8}}}},
      {"indices-float", nullptr, S{{"geo.index_type", {2}}, {"acc.idx.ct", {7}}}},
      {"sparse-count-int-max", nullptr, S{{"sparse", {1}}, {"acc.pos.sparse.count.kind", {4}}}},
      {"sparse-indices-offset-negative", nullptr,
       S{{"sparse", {1}}, {"acc.pos.sparse.indices.byteOffset.kind", {7}}, {"acc.pos.sparse.indices.byteOffset.neg", {7}}}},
      {"sparse-values-offset-negative", nullptr,
       S{{"sparse", {1}}, {"acc.pos.sparse.values.byteOffset.kind", {7}}, {"acc.pos.sparse.values.byteOffset.neg", {11}}}},
      {"sparse-values-offset-int-max", nullptr, S{{"sparse", {1}}, {"acc.pos.sparse.values.byteOffset.kind", {4}}}},
      {"sparse-count-wraps", nullptr, S{{"sparse", {2}}, {"acc.pos.sparse.count.kind", {5}}, {"acc.pos.count.kind", {4}}}},
      // Uris.
      {"uri-dotdot-dotdot", "issue19-uri-dotdot-dotdot",
       S{{"buf.extra", {1}}, {"buf.uri.kind", {3}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"uri-pct-dotdot-dotdot", "issue19-uri-pct-dotdot-dotdot",
       S{{"buf.extra", {1}}, {"buf.uri.kind", {5}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"uri-etc-passwd", "issue19-uri-etc-passwd",
       S{{"buf.extra", {1}}, {"buf.uri.kind", {10}}, {"buf0.uri", {kAsBin0DataUri}}}},
      // The sentinel as the positions: its bytes would become the scene.
      {"uri-dotdot-as-positions", nullptr,
       S{{"buf.extra", {1}}, {"buf.uri.kind", {2}}, {"view.pos.buffer.kind", {1}}, {"view.pos.buffer.d", {5}}}},
      {"uri-cwd-as-positions", nullptr,
       S{{"buf.extra", {1}}, {"buf.uri.kind", {11}}, {"view.pos.buffer.kind", {1}}, {"view.pos.buffer.d", {5}}}},
      {"uri-pct-slash", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {7}}}},
      {"uri-pct-dotdot-slash", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {6}}}},
      {"uri-sub-dotdot", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {8}}}},
      {"uri-absolute", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {9}}}},
      {"uri-absolute-pct", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {27}}}},
      {"uri-cwd-bare", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {11}}}},
      {"uri-cwd-slash", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {12}}}},
      {"uri-nul", nullptr, S{{"buf.extra", {1}}, {"buf.uri.kind", {25}}}},
      {"uri-glb-dotdot", nullptr, S{{"container", {1}}, {"buf.extra", {1}}, {"buf.uri.kind", {3}}}},
      {"uri-image-dotdot", nullptr, S{{"images", {1}}, {"image.uri.kind", {3}}}},
      {"uri-legit-variants", nullptr,
       S{{"buf0.uri", {3}}, {"buf.extra", {3}}, {"buf.uri.kind", {28, 29, 1}}, {"buf.uri.length", {11, 11, 11}}}},
      {"uri-empty-long-dir", nullptr, S{{"buf.extra", {3}}, {"buf.uri.kind", {15, 16, 17}}, {"buf.uri.long", {5000}}}},
      {"uri-bad-data", nullptr, S{{"buf.extra", {2}}, {"buf.uri.kind", {19, 20}}}},
      // JSON and GLB.
      {"extras-nested-20000", "extras-nested-20000",
       S{{"extras.kind", {1}}, {"extras.depth", {19999}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"extras-nested-100000", nullptr, S{{"extras.kind", {1}}, {"extras.depth", {99999}}}},
      {"extras-objects-nested-20000", nullptr, S{{"extras.kind", {2}}, {"extras.depth", {19999}}}},
      {"glb-bin-length-lies", nullptr, S{{"container", {1}}, {"glb.lie", {3}}}},
      {"glb-json-length-lies", nullptr, S{{"container", {1}}, {"glb.lie", {2}}, {"glb.lie_value", {0x7FFFFFF0}}}},
      {"required-extension", nullptr, S{{"ext.required", {2}}}},
      {"materials-huge-emission", nullptr,
       S{{"materials", {1}}, {"mat.emissive", {9}}, {"mat.strength", {1}}, {"mat.strength_value", {9}}}},
      // Extensions (gltf_structure_extensions.cpp); issue 45's hostile files
      // are also written for the byte-level target (issue45-structure-*).
      // Lightmap UVs at the float edges, plain, through meshopt and Draco.
      {"lightmap-uv-nan", "issue45-structure-lightmap-uv-nan",
       S{{"x.geo", {1}}, {"x.uv", {1}}, {"x.uv.edge", {1}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"lightmap-uv-inf", "issue45-structure-lightmap-uv-inf",
       S{{"x.geo", {1}}, {"x.uv", {1}}, {"x.uv.edge", {2}}, {"x.uv.at", {2}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"lightmap-uv-1e30", "issue45-structure-lightmap-uv-1e30",
       S{{"x.geo", {1}}, {"x.uv", {1}}, {"x.uv.edge", {4}}, {"x.uv.component", {1}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"lightmap-uv-denormal-everywhere", nullptr,
       S{{"x.geo", {1}}, {"x.uv", {1}}, {"x.uv.edge", {7}}, {"x.uv.at", {3}}}},
      {"lightmap-uv-nan-meshopt", nullptr, S{{"x.geo", {2}}, {"x.uv", {1}}, {"x.uv.edge", {1}}, {"x.uv.at", {3}}}},
      {"lightmap-uv-inf-draco", nullptr, S{{"x.geo", {3}}, {"x.uv", {1}}, {"x.uv.edge", {3}}}},
      // EXT_meshopt_compression: real streams, then lies.
      {"meshopt", nullptr, S{{"x.geo", {2}}, {"x.verts", {20}}, {"x.tris", {15}}}},
      {"meshopt-exp-u16-sequence-uv", nullptr,
       S{{"x.geo", {2}}, {"x.verts", {30}}, {"x.tris", {20}}, {"x.uv", {1}}, {"x.mo.pos.exp", {1}},
         {"x.mo.pos.bits", {14}}, {"x.mo.idx.u16", {1}}, {"x.mo.idx.sequence", {1}}, {"x.mo.required", {1, 1, 1}}}},
      {"meshopt-announces-1gib", "issue45-structure-meshopt-announces-1gib",
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {1}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"meshopt-announces-8gib", "issue45-structure-meshopt-announces-8gib",
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {2}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"meshopt-indices-announce-1gib", nullptr, S{{"x.geo", {2}}, {"x.mo.idx.lie", {1}}}},
      {"meshopt-announces-64mib-under-the-cap", nullptr,
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {2}}, {"x.mo.pos.size", {1}}}},
      {"meshopt-more-than-encoded", nullptr, S{{"x.geo", {2}}, {"x.mo.pos.lie", {3}}, {"x.mo.pos.more", {7}}}},
      {"meshopt-count-not-view-length", nullptr, S{{"x.geo", {2}}, {"x.mo.idx.lie", {4}}}},
      {"meshopt-truncated", nullptr,
       S{{"x.geo", {2}}, {"x.tris", {10}}, {"x.mo.idx.lie", {5}}, {"x.mo.idx.cut.keep", {9}}}},
      {"meshopt-flipped", nullptr,
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {6}}, {"x.mo.pos.flip.at", {3}}, {"x.mo.pos.flip.xor", {0x3F}}}},
      {"meshopt-mode-triangles-for-attributes", nullptr,
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {7}}, {"x.mo.pos.mode", {1}}}},
      {"meshopt-quaternion-filter-stride-12", nullptr,
       S{{"x.geo", {2}}, {"x.mo.pos.lie", {8}}, {"x.mo.pos.filter", {2}}}},
      {"meshopt-stride-257", nullptr, S{{"x.geo", {2}}, {"x.mo.pos.lie", {9}}, {"x.mo.pos.stride", {9}}}},
      {"meshopt-count-2p64m1", nullptr, S{{"x.geo", {2}}, {"x.mo.pos.lie", {12}}, {"x.mo.pos.count", {~uint64_t{0}}}}},
      {"meshopt-fallback-with-uri", nullptr, S{{"x.geo", {2}}, {"x.mo.fallback", {2}}}},
      // KHR_draco_mesh_compression: real streams, then lies.
      {"draco-sequential-uv", nullptr, S{{"x.geo", {3}}, {"x.verts", {20}}, {"x.tris", {15}}, {"x.uv", {1}}}},
      {"draco-edgebreaker-quantized", nullptr,
       S{{"x.geo", {3}}, {"x.verts", {40}}, {"x.tris", {50}}, {"x.draco.edgebreaker", {1}}, {"x.draco.bits", {1}}}},
      {"draco-announces-2p31-faces", "issue45-structure-draco-announces-2p31-faces",
       S{{"x.geo", {3}}, {"x.draco.lie", {1}}, {"x.draco.faces", {3}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"draco-announces-2p32m1-faces-2p31-points", nullptr,
       S{{"x.geo", {3}}, {"x.draco.edgebreaker", {1}}, {"x.draco.lie", {3}}, {"x.draco.faces", {4}},
         {"x.draco.points", {3}}}},
      {"draco-announces-2p24m1-faces", nullptr, S{{"x.geo", {3}}, {"x.draco.lie", {1}}, {"x.draco.faces", {2}}}},
      {"draco-announces-faces-under-the-cap", nullptr, S{{"x.geo", {3}}, {"x.draco.lie", {15}}}},
      {"draco-truncated", nullptr,
       S{{"x.geo", {3}}, {"x.tris", {10}}, {"x.draco.lie", {4}}, {"x.draco.cut.keep", {20}}}},
      {"draco-no-such-attribute", nullptr, S{{"x.geo", {3}}, {"x.draco.lie", {6}}, {"x.draco.id", {5}}}},
      {"draco-position-is-the-uv", nullptr, S{{"x.geo", {3}}, {"x.uv", {1}}, {"x.draco.lie", {8}}}},
      {"draco-accessor-count-2p40", nullptr,
       S{{"x.geo", {3}}, {"x.draco.lie", {9}}, {"x.draco.accessor_count", {9}}}},
      {"draco-point-cloud-header", nullptr, S{{"x.geo", {3}}, {"x.draco.lie", {13}}}},
      {"draco-view-past-buffer", nullptr, S{{"x.geo", {3}}, {"x.draco.lie", {12}}, {"x.draco.more", {100}}}},
      // EXT_mesh_gpu_instancing: counts to 2^40, sparse, degenerate scales.
      {"instancing-2p40-sparse-zero-triangles", "issue45-structure-instancing-2p40-sparse-zero-triangles",
       S{{"graph.n", {1}}, {"x.inst", {1}}, {"x.inst.node", {1}}, {"x.inst.mesh", {1}}, {"x.inst.count", {9}},
         {"x.inst.TRANSLATION.storage", {1}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"instancing-2p23-sparse", nullptr,
       S{{"graph.n", {1}}, {"x.inst", {1}}, {"x.inst.node", {1}}, {"x.inst.count", {4}},
         {"x.inst.TRANSLATION.storage", {1}}}},
      {"instancing-2p24p1-sparse-spread", nullptr,
       S{{"x.inst", {1}}, {"x.inst.count", {6}}, {"x.inst.TRANSLATION.storage", {2}},
         {"x.inst.TRANSLATION.sparse_at", {2}}}},
      {"instancing-2p40-dense", nullptr, S{{"x.inst", {1}}, {"x.inst.attrs", {3}}, {"x.inst.count", {9}}}},
      {"instance-scale-1e-40", "issue45-structure-instance-scale-1e-40",
       S{{"x.inst", {1}}, {"x.inst.attrs", {4}}, {"x.inst.SCALE.edge", {7}}, {"x.inst.SCALE.at", {1}},
         {"x.inst.SCALE.component", {3}}, {"buf0.uri", {kAsBin0DataUri}}}},
      {"instance-scale-0", nullptr,
       S{{"x.inst", {1}}, {"x.inst.attrs", {4}}, {"x.inst.SCALE.edge", {8}}, {"x.inst.SCALE.component", {3}}}},
      {"instance-scale-nan", nullptr, S{{"x.inst", {1}}, {"x.inst.attrs", {4}}, {"x.inst.SCALE.edge", {1}}}},
      {"instance-translation-inf", nullptr,
       S{{"x.inst", {1}}, {"x.inst.n", {3}}, {"x.inst.TRANSLATION.edge", {2}}, {"x.inst.TRANSLATION.at", {2}}}},
      {"instance-rotation-quaternion-meshopt", nullptr,
       S{{"x.inst", {1}}, {"x.inst.attrs", {2}}, {"x.inst.n", {15}}, {"x.inst.ROTATION.ct", {1}},
         {"x.inst.ROTATION.storage", {3}}, {"x.inst.ROTATION.quaternion", {1}}, {"x.inst.ROTATION.bits", {8}}}},
      {"instancing-meshopt-announces-1gib", nullptr,
       S{{"x.inst", {1}}, {"x.inst.TRANSLATION.storage", {3}}, {"x.inst.TRANSLATION.mo.lie", {1}}}},
      {"instancing-chain-1000-deepest", nullptr,
       S{{"graph.shape", {1}}, {"graph.depth", {999}}, {"x.inst", {1}}, {"x.inst.node", {1}}, {"x.inst.n", {15}}}},
      {"instancing-dag-20-every-node", nullptr,
       S{{"graph.shape", {2}}, {"graph.levels", {19}}, {"graph.mesh_at", {1}}, {"x.inst", {2}}, {"x.inst.n", {3}}}},
      {"instancing-count-mismatch", nullptr, S{{"x.inst", {1}}, {"x.inst.attrs", {3}}, {"x.inst.mismatch", {2}}}},
      {"instancing-no-mesh", nullptr, S{{"graph.n", {2}}, {"x.inst", {1}}, {"x.inst.mesh", {2}}}},
      {"instancing-required-glb-file", nullptr,
       S{{"container", {1}}, {"x.inst", {1}}, {"x.inst.required", {1}}, {"x.buf.file", {1}}}},
      {"instancing-draco", nullptr, S{{"x.geo", {3}}, {"x.inst", {1}}, {"x.inst.n", {7}}, {"x.inst.attrs", {7}}}},
  };
}

bool SameDocument(const Document& a, const Document& b) {
  return a.glb == b.glb && a.explicit_root == b.explicit_root && a.main == b.main && a.files == b.files &&
         a.escapes == b.escapes && a.opaque_values == b.opaque_values;
}

void WriteSeeds(const fs::path& corpus) {
  const Env& env = TheEnv();
  fs::create_directories(corpus / "structure");
  for (const Seed& seed : Seeds()) {
    ScriptChoices script(seed.script);
    const Document d = Generate(script, env);
    std::string missing;
    if (!script.AllUsed(&missing)) {
      std::fprintf(stderr, "seed %s: decision %s was never asked for\n", seed.name, missing.c_str());
      std::exit(2);
    }
    const Bytes data = script.Data();
    FuzzedDataProvider fdp(data.data(), data.size());
    FuzzChoices replay(fdp);
    if (!SameDocument(Generate(replay, env), d) || fdp.remaining_bytes() != 0) {
      std::fprintf(stderr, "seed %s: its bytes do not replay to the same document\n", seed.name);
      std::exit(2);
    }
    WriteFile(corpus / "structure" / seed.name, data);
    if (seed.gltf_name) {
      if (d.glb || !d.files.empty()) {
        std::fprintf(stderr, "seed %s: not one self-contained .gltf\n", seed.name);
        std::exit(2);
      }
      Bytes file = {0};  // even first byte: .gltf
      file.insert(file.end(), d.main.begin(), d.main.end());
      WriteFile(corpus / "gltf" / seed.gltf_name, file);
    }
    std::printf("%-36s %6zu bytes -> %zu-byte %s\n", seed.name, data.size(), d.main.size(), d.Name().c_str());
  }
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  if (const char* corpus = std::getenv("VISQ_FUZZ_WRITE_SEEDS")) {
    WriteSeeds(corpus);
    std::exit(0);
  }
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const Env& env = TheEnv();
  FuzzedDataProvider fdp(data, size);
  FuzzChoices choices(fdp);
  LoadAndCheck(Generate(choices, env), env);
  return 0;
}
