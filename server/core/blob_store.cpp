#include "core/blob_store.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "common/check.h"
#include "core/file_errors.h"

namespace visq::core {
namespace fs = std::filesystem;

Status ErrnoError(absl::string_view what, const fs::path& path, int error) {
  const std::string message = absl::StrCat(what, " ", path.filename().string(), ": ", std::strerror(error));
  if (error == ENOSPC || error == EDQUOT) return absl::ResourceExhaustedError(message);
  if (error == EACCES || error == EPERM || error == EROFS)
    return absl::FailedPreconditionError(absl::StrCat(message, " (the scene repository, --scene-repo, is not writable)"));
  if (error == ENOTDIR || error == EISDIR || error == EEXIST)
    return absl::InvalidArgumentError(absl::StrCat("chunk.file: ", message, " (a file and a folder of the upload clash)"));
  return absl::InternalError(message);
}

Status ErrnoError(absl::string_view what, const fs::path& path) { return ErrnoError(what, path, errno); }

Status MakeOwnerFolders(const fs::path& root, const fs::path& relative) {
  fs::path path = root;
  for (const fs::path& part : relative) {
    path /= part;
    if (::mkdir(path.c_str(), 0700) != 0 && errno != EEXIST) return ErrnoError("create", path);
    struct stat info {};
    if (::lstat(path.c_str(), &info) != 0 || !S_ISDIR(info.st_mode)) return ErrnoError("create", path, ENOTDIR);
  }
  return absl::OkStatus();
}

Status FsyncPath(const fs::path& path, bool directory) {
  const int fd = ::open(path.c_str(), (directory ? O_DIRECTORY : 0) | O_RDONLY | O_CLOEXEC);
  if (fd < 0) return ErrnoError("open for fsync", path);
  const int rc = ::fsync(fd);
  const int error = errno;
  ::close(fd);
  if (rc != 0) return ErrnoError("fsync", path, error);
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------
// Sha256

Sha256::Sha256() : context_(EVP_MD_CTX_new()) {
  VISQ_CHECK(context_ != nullptr);
  VISQ_CHECK(EVP_DigestInit_ex(context_.get(), EVP_sha256(), nullptr) == 1);
}

void Sha256::Update(absl::string_view data) {
  VISQ_CHECK(EVP_DigestUpdate(context_.get(), data.data(), data.size()) == 1);
}

std::string Sha256::HexDigest() {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  VISQ_CHECK(EVP_DigestFinal_ex(context_.get(), digest, &length) == 1);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex;
  hex.reserve(2 * length);
  for (unsigned int i = 0; i < length; ++i) {
    hex.push_back(kHex[digest[i] >> 4]);
    hex.push_back(kHex[digest[i] & 15]);
  }
  return hex;
}

bool IsBlobHash(absl::string_view hash) {
  if (hash.size() != 64) return false;
  for (char c : hash)
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  return true;
}

// ---------------------------------------------------------------------------
// BlobStore

StatusOr<BlobStore> BlobStore::Open(const fs::path& root) {
  VISQ_RETURN_IF_ERROR(MakeOwnerFolders(root.parent_path(), root.filename()));
  return BlobStore(root);
}

fs::path BlobStore::PathOf(absl::string_view hash) const {
  VISQ_CHECK(IsBlobHash(hash));
  return root_ / std::string(hash.substr(0, 2)) / std::string(hash);
}

Status BlobStore::Publish(const fs::path& file, absl::string_view hash) const {
  const fs::path blob = PathOf(hash);
  VISQ_RETURN_IF_ERROR(MakeOwnerFolders(root_, blob.parent_path().filename()));
  // link() never replaces: a blob already there is these bytes (its name is
  // their hash) and stays as it is.
  if (::link(file.c_str(), blob.c_str()) != 0 && errno != EEXIST) return ErrnoError("store blob", blob);
  return FsyncPath(blob.parent_path(), /*directory=*/true);
}

bool BlobStore::Contains(absl::string_view hash) const {
  struct stat info {};
  return IsBlobHash(hash) && ::lstat(PathOf(hash).c_str(), &info) == 0 && S_ISREG(info.st_mode);
}

Status BlobStore::LinkTo(absl::string_view hash, uint64_t size, const fs::path& target) const {
  if (!IsBlobHash(hash)) return absl::InternalError(absl::StrCat("the catalog names a blob '", hash, "'"));
  const fs::path blob = PathOf(hash);
  if (::link(blob.c_str(), target.c_str()) != 0) {
    if (errno == ENOENT) return absl::NotFoundError(absl::StrCat("blob ", hash, " is not in the repository"));
    return ErrnoError("link blob", blob);
  }
  // A blob's size is its catalog's: anything else is a damaged repository,
  // never loaded as if it were the upload.
  struct stat info {};
  if (::stat(target.c_str(), &info) != 0) return ErrnoError("stat", target);
  if (static_cast<uint64_t>(info.st_size) != size)
    return absl::DataLossError(
        absl::StrCat("blob ", hash, " holds ", info.st_size, " bytes, the catalog says ", size));
  return absl::OkStatus();
}

Status BlobStore::Remove(absl::string_view hash) const {
  const fs::path blob = PathOf(hash);
  if (::unlink(blob.c_str()) != 0 && errno != ENOENT) return ErrnoError("remove blob", blob);
  return absl::OkStatus();
}

std::vector<std::string> BlobStore::List() const {
  std::vector<std::string> hashes;
  std::error_code ec;
  for (const auto& shard : fs::directory_iterator(root_, ec)) {
    std::error_code inner;
    if (!shard.is_directory(inner)) continue;
    for (const auto& entry : fs::directory_iterator(shard.path(), inner)) {
      std::string name = entry.path().filename().string();
      if (IsBlobHash(name)) hashes.push_back(std::move(name));
    }
  }
  return hashes;
}

}  // namespace visq::core
