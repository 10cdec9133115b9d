// Scene files as immutable, content-addressed blobs: a file is named by the
// SHA-256 of its bytes, reaches its name by a link from a fully written and
// fsynced temporary file, and is never changed afterwards. Two uploads that
// send the same bytes share one blob; a blob is removed only when no version
// in the catalog names it (SceneRepository decides when, under the
// catalog's write lock).
#pragma once

#include <openssl/evp.h>

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "common/status.h"

namespace visq::core {

// An incremental SHA-256: cryptographic, because a client that could make
// two files collide could make another client's upload share its content.
class Sha256 {
 public:
  Sha256();
  void Update(absl::string_view data);
  // The digest as 64 lower-case hex digits; the object is spent after.
  std::string HexDigest();

 private:
  struct Free {
    void operator()(EVP_MD_CTX* context) const { EVP_MD_CTX_free(context); }
  };
  std::unique_ptr<EVP_MD_CTX, Free> context_;
};

// True for 64 lower-case hex digits (what HexDigest returns): the only names
// a blob path is ever made from.
bool IsBlobHash(absl::string_view hash);

class BlobStore {
 public:
  // `root` is <scene-repo>/.visq/blobs, made if needed.
  [[nodiscard]] static StatusOr<BlobStore> Open(const std::filesystem::path& root);

  // <root>/<first two digits>/<hash>.
  std::filesystem::path PathOf(absl::string_view hash) const;
  // Makes `file` (written and fsynced by the caller, on the same file
  // system) the blob `hash` by a hard link; a blob already there is the same
  // bytes and is kept. The blob's folder is fsynced before this returns.
  [[nodiscard]] Status Publish(const std::filesystem::path& file, absl::string_view hash) const;
  bool Contains(absl::string_view hash) const;
  // Links the blob to `target` (a load's private view): the view keeps the
  // bytes even if the blob is collected while the load reads them.
  [[nodiscard]] Status LinkTo(absl::string_view hash, uint64_t size, const std::filesystem::path& target) const;
  // Removes the blob; one already gone is not an error.
  [[nodiscard]] Status Remove(absl::string_view hash) const;
  // Every blob stored (their hashes).
  std::vector<std::string> List() const;

 private:
  explicit BlobStore(std::filesystem::path root) : root_(std::move(root)) {}
  std::filesystem::path root_;
};

}  // namespace visq::core
