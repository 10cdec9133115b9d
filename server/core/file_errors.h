// How a failed file operation of the scene repository becomes a Status.
#pragma once

#include <filesystem>

#include "common/status.h"

namespace visq::core {

// The errno of the moment as a Status that names the file, not where the
// repository lives: messages reach clients. A full disk or quota is the
// caller's to act on (RESOURCE_EXHAUSTED); a repository the server may not
// write is the operator's to fix (FAILED_PRECONDITION); an upload whose
// files clash (a file where another chunk made a folder, or the reverse) is
// the client's (INVALID_ARGUMENT).
Status ErrnoError(absl::string_view what, const std::filesystem::path& path);
Status ErrnoError(absl::string_view what, const std::filesystem::path& path, int error);

// Makes `path` and the folders above it up to `root` (which exists), each
// its owner's alone (0700): a shared machine's other users read no scene.
Status MakeOwnerFolders(const std::filesystem::path& root, const std::filesystem::path& relative);

// fsync of a file or folder, so that what was written or renamed in it
// survives a crash.
Status FsyncPath(const std::filesystem::path& path, bool directory);

}  // namespace visq::core
