// The scene repository: a directory of glTF scenes that the server loads at
// start and that uploads are stored into. Writes are atomic: an upload is
// staged in a hidden folder, fsynced, and renamed into place, so a crash
// leaves either the old scene or the new one, never half of one.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "common/status.h"

namespace visq::core {

class SceneRepository;

// Files of one upload, written into a staging folder as chunks arrive.
// Destroying an uncommitted staging removes it.
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
  Status CloseAll();

  std::filesystem::path dir_;
  std::string name_;
  std::string main_file_;
  uint64_t max_bytes_;
  uint64_t bytes_ = 0;
  bool committed_ = false;
  std::string open_file_;
  int open_fd_ = -1;
  // Held (flock) while the upload lives, so that a replica starting on the
  // same repository leaves this folder alone (SceneRepository::Open).
  int lock_fd_ = -1;
  std::vector<std::string> files_;
};

class SceneRepository {
 public:
  // Creates the directory if needed and removes the staging folders left by
  // a crash: those no live upload holds locked (a replica sharing the
  // repository keeps its uploads in flight).
  [[nodiscard]] static StatusOr<std::unique_ptr<SceneRepository>> Open(const std::filesystem::path& root);

  // Names are letters, digits, '.', '_' and '-', at most 128 characters, not
  // starting with '.'; anything else is INVALID_ARGUMENT.
  [[nodiscard]] static Status ValidateName(absl::string_view name);

  const std::filesystem::path& root() const { return root_; }
  // Names of the scenes stored, sorted.
  std::vector<std::string> List() const;
  // The .gltf/.glb of a stored scene: <root>/<name>.glb, <root>/<name>.gltf,
  // or the main file of the folder <root>/<name>/.
  [[nodiscard]] StatusOr<std::filesystem::path> MainFile(absl::string_view name) const;
  bool Contains(absl::string_view name) const { return MainFile(name).ok(); }
  // The folder whose files a stored scene's glTF may read: its own folder,
  // or the repository itself for a plain .gltf/.glb placed there by hand.
  std::filesystem::path FileRoot(const std::filesystem::path& main_file) const;

  // Scene versions come from one counter kept in the repository (a file
  // under flock), so they never repeat: not after a restart, and not between
  // replicas that share the repository. A stored upload keeps the version it
  // was committed with, so every replica that loads it reports the same one.
  [[nodiscard]] StatusOr<uint64_t> NextVersion() const;
  // The version a stored scene was committed with; 0 for a scene placed in
  // the repository by hand (it takes NextVersion when loaded).
  uint64_t StoredVersion(absl::string_view name) const;

  [[nodiscard]] StatusOr<std::unique_ptr<UploadStaging>> BeginUpload(absl::string_view name,
                                                                     absl::string_view main_file,
                                                                     uint64_t max_bytes) const;
  // Makes the staged files the stored scene `name` under a new version.
  // With `replace`, an existing one is exchanged atomically (renameat2
  // RENAME_EXCHANGE); without, the rename refuses to replace anything
  // (RENAME_NOREPLACE): a scene another replica stored meanwhile under the
  // same name is ALREADY_EXISTS, never silently overwritten.
  struct Stored {
    std::filesystem::path main_file;
    uint64_t version = 0;
  };
  [[nodiscard]] StatusOr<Stored> Commit(UploadStaging& staging, bool replace);

  // What a stored scene is right now: its folder's (or file's) inode and its
  // committed version. Equal before and after a load means the load read one
  // upload's files, whatever other replicas committed meanwhile (a commit
  // exchanges the folder: a new inode).
  struct Identity {
    uint64_t device = 0, inode = 0, version = 0;
    bool operator==(const Identity&) const = default;
  };
  Identity StoredIdentity(absl::string_view name) const;
  [[nodiscard]] Status Remove(absl::string_view name);

 private:
  explicit SceneRepository(std::filesystem::path root) : root_(std::move(root)) {}
  std::filesystem::path root_;
};

}  // namespace visq::core
