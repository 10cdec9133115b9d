#include "core/scene_repository.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <random>
#include <set>

#include <absl/strings/ascii.h>
#include <absl/strings/match.h>
#include <absl/strings/numbers.h>
#include <spdlog/spdlog.h>

namespace visq::core {
namespace fs = std::filesystem;
namespace {

constexpr size_t kMaxNameLength = 128;
constexpr std::string_view kStagingPrefix = ".staging-";
constexpr std::string_view kMainFileMarker = ".visq-main";
constexpr std::string_view kVersionMarker = ".visq-version";
constexpr std::string_view kVersionCounter = ".visq-version-counter";

// Names the file, not where the repository lives: messages reach clients.
// A full disk or quota is the caller's to act on (RESOURCE_EXHAUSTED).
// A repository the server may not write is the operator's to fix
// (FAILED_PRECONDITION); an upload whose files clash (a file where another
// chunk made a folder, or the reverse) is the client's (INVALID_ARGUMENT).
Status ErrnoError(absl::string_view what, const fs::path& path) {
  const int error = errno;
  const std::string message = absl::StrCat(what, " ", path.filename().string(), ": ", std::strerror(error));
  if (error == ENOSPC || error == EDQUOT) return absl::ResourceExhaustedError(message);
  if (error == EACCES || error == EPERM || error == EROFS)
    return absl::FailedPreconditionError(absl::StrCat(message, " (the scene repository, --scene-repo, is not writable)"));
  if (error == ENOTDIR || error == EISDIR || error == EEXIST)
    return absl::InvalidArgumentError(absl::StrCat("chunk.file: ", message, " (a file and a folder of the upload clash)"));
  return absl::InternalError(message);
}

Status ErrorCodeError(absl::string_view what, const fs::path& path, const std::error_code& ec) {
  errno = ec.value();
  if (ec.category() == std::generic_category() || ec.category() == std::system_category()) return ErrnoError(what, path);
  return absl::InternalError(absl::StrCat(what, " ", path.filename().string(), ": ", ec.message()));
}

// Folders an upload makes are its owner's alone (0700), as its files are
// (0600): a shared machine's other users read no uploaded scene.
Status MakeOwnerFolders(const fs::path& root, const fs::path& relative) {
  fs::path path = root;
  for (const fs::path& part : relative) {
    path /= part;
    if (::mkdir(path.c_str(), 0700) != 0 && errno != EEXIST) return ErrnoError("create", path);
    struct stat info {};
    if (::lstat(path.c_str(), &info) != 0 || !S_ISDIR(info.st_mode)) {
      errno = ENOTDIR;
      return ErrnoError("create", path);
    }
  }
  return absl::OkStatus();
}

bool IsSceneFile(const fs::path& path) {
  const std::string ext = path.extension().string();
  return ext == ".gltf" || ext == ".glb";
}

Status FsyncPath(const fs::path& path, bool directory) {
  const int fd = ::open(path.c_str(), (directory ? O_DIRECTORY : 0) | O_RDONLY | O_CLOEXEC);
  if (fd < 0) return ErrnoError("open for fsync", path);
  const int rc = ::fsync(fd);
  ::close(fd);
  if (rc != 0) return ErrnoError("fsync", path);
  return absl::OkStatus();
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

std::string RandomSuffix() {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  return absl::StrCat(absl::Hex(rng(), absl::kZeroPad16));
}

}  // namespace

// ---------------------------------------------------------------------------
// UploadStaging

UploadStaging::UploadStaging(fs::path dir, std::string name, std::string main_file, uint64_t max_bytes)
    : dir_(std::move(dir)), name_(std::move(name)), main_file_(std::move(main_file)), max_bytes_(max_bytes) {}

UploadStaging::~UploadStaging() {
  if (open_fd_ >= 0) ::close(open_fd_);
  if (lock_fd_ >= 0) ::close(lock_fd_);  // releases the flock
  if (!committed_) {
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }
}

Status UploadStaging::Append(absl::string_view file, absl::string_view data) {
  VISQ_RETURN_IF_ERROR(ValidateUploadFile(file));
  if (bytes_ + data.size() > max_bytes_)
    return absl::ResourceExhaustedError(
        absl::StrCat("upload exceeds the server's upload limit of ", max_bytes_, " bytes (--max-upload-bytes)"));
  if (file != open_file_) {
    // Chunks of one file arrive together; a file seen before must not reopen.
    if (std::find(files_.begin(), files_.end(), std::string(file)) != files_.end())
      return absl::InvalidArgumentError(absl::StrCat("chunk.file '", file, "': chunks of a file must be contiguous"));
    if (open_fd_ >= 0) {
      if (::fsync(open_fd_) != 0) return ErrnoError("fsync", dir_ / open_file_);
      ::close(open_fd_);
      open_fd_ = -1;
    }
    const fs::path relative{std::string(file)};
    const fs::path path = dir_ / relative;
    VISQ_RETURN_IF_ERROR(MakeOwnerFolders(dir_, relative.parent_path()));
    open_fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0600);
    if (open_fd_ < 0) return ErrnoError("create", path);
    open_file_ = std::string(file);
    files_.push_back(open_file_);
  }
  size_t written = 0;
  while (written < data.size()) {
    const ssize_t n = ::write(open_fd_, data.data() + written, data.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      return ErrnoError("write", dir_ / open_file_);
    }
    written += static_cast<size_t>(n);
  }
  bytes_ += data.size();
  return absl::OkStatus();
}

StatusOr<size_t> UploadStaging::KeepOnly(const std::vector<fs::path>& needed) {
  VISQ_RETURN_IF_ERROR(CloseAll());
  std::set<fs::path> keep;
  std::error_code ec;
  for (const fs::path& path : needed) keep.insert(fs::weakly_canonical(path, ec));
  size_t removed = 0;
  std::vector<std::string> kept;
  for (const std::string& file : files_) {
    const fs::path path = dir_ / fs::path(file);
    if (file == main_file_ || keep.count(fs::weakly_canonical(path, ec))) {
      kept.push_back(file);
      continue;
    }
    if (!fs::remove(path, ec) || ec) return ErrorCodeError("remove", path, ec);
    ++removed;
  }
  files_ = std::move(kept);
  return removed;
}

Status UploadStaging::CloseAll() {
  if (open_fd_ >= 0) {
    if (::fsync(open_fd_) != 0) return ErrnoError("fsync", dir_ / open_file_);
    ::close(open_fd_);
    open_fd_ = -1;
  }
  open_file_.clear();
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------
// SceneRepository

Status SceneRepository::ValidateName(absl::string_view name) {
  if (name.empty()) return absl::InvalidArgumentError("scene name is empty");
  if (name.size() > kMaxNameLength)
    return absl::InvalidArgumentError(absl::StrCat("scene name longer than ", kMaxNameLength, " characters"));
  if (name[0] == '.') return absl::InvalidArgumentError(absl::StrCat("scene name '", name, "' starts with '.'"));
  // "x.glb" is where the scene "x" may be stored: the name would alias it.
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

StatusOr<std::unique_ptr<SceneRepository>> SceneRepository::Open(const fs::path& root) {
  std::error_code ec;
  fs::create_directories(root, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("scene repository ", root.string(), ": ", ec.message()));
  const fs::path canonical = fs::canonical(root, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("scene repository ", root.string(), ": ", ec.message()));
  // Staging folders left by a crash never became scenes: remove them, but
  // not those of uploads in flight on a replica sharing the repository,
  // which hold their folder locked. (One made a moment ago and not locked
  // yet is taken here: its upload fails at its own lock, with an error.)
  for (const auto& entry : fs::directory_iterator(canonical, ec)) {
    const std::string file = entry.path().filename().string();
    if (file.rfind(kStagingPrefix, 0) != 0) continue;
    const int fd = ::open(entry.path().c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
    if (fd >= 0 && ::flock(fd, LOCK_EX | LOCK_NB) != 0) {
      ::close(fd);
      spdlog::info("staging folder {} belongs to an upload in flight elsewhere: kept", file);
      continue;
    }
    spdlog::warn("removing staging folder left by an interrupted upload: {}", file);
    fs::remove_all(entry.path(), ec);
    if (fd >= 0) ::close(fd);
  }
  return std::unique_ptr<SceneRepository>(new SceneRepository(canonical));
}

std::vector<std::string> SceneRepository::List() const {
  std::set<std::string> names;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(root_, ec)) {
    const fs::path& path = entry.path();
    std::string name = entry.is_directory() ? path.filename().string() : path.stem().string();
    if (!ValidateName(name).ok()) continue;
    if (entry.is_directory() || IsSceneFile(path))
      if (MainFile(name).ok()) names.insert(name);
  }
  return {names.begin(), names.end()};
}

StatusOr<fs::path> SceneRepository::MainFile(absl::string_view name) const {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  std::error_code ec;
  const fs::path folder = root_ / std::string(name);
  fs::path candidate;
  if (fs::is_directory(folder, ec)) {
    // An uploaded folder names its main file; a hand-made one has exactly one.
    std::FILE* marker = std::fopen((folder / std::string(kMainFileMarker)).c_str(), "r");
    if (marker != nullptr) {
      char buffer[600] = {};
      const size_t n = std::fread(buffer, 1, sizeof(buffer) - 1, marker);
      std::fclose(marker);
      std::string main(buffer, n);
      while (!main.empty() && (main.back() == '\n' || main.back() == ' ')) main.pop_back();
      VISQ_RETURN_IF_ERROR(ValidateUploadFile(main));
      candidate = folder / main;
    } else {
      std::vector<fs::path> found;
      for (const auto& entry : fs::directory_iterator(folder, ec))
        if (entry.is_regular_file() && IsSceneFile(entry.path())) found.push_back(entry.path());
      if (found.size() != 1)
        return absl::NotFoundError(absl::StrCat("scene '", name, "': folder holds ", found.size(),
                                                " .gltf/.glb files, expected exactly one"));
      candidate = found[0];
    }
  } else if (fs::is_regular_file(root_ / absl::StrCat(name, ".glb"), ec)) {
    candidate = root_ / absl::StrCat(name, ".glb");
  } else if (fs::is_regular_file(root_ / absl::StrCat(name, ".gltf"), ec)) {
    candidate = root_ / absl::StrCat(name, ".gltf");
  } else {
    return absl::NotFoundError(absl::StrCat("scene '", name, "' is not in the repository"));
  }
  // Symlinks may point anywhere on disk: only what stays inside the
  // repository is served.
  const fs::path resolved = fs::weakly_canonical(candidate, ec);
  const std::string root_prefix = root_.string() + "/";
  if (ec || resolved.string().rfind(root_prefix, 0) != 0)
    return absl::PermissionDeniedError(absl::StrCat("scene '", name, "' resolves outside the repository"));
  if (!fs::is_regular_file(resolved, ec))
    return absl::NotFoundError(absl::StrCat("scene '", name, "': main file missing"));
  return resolved;
}

fs::path SceneRepository::FileRoot(const fs::path& main_file) const {
  const fs::path relative = main_file.lexically_relative(root_);
  if (relative.empty() || std::distance(relative.begin(), relative.end()) < 2) return root_;
  return root_ / *relative.begin();
}

StatusOr<uint64_t> SceneRepository::NextVersion() const {
  const fs::path path = root_ / std::string(kVersionCounter);
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (fd < 0) return ErrnoError("open", path);
  // The lock goes with the descriptor: a crashed holder releases it.
  while (::flock(fd, LOCK_EX) != 0)
    if (errno != EINTR) {
      const Status error = ErrnoError("lock", path);
      ::close(fd);
      return error;
    }
  char text[32] = {};
  const ssize_t n = ::pread(fd, text, sizeof(text) - 1, 0);
  uint64_t last = 0;
  if (n > 0 && !absl::SimpleAtoi(absl::StripAsciiWhitespace(absl::string_view(text, static_cast<size_t>(n))), &last))
    last = 0;
  const std::string next = absl::StrCat(last + 1, "\n");
  Status status = absl::OkStatus();
  if (::pwrite(fd, next.data(), next.size(), 0) != static_cast<ssize_t>(next.size()) ||
      ::ftruncate(fd, static_cast<off_t>(next.size())) != 0 || ::fsync(fd) != 0)
    status = ErrnoError("write", path);
  ::close(fd);
  if (!status.ok()) return status;
  return last + 1;
}

uint64_t SceneRepository::StoredVersion(absl::string_view name) const {
  if (!ValidateName(name).ok()) return 0;
  std::FILE* f = std::fopen((root_ / std::string(name) / std::string(kVersionMarker)).c_str(), "r");
  if (f == nullptr) return 0;
  char text[32] = {};
  const size_t n = std::fread(text, 1, sizeof(text) - 1, f);
  std::fclose(f);
  uint64_t version = 0;
  if (!absl::SimpleAtoi(absl::StripAsciiWhitespace(absl::string_view(text, n)), &version)) return 0;
  return version;
}

StatusOr<std::unique_ptr<UploadStaging>> SceneRepository::BeginUpload(absl::string_view name,
                                                                      absl::string_view main_file,
                                                                      uint64_t max_bytes) const {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  VISQ_RETURN_IF_ERROR(ValidateUploadFile(main_file));
  if (!IsSceneFile(fs::path(std::string(main_file))))
    return absl::InvalidArgumentError(absl::StrCat("upload_main_file '", main_file, "': not a .gltf or .glb"));
  const fs::path dir = root_ / absl::StrCat(AbslView(kStagingPrefix), name, "-", RandomSuffix());
  if (::mkdir(dir.c_str(), 0700) != 0) return ErrnoError("create staging folder", dir);
  std::unique_ptr<UploadStaging> staging(new UploadStaging(dir, std::string(name), std::string(main_file), max_bytes));
  staging->lock_fd_ = ::open(dir.c_str(), O_RDONLY | O_CLOEXEC | O_DIRECTORY | O_NOFOLLOW);
  if (staging->lock_fd_ < 0 || ::flock(staging->lock_fd_, LOCK_EX | LOCK_NB) != 0)
    return ErrnoError("lock staging folder", dir);
  return staging;
}

SceneRepository::Identity SceneRepository::StoredIdentity(absl::string_view name) const {
  Identity identity;
  if (!ValidateName(name).ok()) return identity;
  struct stat info {};
  for (const fs::path& path : {root_ / std::string(name), root_ / absl::StrCat(name, ".glb"),
                               root_ / absl::StrCat(name, ".gltf")})
    if (::lstat(path.c_str(), &info) == 0) {
      identity.device = info.st_dev;
      identity.inode = info.st_ino;
      break;
    }
  identity.version = StoredVersion(name);
  return identity;
}

StatusOr<SceneRepository::Stored> SceneRepository::Commit(UploadStaging& staging, bool replace) {
  VISQ_RETURN_IF_ERROR(staging.CloseAll());
  VISQ_ASSIGN_OR_RETURN(const uint64_t version, NextVersion());
  // The markers, then everything, reach the disk before the rename does.
  auto write_marker = [&](std::string_view marker_name, const std::string& text) -> Status {
    const fs::path marker = staging.dir_ / std::string(marker_name);
    const int fd = ::open(marker.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0600);
    std::FILE* f = fd >= 0 ? ::fdopen(fd, "w") : nullptr;
    if (f == nullptr) {
      const Status error = ErrnoError("create", marker);
      if (fd >= 0) ::close(fd);
      return error;
    }
    const bool written = std::fputs(text.c_str(), f) >= 0 && std::fflush(f) == 0;
    const int rc = written ? ::fsync(fileno(f)) : -1;
    std::fclose(f);
    if (rc != 0) return ErrnoError("write", marker);
    return absl::OkStatus();
  };
  VISQ_RETURN_IF_ERROR(write_marker(kMainFileMarker, staging.main_file_));
  VISQ_RETURN_IF_ERROR(write_marker(kVersionMarker, absl::StrCat(version, "\n")));
  VISQ_RETURN_IF_ERROR(FsyncPath(staging.dir_, true));

  const fs::path target = root_ / staging.name_;
  std::error_code ec;
  const fs::file_status target_status = fs::symlink_status(target, ec);
  const bool replacing = fs::exists(target_status);
  // Only a stored scene's folder is ever exchanged: a file or link of that
  // name is not ours to destroy.
  if (replacing && !fs::is_directory(target_status))
    return absl::AlreadyExistsError(
        absl::StrCat("scene '", staging.name_, "': the repository holds a file of that name; nothing stored"));
  // A plain-file scene of the same name would shadow nothing but confuse
  // MainFile; uploads always become folders.
  for (const char* ext : {".glb", ".gltf"}) fs::remove(root_ / absl::StrCat(staging.name_, ext), ec);
  auto stored_meanwhile = [&] {
    return absl::AlreadyExistsError(absl::StrCat("scene '", staging.name_,
                                                 "' was stored meanwhile (by another replica?); nothing stored: set "
                                                 "replace to replace it"));
  };
  if (replacing && !replace) return stored_meanwhile();
  // A create never replaces: the rename fails if the name appeared since the
  // check (another replica's commit), and a replace that found nothing
  // exchanges once the name has appeared.
  bool exchanged = false;
  if (!replacing) {
    if (::renameat2(AT_FDCWD, staging.dir_.c_str(), AT_FDCWD, target.c_str(), RENAME_NOREPLACE) != 0) {
      if (errno != EEXIST && errno != ENOTEMPTY) return ErrnoError("rename into", target);
      if (!replace) return stored_meanwhile();
      exchanged = true;
    }
  } else {
    exchanged = true;
  }
  if (exchanged) {
    // Swap atomically: the old folder ends up at the staging path and is
    // removed after; readers see the old scene or the new one.
    if (::renameat2(AT_FDCWD, staging.dir_.c_str(), AT_FDCWD, target.c_str(), RENAME_EXCHANGE) != 0)
      return ErrnoError("exchange into", target);
    fs::remove_all(staging.dir_, ec);
  }
  staging.committed_ = true;
  VISQ_RETURN_IF_ERROR(FsyncPath(root_, true));
  return Stored{target / staging.main_file_, version};
}

Status SceneRepository::Remove(absl::string_view name) {
  VISQ_RETURN_IF_ERROR(ValidateName(name));
  std::error_code ec;
  bool removed = false;
  const fs::path folder = root_ / std::string(name);
  if (fs::exists(fs::symlink_status(folder, ec))) {
    // Move aside first so a crash mid-delete never leaves a half scene.
    const fs::path doomed = root_ / absl::StrCat(AbslView(kStagingPrefix), "deleted-", name, "-", RandomSuffix());
    if (::rename(folder.c_str(), doomed.c_str()) != 0) return ErrnoError("rename", folder);
    fs::remove_all(doomed, ec);
    removed = true;
  }
  for (const char* ext : {".glb", ".gltf"}) removed |= fs::remove(root_ / absl::StrCat(name, ext), ec);
  if (!removed) return absl::NotFoundError(absl::StrCat("scene '", name, "' is not in the repository"));
  return FsyncPath(root_, true);
}

}  // namespace visq::core
