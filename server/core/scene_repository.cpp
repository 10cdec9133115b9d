#include "core/scene_repository.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <fstream>
#include <random>
#include <set>
#include <thread>

#include <absl/strings/ascii.h>
#include <absl/strings/escaping.h>
#include <absl/strings/match.h>
#include <absl/strings/numbers.h>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "core/file_errors.h"

namespace visq::core {
namespace fs = std::filesystem;
namespace {

constexpr size_t kMaxNameLength = 128;
constexpr size_t kMaxReplicaIdLength = 64;
constexpr std::string_view kHidden = ".visq";
constexpr std::string_view kOwnerLock = ".owner";
constexpr std::string_view kCatalogKind = "catalog-kind";
// The layout before the catalog: an upload's folder named its main file and
// its version in these, a counter file numbered versions, and uploads were
// staged at the top of the folder.
constexpr std::string_view kLegacyMainMarker = ".visq-main";
constexpr std::string_view kLegacyVersionMarker = ".visq-version";
constexpr std::string_view kLegacyCounter = ".visq-version-counter";
constexpr std::string_view kLegacyStagingPrefix = ".staging-";
// The last version number the layout before the catalog handed out: a
// migrated scene keeps its number only if it is at most this.
constexpr absl::string_view kLegacyCounterMeta = "legacy_counter";
// A repository's SQLite catalog names itself with a random id when it moves
// to PostgreSQL, and PostgreSQL's meta keeps the id of the catalog it took
// over: a replica that finds it there knows the move made (by another
// replica, or by a start that crashed before it recorded the kind).
constexpr absl::string_view kRepositoryIdMeta = "repository_id";
constexpr absl::string_view kMovedFromSqliteMeta = "moved_from_sqlite";

bool IsSceneFile(const fs::path& path) {
  const std::string ext = path.extension().string();
  return ext == ".gltf" || ext == ".glb";
}

// A relative file name inside an upload: no absolute paths, no "..", no
// hidden components (which are the repository's own).
Status ValidateUploadFile(absl::string_view file) {
  if (file.empty() || file.size() > 512) return absl::InvalidArgumentError("chunk.file: empty or too long");
  const fs::path path{std::string(file)};
  if (path.is_absolute()) return absl::InvalidArgumentError(absl::StrCat("chunk.file '", file, "': absolute path"));
  for (const auto& part : path) {
    const std::string s = part.string();
    if (s == ".." || s == "." || s.empty() || s[0] == '.')
      return absl::InvalidArgumentError(absl::StrCat("chunk.file '", file, "': '", s, "' is not allowed"));
    if (s.size() > 255)
      return absl::InvalidArgumentError(
          absl::StrCat("chunk.file: a name of ", s.size(), " bytes; a file or folder name holds at most 255"));
    for (char c : s)
      if (c == '\\' || c == '\0' || static_cast<unsigned char>(c) < 0x20)
        return absl::InvalidArgumentError(absl::StrCat("chunk.file '", file, "': control or backslash character"));
  }
  return absl::OkStatus();
}

// Seeded again in a forked child: with its parent's generator state it
// would repeat the parent's names, and a sibling killed between creating a
// temporary file and renaming it would leave the next one's name taken
// (O_EXCL: the catalog kind's record failed, and with it the start).
std::string RandomSuffix() {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  static thread_local pid_t seeded_in = ::getpid();
  if (const pid_t pid = ::getpid(); pid != seeded_in) {
    rng.seed(std::random_device{}());
    seeded_in = pid;
  }
  return absl::StrCat(absl::Hex(rng(), absl::kZeroPad16));
}

std::optional<std::string> ReadSmallFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::string text(600, '\0');
  in.read(text.data(), static_cast<std::streamsize>(text.size()));
  text.resize(static_cast<size_t>(in.gcount()));
  return std::string(absl::StripAsciiWhitespace(text));
}

uint64_t ReadNumberFile(const fs::path& path) {
  uint64_t value = 0;
  const std::optional<std::string> text = ReadSmallFile(path);
  if (!text || !absl::SimpleAtoi(*text, &value)) return 0;
  return value;
}

// A descriptor closed with its owner.
struct OwnedFd {
  int fd = -1;
  explicit OwnedFd(int f) : fd(f) {}
  ~OwnedFd() {
    if (fd >= 0) ::close(fd);
  }
  OwnedFd(const OwnedFd&) = delete;
  OwnedFd& operator=(const OwnedFd&) = delete;
  int release() { return std::exchange(fd, -1); }
};

// ---------------------------------------------------------------------------
// Scenes placed at the top of the folder by hand, or uploads of the layout
// before the catalog: what to import for each.

struct HandPlaced {
  std::string name;
  fs::path entry;                                    // the folder, or the .gltf/.glb
  std::string main_file;                             // relative to `base`
  fs::path base;                                     // the folder its files are relative to
  std::vector<std::string> files;                    // relative to `base`, the main file among them
  uint64_t version = 0;                              // from the old layout's marker; 0: none
};

// The buffers a glTF at the top of the folder reads beside it (images are
// never read: the scene model keeps no textures). A .glb's JSON is its first
// chunk.
StatusOr<std::vector<std::string>> ReferencedBuffers(const fs::path& main_file) {
  std::ifstream in(main_file, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", main_file.filename().string()));
  std::string text;
  if (main_file.extension() == ".glb") {
    uint32_t header[5] = {};
    in.read(reinterpret_cast<char*>(header), sizeof(header));
    // magic "glTF", version, length, then the JSON chunk's length and type.
    if (in.gcount() != sizeof(header) || header[0] != 0x46546C67u || header[4] != 0x4E4F534Au || header[3] > (64u << 20))
      return absl::InvalidArgumentError(absl::StrCat(main_file.filename().string(), ": not a glTF binary"));
    text.resize(header[3]);
    in.read(text.data(), static_cast<std::streamsize>(text.size()));
  } else {
    text.assign(std::istreambuf_iterator<char>(in), {});
  }
  const nlohmann::json doc = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded() || !doc.is_object())
    return absl::InvalidArgumentError(absl::StrCat(main_file.filename().string(), ": not JSON"));
  std::vector<std::string> uris;
  if (doc.contains("buffers") && doc["buffers"].is_array())
    for (const auto& buffer : doc["buffers"])
      if (buffer.is_object() && buffer.contains("uri") && buffer["uri"].is_string()) {
        const std::string uri = buffer["uri"].get<std::string>();
        if (absl::StartsWith(uri, "data:")) continue;
        // Percent-escapes, as URIs may carry them (a space as %20).
        std::string decoded;
        for (size_t i = 0; i < uri.size(); ++i) {
          int hex = 0;
          if (uri[i] == '%' && i + 2 < uri.size() && absl::SimpleHexAtoi(uri.substr(i + 1, 2), &hex)) {
            decoded.push_back(static_cast<char>(hex));
            i += 2;
          } else {
            decoded.push_back(uri[i]);
          }
        }
        uris.push_back(decoded);
      }
  return uris;
}

// What a top-level entry holds, or nullopt for an entry that is no scene
// (the repository's own files, logs, stray data).
StatusOr<std::optional<HandPlaced>> ReadHandPlaced(const fs::path& root, const fs::directory_entry& entry) {
  const std::string file = entry.path().filename().string();
  std::error_code ec;
  HandPlaced found;
  found.entry = entry.path();
  if (entry.is_directory(ec)) {
    if (!SceneRepository::ValidateName(file).ok()) return std::optional<HandPlaced>();
    found.name = file;
    found.base = entry.path();
    // Every regular file below (links only when they stay inside the
    // repository), the old layout's markers aside.
    const std::string root_prefix = root.string() + "/";
    for (auto it = fs::recursive_directory_iterator(entry.path(), ec); !ec && it != fs::recursive_directory_iterator();
         it.increment(ec)) {
      const fs::path relative = it->path().lexically_relative(entry.path());
      if (!ValidateUploadFile(relative.string()).ok()) {
        if (it->is_directory()) it.disable_recursion_pending();
        continue;
      }
      std::error_code inner;
      const fs::path resolved = fs::weakly_canonical(it->path(), inner);
      if (inner || resolved.string().rfind(root_prefix, 0) != 0) continue;
      if (fs::is_regular_file(resolved, inner)) found.files.push_back(relative.string());
    }
    if (ec) return absl::InternalError(absl::StrCat("scene folder '", file, "': ", ec.message()));
    if (std::optional<std::string> main = ReadSmallFile(entry.path() / std::string(kLegacyMainMarker))) {
      found.main_file = *main;
    } else {
      std::vector<std::string> mains;
      for (const std::string& f : found.files)
        if (f.find('/') == std::string::npos && IsSceneFile(f)) mains.push_back(f);
      if (mains.size() != 1)
        return absl::InvalidArgumentError(
            absl::StrCat("scene folder '", file, "' holds ", mains.size(), " .gltf/.glb files, expected exactly one"));
      found.main_file = mains[0];
    }
    if (std::find(found.files.begin(), found.files.end(), found.main_file) == found.files.end())
      return absl::InvalidArgumentError(absl::StrCat("scene folder '", file, "': main file missing"));
    found.version = ReadNumberFile(entry.path() / std::string(kLegacyVersionMarker));
    return std::optional<HandPlaced>(std::move(found));
  }
  if (!entry.is_regular_file(ec) || !IsSceneFile(entry.path())) return std::optional<HandPlaced>();
  found.name = entry.path().stem().string();
  if (!SceneRepository::ValidateName(found.name).ok()) return std::optional<HandPlaced>();
  found.base = root;
  found.main_file = file;
  found.files.push_back(file);
  // A file whose buffers cannot be told (not glTF, a buffer missing or
  // outside the folder) is imported as it is: its load says what is wrong,
  // as it would have before.
  StatusOr<std::vector<std::string>> buffers = ReferencedBuffers(entry.path());
  if (!buffers.ok()) spdlog::warn("{}: {}; imported alone", file, buffers.status().message());
  for (const std::string& buffer : buffers.value_or(std::vector<std::string>())) {
    if (Status valid = ValidateUploadFile(buffer); !valid.ok() || !fs::is_regular_file(root / buffer, ec)) {
      spdlog::warn("{}: its buffer '{}' is not beside it; imported without", file, buffer);
      continue;
    }
    if (std::find(found.files.begin(), found.files.end(), buffer) == found.files.end()) found.files.push_back(buffer);
  }
  return std::optional<HandPlaced>(std::move(found));
}

}  // namespace

// ---------------------------------------------------------------------------
// UploadStaging

UploadStaging::UploadStaging(fs::path dir, std::string name, std::string main_file, uint64_t max_bytes)
    : dir_(std::move(dir)), name_(std::move(name)), main_file_(std::move(main_file)), max_bytes_(max_bytes) {}

UploadStaging::~UploadStaging() {
  if (open_fd_ >= 0) ::close(open_fd_);
  // A committed upload's files are blobs by now (links of their own).
  std::error_code ec;
  fs::remove_all(dir_, ec);
}

Status UploadStaging::Append(absl::string_view file, absl::string_view data) {
  VISQ_RETURN_IF_ERROR(ValidateUploadFile(file));
  if (bytes_ + data.size() > max_bytes_)
    return absl::ResourceExhaustedError(
        absl::StrCat("upload exceeds the server's upload limit of ", max_bytes_, " bytes (--max-upload-bytes)"));
  if (open_fd_ < 0 || files_.empty() || file != files_.back().path) {
    // Chunks of one file arrive together; a file seen before must not reopen.
    for (const File& seen : files_)
      if (seen.path == file)
        return absl::InvalidArgumentError(absl::StrCat("chunk.file '", file, "': chunks of a file must be contiguous"));
    VISQ_RETURN_IF_ERROR(CloseAll());
    const fs::path relative{std::string(file)};
    const fs::path path = dir_ / relative;
    VISQ_RETURN_IF_ERROR(MakeOwnerFolders(dir_, relative.parent_path()));
    open_fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0600);
    if (open_fd_ < 0) return ErrnoError("create", path);
    open_hash_ = std::make_unique<Sha256>();
    files_.push_back(File{std::string(file), 0, ""});
  }
  File& open = files_.back();
  size_t written = 0;
  while (written < data.size()) {
    const ssize_t n = ::write(open_fd_, data.data() + written, data.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      return ErrnoError("write", dir_ / open.path);
    }
    written += static_cast<size_t>(n);
  }
  open_hash_->Update(data);
  open.size += data.size();
  bytes_ += data.size();
  return absl::OkStatus();
}

StatusOr<size_t> UploadStaging::KeepOnly(const std::vector<fs::path>& needed) {
  VISQ_RETURN_IF_ERROR(CloseAll());
  std::set<fs::path> keep;
  std::error_code ec;
  for (const fs::path& path : needed) keep.insert(fs::weakly_canonical(path, ec));
  size_t removed = 0;
  std::vector<File> kept;
  for (File& file : files_) {
    const fs::path path = dir_ / fs::path(file.path);
    if (file.path == main_file_ || keep.count(fs::weakly_canonical(path, ec))) {
      kept.push_back(std::move(file));
      continue;
    }
    if (!fs::remove(path, ec) || ec) return ErrnoError("remove", path, ec ? ec.value() : ENOENT);
    ++removed;
  }
  files_ = std::move(kept);
  return removed;
}

Status UploadStaging::CloseAll() {
  if (open_fd_ >= 0) {
    // Durable before it can become a blob: a blob is never a torn file.
    const int rc = ::fsync(open_fd_);
    const int error = errno;
    ::close(open_fd_);
    open_fd_ = -1;
    if (rc != 0) return ErrnoError("fsync", dir_ / files_.back().path, error);
    files_.back().blob = open_hash_->HexDigest();
    open_hash_.reset();
  }
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------
// StoredSceneView

StoredSceneView::~StoredSceneView() {
  std::error_code ec;
  fs::remove_all(dir_, ec);
}

// ---------------------------------------------------------------------------
// SceneRepository

Status SceneRepository::ValidateName(absl::string_view name) {
  if (name.empty()) return absl::InvalidArgumentError("scene name is empty");
  if (name.size() > kMaxNameLength)
    return absl::InvalidArgumentError(absl::StrCat("scene name longer than ", kMaxNameLength, " characters"));
  if (name[0] == '.') return absl::InvalidArgumentError(absl::StrCat("scene name '", name, "' starts with '.'"));
  // "x.glb" is where a hand-placed scene "x" lies: the name would alias it.
  const std::string lower = absl::AsciiStrToLower(name);
  if (absl::EndsWith(lower, ".glb") || absl::EndsWith(lower, ".gltf"))
    return absl::InvalidArgumentError(
        absl::StrCat("scene name '", name, "' ends in .glb or .gltf (name the scene, not its file)"));
  for (char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '.' ||
                    c == '_' || c == '-';
    if (!ok)
      return absl::InvalidArgumentError(
          absl::StrCat("scene name '", name, "': only letters, digits, '.', '_' and '-' are allowed"));
  }
  return absl::OkStatus();
}

SceneRepository::SceneRepository(fs::path root, std::string replica_id, fs::path staging, int owner_fd,
                                 BlobStore blobs, std::unique_ptr<SceneCatalog> catalog)
    : root_(std::move(root)),
      replica_id_(std::move(replica_id)),
      staging_(std::move(staging)),
      owner_fd_(owner_fd),
      blobs_(std::move(blobs)),
      catalog_(std::move(catalog)) {}

SceneRepository::~SceneRepository() {
  if (owner_fd_ >= 0) ::close(owner_fd_);  // releases the replica's flock
}

namespace {

// The catalog's database from --catalog. The value may hold a password:
// messages never repeat it.
StatusOr<std::unique_ptr<CatalogDb>> OpenCatalogDb(const std::string& spec, const fs::path& hidden) {
  if (absl::StartsWith(spec, "postgresql://") || absl::StartsWith(spec, "postgres://"))
    return OpenPostgresCatalog(spec);
  std::string file = (hidden / "catalog.sqlite3").string();
  if (absl::StartsWith(spec, "sqlite:") && spec.size() > 7) {
    file = spec.substr(7);
  } else if (!spec.empty() && spec != "sqlite") {
    return absl::InvalidArgumentError(
        "--catalog: expected 'sqlite', 'sqlite:<file>' or a PostgreSQL URI (postgresql://user@host:port/database)");
  }
  // The catalog names every scene: its owner's alone, as the scenes are.
  // (SQLite gives its -wal and -shm files the database file's mode.)
  const int fd = ::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0600);
  if (fd < 0) return ErrnoError("create catalog", file);
  ::close(fd);
  return OpenSqliteCatalog(file);
}

std::string CatalogKindOf(const std::string& spec) {
  return absl::StartsWith(spec, "postgres") ? "postgresql" : "sqlite";
}

// Records which kind holds the catalog: a new file renamed over the old, so
// that a crash leaves one kind or the other, never an empty file.
Status RecordCatalogKind(const fs::path& kind_file, const std::string& kind) {
  const fs::path temporary = fs::path(kind_file).concat(absl::StrCat(".", RandomSuffix()));
  OwnedFd fd(::open(temporary.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600));
  if (fd.fd < 0) return ErrnoError("create", temporary);
  const std::string text = kind + "\n";
  if (::write(fd.fd, text.data(), text.size()) != static_cast<ssize_t>(text.size()) || ::fsync(fd.fd) != 0 ||
      ::rename(temporary.c_str(), kind_file.c_str()) != 0) {
    const Status failed = ErrnoError("write", kind_file);
    ::unlink(temporary.c_str());
    return failed;
  }
  return FsyncPath(kind_file.parent_path(), /*directory=*/true);
}

// Moves the catalog of a repository recorded as SQLite's into `target`, a
// PostgreSQL catalog, before the repository records its new kind: rows
// only, as the blobs are the repository's already. One transaction on the
// PostgreSQL side, so that a crash leaves all of it or nothing (moved at the
// next start); replicas starting together take turns on its write lock, and
// the later ones find the mark. The SQLite file stays as it is (see
// docs/deploy.md): the recorded kind refuses it from then on.
Status MoveCatalogFromSqlite(const fs::path& sqlite_file, SceneCatalog& target) {
  const auto start = std::chrono::steady_clock::now();
  std::error_code ec;
  if (!fs::is_regular_file(sqlite_file, ec))
    return absl::FailedPreconditionError(absl::StrCat(
        "--catalog: this repository's catalog is in sqlite, and its move to postgresql reads it from ",
        sqlite_file.string(), ", which is not there (a catalog kept elsewhere with sqlite:<file>: copy it there "
        "first, the server stopped)"));
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<CatalogDb> db, OpenSqliteCatalog(sqlite_file.string()));
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<SceneCatalog> source, SceneCatalog::Open(std::move(db)));
  VISQ_ASSIGN_OR_RETURN(const std::string id,
                        source->MetaOrInit(kRepositoryIdMeta, absl::StrCat(RandomSuffix(), RandomSuffix())));
  VISQ_ASSIGN_OR_RETURN(const SceneCatalog::Contents contents, source->ReadAll());
  VISQ_ASSIGN_OR_RETURN(const SceneCatalog::TakenOver taken, target.TakeOver(contents, kMovedFromSqliteMeta, id));
  const auto ms =
      std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start).count();
  switch (taken.outcome) {
    case SceneCatalog::TakenOver::Outcome::kOccupied:
      return absl::FailedPreconditionError(absl::StrCat(
          "--catalog: ", target.Describe(), " already holds ", taken.scenes,
          " scene(s) of another repository; this repository's catalog (in sqlite) moves only into a PostgreSQL "
          "catalog that holds no scene: give --catalog a database of its own (see docs/deploy.md, choosing the "
          "catalog)"));
    case SceneCatalog::TakenOver::Outcome::kAlreadyMoved:
      spdlog::info("scene catalog: {} was already moved to {} (by another replica, or before a crash)",
                   sqlite_file.string(), target.Describe());
      return absl::OkStatus();
    case SceneCatalog::TakenOver::Outcome::kMoved:
      spdlog::info("scene catalog moved from sqlite {} to {}: {} scene(s), {} file(s), counter {}, in {} ms",
                   sqlite_file.string(), target.Describe(), taken.scenes, taken.files, contents.counter, ms);
      return absl::OkStatus();
  }
  return absl::InternalError("scene catalog: unknown move outcome");
}

// Takes this replica's staging folder: its lock is held as long as the
// server runs. A process that died released it.
StatusOr<int> LockReplicaStaging(const fs::path& folder) {
  if (::mkdir(folder.c_str(), 0700) != 0 && errno != EEXIST) return ErrnoError("create staging folder", folder);
  OwnedFd fd(::open((folder / std::string(kOwnerLock)).c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW, 0600));
  if (fd.fd < 0) return ErrnoError("create", folder / std::string(kOwnerLock));
  // Another replica cleaning this folder after a crash holds the lock for
  // a moment: wait for it before concluding that a live server has it.
  for (int attempt = 0; attempt < 20; ++attempt) {
    if (::flock(fd.fd, LOCK_EX | LOCK_NB) == 0) return fd.release();
    if (errno != EWOULDBLOCK && errno != EINTR) return ErrnoError("lock", folder / std::string(kOwnerLock));
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return absl::AlreadyExistsError("held by a running server");
}

// Removes what a folder holds, its lock file aside.
void EmptyStaging(const fs::path& folder) {
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(folder, ec)) {
    if (entry.path().filename() == std::string(kOwnerLock)) continue;
    std::error_code inner;
    fs::remove_all(entry.path(), inner);
  }
}

}  // namespace

StatusOr<std::unique_ptr<SceneRepository>> SceneRepository::Open(const RepositoryOptions& options) {
  std::error_code ec;
  fs::create_directories(options.root, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("scene repository ", options.root.string(), ": ", ec.message()));
  const fs::path root = fs::canonical(options.root, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("scene repository ", root.string(), ": ", ec.message()));
  const fs::path hidden = root / std::string(kHidden);
  VISQ_RETURN_IF_ERROR(MakeOwnerFolders(root, fs::path(std::string(kHidden)) / "staging"));

  // Which database holds this repository's catalog is fixed at its first
  // start: a replica pointed at the other would see an empty catalog and
  // serve a repository without its scenes. SQLite's moves to PostgreSQL
  // (below, once the catalog is open); there is no way back.
  const std::string kind = CatalogKindOf(options.catalog);
  const fs::path kind_file = hidden / std::string(kCatalogKind);
  const std::optional<std::string> recorded_kind = ReadSmallFile(kind_file);
  const bool move_from_sqlite = recorded_kind && *recorded_kind == "sqlite" && kind == "postgresql";
  if (recorded_kind && *recorded_kind != kind && !move_from_sqlite)
    return absl::FailedPreconditionError(absl::StrCat("--catalog: this repository's catalog is in ", *recorded_kind,
                                                      ", not ", kind, " (there is no move from ", *recorded_kind,
                                                      " to ", kind, "; see docs/deploy.md, choosing the catalog)"));

  // This replica's staging, and whose it is.
  std::string replica_id = options.replica_id;
  const bool named = !replica_id.empty();
  if (!named) {
    char host[256] = {};
    ::gethostname(host, sizeof(host) - 1);
    replica_id = host;
    for (char& c : replica_id)
      if (!absl::ascii_isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_' && c != '.') c = '_';
    if (replica_id.empty() || replica_id[0] == '.') replica_id = "replica" + replica_id;
    replica_id = replica_id.substr(0, kMaxReplicaIdLength);
  } else {
    for (char c : replica_id)
      if (!absl::ascii_isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_')
        return absl::InvalidArgumentError(
            absl::StrCat("--replica-id '", absl::CHexEscape(replica_id), "': only letters, digits, '-' and '_'"));
    if (replica_id.size() > kMaxReplicaIdLength)
      return absl::InvalidArgumentError(absl::StrCat("--replica-id: longer than ", kMaxReplicaIdLength, " characters"));
  }
  const fs::path staging_root = hidden / "staging";
  StatusOr<int> owner = LockReplicaStaging(staging_root / replica_id);
  if (!owner.ok() && absl::IsAlreadyExists(owner.status())) {
    if (named)
      return absl::FailedPreconditionError(absl::StrCat("--replica-id '", replica_id,
                                                        "': a running server sharing this repository uses it; give "
                                                        "each replica its own"));
    // Two servers on one host, neither named: the second is told apart by
    // its pid (its staging is then cleaned when it is found unlocked).
    replica_id = absl::StrCat(replica_id, "-", ::getpid());
    owner = LockReplicaStaging(staging_root / replica_id);
  }
  if (!owner.ok()) return owner.status();
  OwnedFd owner_fd(*owner);
  const fs::path staging = staging_root / replica_id;

  // Staging left by this replica's last run never became anything. Other
  // replicas' staging is theirs while they run (they hold its lock); that
  // of a replica no longer running is emptied.
  EmptyStaging(staging);
  for (const auto& entry : fs::directory_iterator(staging_root, ec)) {
    if (entry.path() == staging) continue;
    // Every live replica holds its folder's lock file locked; a folder
    // without one has no live owner either.
    OwnedFd fd(::open((entry.path() / std::string(kOwnerLock)).c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW));
    if (fd.fd < 0 ? errno != ENOENT : ::flock(fd.fd, LOCK_EX | LOCK_NB) != 0) continue;
    spdlog::info("emptying the staging of replica {}, which is not running", entry.path().filename().string());
    EmptyStaging(entry.path());
  }
  // The layout before the catalog staged uploads at the top of the folder,
  // each holding its folder locked while it ran.
  for (const auto& entry : fs::directory_iterator(root, ec)) {
    const std::string file = entry.path().filename().string();
    if (file.rfind(kLegacyStagingPrefix, 0) != 0) continue;
    OwnedFd fd(::open(entry.path().c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW));
    if (fd.fd >= 0 && ::flock(fd.fd, LOCK_EX | LOCK_NB) != 0) continue;
    spdlog::warn("removing staging folder left by an interrupted upload: {}", file);
    std::error_code inner;
    fs::remove_all(entry.path(), inner);
  }

  VISQ_ASSIGN_OR_RETURN(BlobStore blobs, BlobStore::Open(hidden / "blobs"));
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<CatalogDb> db, OpenCatalogDb(options.catalog, hidden));
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<SceneCatalog> catalog, SceneCatalog::Open(std::move(db)));
  if (move_from_sqlite) VISQ_RETURN_IF_ERROR(MoveCatalogFromSqlite(hidden / "catalog.sqlite3", *catalog));
  if (!recorded_kind || move_from_sqlite) VISQ_RETURN_IF_ERROR(RecordCatalogKind(kind_file, kind));
  std::unique_ptr<SceneRepository> repository(new SceneRepository(
      root, replica_id, staging, owner_fd.release(), std::move(blobs), std::move(catalog)));
  spdlog::info("scene repository {}: catalog {}, replica {}", root.string(), repository->DescribeCatalog(), replica_id);

  // A repository of the layout before the catalog: its numbers go on where
  // its counter stopped, and its scenes keep theirs.
  uint64_t legacy = ReadNumberFile(root / std::string(kLegacyCounter));
  for (const auto& entry : fs::directory_iterator(root, ec))
    legacy = std::max(legacy, ReadNumberFile(entry.path() / std::string(kLegacyVersionMarker)));
  VISQ_ASSIGN_OR_RETURN(const std::optional<std::string> recorded, repository->catalog_->Meta(kLegacyCounterMeta));
  if (!recorded) VISQ_RETURN_IF_ERROR(repository->catalog_->SetMeta(kLegacyCounterMeta, absl::StrCat(legacy)));
  if (legacy > 0) VISQ_RETURN_IF_ERROR(repository->catalog_->RaiseCounter(legacy));
  VISQ_RETURN_IF_ERROR(repository->ImportHandPlaced(std::nullopt));
  // Blobs no version names: those of deleted and replaced versions, and
  // those a commit published before it failed.
  repository->Collect(repository->blobs_.List());
  return repository;
}

Status SceneRepository::ImportHandPlaced(const std::optional<std::string>& only) {
  std::error_code ec;
  std::vector<fs::directory_entry> entries;
  if (only) {
    for (const fs::path& path : {root_ / *only, root_ / (*only + ".glb"), root_ / (*only + ".gltf")})
      if (fs::exists(fs::symlink_status(path, ec))) entries.emplace_back(path);
  } else {
    for (const auto& entry : fs::directory_iterator(root_, ec)) entries.push_back(entry);
    std::sort(entries.begin(), entries.end());
  }
  if (entries.empty()) return absl::OkStatus();
  VISQ_ASSIGN_OR_RETURN(const std::optional<std::string> legacy_text, catalog_->Meta(kLegacyCounterMeta));
  uint64_t legacy_counter = 0;
  if (legacy_text && !absl::SimpleAtoi(*legacy_text, &legacy_counter)) legacy_counter = 0;

  std::vector<HandPlaced> imported;
  std::set<std::string> names_seen;
  for (const fs::directory_entry& entry : entries) {
    if (entry.path().filename().string()[0] == '.') continue;
    StatusOr<std::optional<HandPlaced>> read = ReadHandPlaced(root_, entry);
    if (!read.ok()) {
      spdlog::error("{} in the scene repository is not imported: {}", entry.path().filename().string(),
                    read.status().message());
      continue;
    }
    if (!read->has_value()) continue;
    HandPlaced& scene = **read;
    // "x/", "x.glb" and "x.gltf" would all be the scene x: the first wins.
    if (!names_seen.insert(scene.name).second) {
      spdlog::error("{} in the scene repository is not imported: another entry is the scene '{}'",
                    entry.path().filename().string(), scene.name);
      continue;
    }
    // Copied through a staging like an upload's: the hand-placed file may be
    // edited in place later, a blob never is.
    VISQ_ASSIGN_OR_RETURN(std::unique_ptr<UploadStaging> staging,
                          BeginUpload(scene.name, scene.main_file, std::numeric_limits<uint64_t>::max()));
    Status copied = absl::OkStatus();
    for (const std::string& file : scene.files) {
      std::ifstream in(scene.base / file, std::ios::binary);
      if (!in) {
        copied = absl::NotFoundError(absl::StrCat("cannot read ", file));
        break;
      }
      std::string chunk(1 << 20, '\0');
      do {
        in.read(chunk.data(), static_cast<std::streamsize>(chunk.size()));
        copied = staging->Append(file, absl::string_view(chunk.data(), static_cast<size_t>(in.gcount())));
      } while (copied.ok() && in.gcount() > 0);
      if (!copied.ok()) break;
    }
    bool stored = false;
    const uint64_t keep = scene.version <= legacy_counter ? scene.version : 0;
    StatusOr<Stored> committed =
        copied.ok() ? CommitFiles(*staging, /*replace=*/true, /*unless_unchanged=*/true, keep, &stored) : copied;
    if (!committed.ok()) {
      // Another replica importing the same entry may have removed it.
      if (fs::exists(fs::symlink_status(entry.path(), ec)))
        spdlog::error("{} in the scene repository is not imported: {}", entry.path().filename().string(),
                      committed.status().message());
      continue;
    }
    spdlog::info("scene '{}' {} from {} as v{}", scene.name, stored ? "imported" : "already in the catalog",
                 entry.path().filename().string(), committed->version);
    imported.push_back(std::move(scene));
  }

  // The imported entries go: the catalog has them now, and an entry left
  // there would be imported again over later uploads. A buffer beside a
  // top-level .gltf stays while another top-level glTF still reads it.
  std::set<fs::path> still_read;
  for (const auto& entry : fs::directory_iterator(root_, ec)) {
    if (!entry.is_regular_file() || !IsSceneFile(entry.path())) continue;
    if (std::any_of(imported.begin(), imported.end(), [&](const HandPlaced& s) { return s.entry == entry.path(); }))
      continue;
    if (StatusOr<std::vector<std::string>> buffers = ReferencedBuffers(entry.path()); buffers.ok())
      for (const std::string& buffer : *buffers) still_read.insert(root_ / buffer);
  }
  for (const HandPlaced& scene : imported) {
    std::error_code inner;
    if (scene.base == root_) {
      for (const std::string& file : scene.files)
        if (!still_read.count(root_ / file)) fs::remove(root_ / file, inner);
    } else {
      fs::remove_all(scene.entry, inner);
    }
  }
  if (!imported.empty()) (void)FsyncPath(root_, /*directory=*/true);
  return absl::OkStatus();
}

void SceneRepository::Collect(const std::vector<std::string>& blobs) {
  size_t removed = 0;
  const Status collected = catalog_->CollectBlobs(blobs, [&](const std::string& blob) {
    ++removed;
    return blobs_.Remove(blob);
  });
  if (!collected.ok()) spdlog::warn("scene repository: blobs not collected: {}", collected.message());
  if (removed > 0) spdlog::info("scene repository: {} blob(s) no version names removed", removed);
}

std::vector<std::string> SceneRepository::List() {
  StatusOr<std::vector<std::string>> names = catalog_->Names();
  if (!names.ok()) {
    spdlog::error("scene repository: cannot list the catalog: {}", names.status().message());
    return {};
  }
  return *std::move(names);
}

bool SceneRepository::Contains(absl::string_view name) {
  if (!ValidateName(name).ok()) return false;
  StatusOr<std::optional<CatalogVersion>> current = catalog_->Current(name);
  if (current.ok() && current->has_value()) return true;
  // A scene placed by hand while the server runs is taken in on first use.
  const Status imported = ImportHandPlaced(std::string(name));
  if (!imported.ok()) spdlog::error("scene '{}' not imported: {}", name, imported.message());
  current = catalog_->Current(name);
  return current.ok() && current->has_value();
}

StatusOr<uint64_t> SceneRepository::NextVersion() { return catalog_->NextVersion(); }

StatusOr<fs::path> SceneRepository::NewStagingFolder(absl::string_view prefix) const {
  const fs::path dir = staging_ / absl::StrCat(prefix, RandomSuffix());
  if (::mkdir(dir.c_str(), 0700) != 0) return ErrnoError("create staging folder", dir);
  return dir;
}

StatusOr<std::unique_ptr<UploadStaging>> SceneRepository::BeginUpload(absl::string_view name,
                                                                      absl::string_view main_file,
                                                                      uint64_t max_bytes) {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  VISQ_RETURN_IF_ERROR(ValidateUploadFile(main_file));
  if (!IsSceneFile(fs::path(std::string(main_file))))
    return absl::InvalidArgumentError(absl::StrCat("upload_main_file '", main_file, "': not a .gltf or .glb"));
  VISQ_ASSIGN_OR_RETURN(const fs::path dir, NewStagingFolder("upload-"));
  return std::unique_ptr<UploadStaging>(
      new UploadStaging(dir, std::string(name), std::string(main_file), max_bytes));
}

StatusOr<SceneRepository::Stored> SceneRepository::Commit(UploadStaging& staging, bool replace) {
  bool stored = false;
  return CommitFiles(staging, replace, /*unless_unchanged=*/false, /*keep_version=*/0, &stored);
}

StatusOr<SceneRepository::Stored> SceneRepository::CommitFiles(UploadStaging& staging, bool replace,
                                                               bool unless_unchanged, uint64_t keep_version,
                                                               bool* stored) {
  VISQ_RETURN_IF_ERROR(staging.CloseAll());
  SceneCatalog::CommitRequest request;
  request.name = staging.name_;
  request.main_file = staging.main_file_;
  request.replace = replace;
  request.unless_unchanged = unless_unchanged;
  request.keep_version = keep_version;
  bool has_main = false;
  for (const UploadStaging::File& file : staging.files_) {
    request.files.push_back(CatalogFile{file.path, file.blob, file.size});
    has_main |= file.path == staging.main_file_;
  }
  if (!has_main)
    return absl::InvalidArgumentError(absl::StrCat("header.upload_main_file '", staging.main_file_,
                                                   "': never sent (no chunk carries that file); nothing stored"));
  VISQ_ASSIGN_OR_RETURN(const SceneCatalog::Committed committed,
                        catalog_->Commit(request, [&](const CatalogFile& file) {
                          return blobs_.Publish(staging.dir_ / file.path, file.blob);
                        }));
  *stored = committed.stored;
  Collect(committed.released);
  return Stored{committed.version};
}

StatusOr<std::unique_ptr<StoredSceneView>> SceneRepository::Checkout(absl::string_view name) {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  // A version replaced by another replica between reading the catalog and
  // linking its blobs may have lost them to collection: read the catalog
  // again, which now names the newer version.
  constexpr int kAttempts = 4;
  Status last;
  for (int attempt = 0; attempt < kAttempts; ++attempt) {
    VISQ_ASSIGN_OR_RETURN(std::optional<CatalogVersion> current, catalog_->Current(name));
    if (!current && attempt == 0 && Contains(name)) {  // placed by hand since the start
      VISQ_ASSIGN_OR_RETURN(current, catalog_->Current(name));
    }
    if (!current) return absl::NotFoundError(absl::StrCat("scene '", name, "' is not in the repository"));
    VISQ_ASSIGN_OR_RETURN(const fs::path dir, NewStagingFolder("load-"));
    std::unique_ptr<StoredSceneView> view(new StoredSceneView(dir, current->name, current->version, current->main_file));
    last = absl::OkStatus();
    for (const CatalogFile& file : current->files) {
      // The catalog's paths were checked as the upload's were; a catalog
      // edited by hand is still not followed out of the view.
      if (Status valid = ValidateUploadFile(file.path); !valid.ok())
        return absl::DataLossError(absl::StrCat("scene '", name, "' v", current->version, ": ", valid.message()));
      const fs::path relative(file.path);
      last = MakeOwnerFolders(dir, relative.parent_path());
      if (last.ok()) last = blobs_.LinkTo(file.blob, file.size, dir / relative);
      if (!last.ok()) break;
    }
    if (last.ok()) return view;
    if (!absl::IsNotFound(last)) return last;
  }
  return absl::DataLossError(absl::StrCat("scene '", name, "': ", last.message()));
}

Status SceneRepository::Remove(absl::string_view name) {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  StatusOr<std::vector<std::string>> released = catalog_->Remove(name);
  // A scene placed by hand and never used is still the operator's to delete.
  if (absl::IsNotFound(released.status()) && Contains(name)) released = catalog_->Remove(name);
  VISQ_RETURN_IF_ERROR(released.status());
  Collect(*released);
  return absl::OkStatus();
}

}  // namespace visq::core
