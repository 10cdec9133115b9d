// The scene repository: uploaded scenes, kept so that the server (and every
// replica sharing the folder) can load them again.
//
//   <scene-repo>/.visq/blobs/ab/abcd...   scene files, named by their SHA-256,
//                                         never changed once there
//   <scene-repo>/.visq/catalog.sqlite3    the catalog (the default; or
//                                         PostgreSQL, --catalog): name ->
//                                         version -> the blobs of that version
//   <scene-repo>/.visq/staging/<replica>/ each replica's uploads in flight and
//                                         loads' private views
//
// An upload is staged, hashed as it arrives, and committed in one catalog
// transaction, which allocates its version number; a load reads one
// version's blobs by hash, so it never mixes two uploads and a (scene,
// version) names one content. Scenes placed in the folder by hand (and a
// repository of the layout before the catalog) are imported at start.
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/status.h"
#include "core/blob_store.h"
#include "core/scene_catalog.h"

namespace visq::core {

class SceneRepository;

struct RepositoryOptions {
  std::filesystem::path root;
  // Where the catalog is (--catalog): "" or "sqlite" for
  // <root>/.visq/catalog.sqlite3, "sqlite:<file>", or a PostgreSQL URI
  // ("postgresql://user@host:5432/db", "postgres://...").
  std::string catalog;
  // This replica's name among those sharing the repository (--replica-id):
  // its start removes its own staging only. Empty: the host name (two
  // processes on one host with the same name: the second adds its pid).
  std::string replica_id;
};

// Files of one upload, written into the replica's staging folder as chunks
// arrive and hashed as they are written. Destroying it removes the staging
// (a committed upload's files live on as blobs).
class UploadStaging {
 public:
  ~UploadStaging();
  UploadStaging(const UploadStaging&) = delete;
  UploadStaging& operator=(const UploadStaging&) = delete;

  // Appends to `file` (a plain name, or a relative path without "..").
  [[nodiscard]] Status Append(absl::string_view file, absl::string_view data);
  const std::string& name() const { return name_; }
  std::filesystem::path main_file() const { return dir_ / main_file_; }
  // The folder the upload's files are in: its glTF may read nothing else.
  const std::filesystem::path& dir() const { return dir_; }
  uint64_t bytes() const { return bytes_; }
  // Removes the uploaded files, other than the main file, that are not in
  // `needed` (resolved paths, as the loader reports the files it read):
  // textures and stray files are not stored. Returns how many went.
  [[nodiscard]] StatusOr<size_t> KeepOnly(const std::vector<std::filesystem::path>& needed);

 private:
  friend class SceneRepository;
  UploadStaging(std::filesystem::path dir, std::string name, std::string main_file, uint64_t max_bytes);
  // Closes the open file: fsynced, and its hash final.
  Status CloseAll();

  struct File {
    std::string path;
    uint64_t size = 0;
    std::string blob;  // empty until the file is closed
  };
  std::filesystem::path dir_;
  std::string name_;
  std::string main_file_;
  uint64_t max_bytes_;
  uint64_t bytes_ = 0;
  int open_fd_ = -1;
  std::unique_ptr<Sha256> open_hash_;
  std::vector<File> files_;  // the last one is open while open_fd_ >= 0
};

// One version of a stored scene, checked out for a load: its files, linked
// from their blobs into a private folder of this replica's staging, which
// goes with the object. The links keep the bytes even if the blobs are
// collected meanwhile.
class StoredSceneView {
 public:
  ~StoredSceneView();
  StoredSceneView(const StoredSceneView&) = delete;
  StoredSceneView& operator=(const StoredSceneView&) = delete;
  const std::string& name() const { return name_; }
  uint64_t version() const { return version_; }
  std::filesystem::path main_file() const { return dir_ / main_file_; }
  // The folder the scene's glTF may read files from.
  const std::filesystem::path& dir() const { return dir_; }

 private:
  friend class SceneRepository;
  StoredSceneView(std::filesystem::path dir, std::string name, uint64_t version, std::string main_file)
      : dir_(std::move(dir)), name_(std::move(name)), version_(version), main_file_(std::move(main_file)) {}
  std::filesystem::path dir_;
  std::string name_;
  uint64_t version_;
  std::string main_file_;
};

class SceneRepository {
 public:
  // Creates the folder and the catalog if needed, removes this replica's
  // staging (left by its last run) and that of replicas no longer running,
  // imports scenes placed in the folder by hand or left in the layout
  // before the catalog (a first start moves an old repository over), and
  // collects blobs no version names.
  [[nodiscard]] static StatusOr<std::unique_ptr<SceneRepository>> Open(const RepositoryOptions& options);
  [[nodiscard]] static StatusOr<std::unique_ptr<SceneRepository>> Open(const std::filesystem::path& root) {
    return Open(RepositoryOptions{.root = root});
  }
  ~SceneRepository();

  // Names are letters, digits, '.', '_' and '-', at most 128 characters, not
  // starting with '.'; anything else is INVALID_ARGUMENT.
  [[nodiscard]] static Status ValidateName(absl::string_view name);

  const std::filesystem::path& root() const { return root_; }
  const std::string& replica_id() const { return replica_id_; }
  // "sqlite <file>" or "postgresql <host>:<port>/<db>".
  std::string DescribeCatalog() const { return catalog_->Describe(); }
  // Names of the scenes stored, sorted (empty when the catalog cannot be
  // read: logged).
  std::vector<std::string> List();
  // Whether the catalog holds `name`; a scene of that name placed in the
  // folder by hand since the start is imported first.
  bool Contains(absl::string_view name);

  // A version number never handed out before, by any replica sharing the
  // catalog, before or after a restart (node edits take these).
  [[nodiscard]] StatusOr<uint64_t> NextVersion();

  [[nodiscard]] StatusOr<std::unique_ptr<UploadStaging>> BeginUpload(absl::string_view name,
                                                                     absl::string_view main_file,
                                                                     uint64_t max_bytes);
  // Stores the staged files as a new version of the scene, in one catalog
  // transaction. Without `replace`, a scene of that name (stored meanwhile
  // by another replica too) is ALREADY_EXISTS and nothing is stored.
  struct Stored {
    uint64_t version = 0;
  };
  [[nodiscard]] StatusOr<Stored> Commit(UploadStaging& staging, bool replace);

  // The current version of `name`, its files linked into a private folder.
  // NOT_FOUND when the catalog has no such scene.
  [[nodiscard]] StatusOr<std::unique_ptr<StoredSceneView>> Checkout(absl::string_view name);
  [[nodiscard]] Status Remove(absl::string_view name);

 private:
  SceneRepository(std::filesystem::path root, std::string replica_id, std::filesystem::path staging, int owner_fd,
                  BlobStore blobs, std::unique_ptr<SceneCatalog> catalog);
  // A fresh folder in this replica's staging.
  StatusOr<std::filesystem::path> NewStagingFolder(absl::string_view prefix) const;
  // Imports the scenes at the top of the folder (all, or `only` that
  // name); a scene imported is removed from there.
  Status ImportHandPlaced(const std::optional<std::string>& only);
  // Removes those of `blobs` that no version names (under the catalog's
  // write lock); failures are logged, never the caller's.
  void Collect(const std::vector<std::string>& blobs);
  StatusOr<Stored> CommitFiles(UploadStaging& staging, bool replace, bool unless_unchanged, uint64_t keep_version,
                               bool* stored);

  std::filesystem::path root_;
  std::string replica_id_;
  std::filesystem::path staging_;  // <root>/.visq/staging/<replica_id_>
  int owner_fd_;                   // flock held while this replica runs
  BlobStore blobs_;
  std::unique_ptr<SceneCatalog> catalog_;
};

}  // namespace visq::core
