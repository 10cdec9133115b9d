// Compressed glTF geometry, as gltfpack and gltf-transform write it:
// EXT_meshopt_compression buffer views (meshoptimizer) and
// KHR_draco_mesh_compression primitives (Draco), decoded into plain buffers
// so that the loader reads ordinary accessors. KHR_mesh_quantization needs
// no decoding: the loader reads its integer attributes directly.
#pragma once

#include <cstdint>
#include <string>

#include "common/status.h"

namespace tinygltf {
class Model;
}

namespace visq {

// Before tinygltf parses the file, what its parser would refuse in a valid
// compressed document: a meshopt fallback buffer without a uri (its bytes
// were never written; tinygltf would look for a file, or copy a GLB's BIN
// chunk into it) gets one byte of inline data, and a Draco primitive's
// indices accessor without a buffer view borrows the Draco stream's.
// `bytes` is the whole .gltf or .glb; a document without compression comes
// back as it was.
[[nodiscard]] StatusOr<std::string> PrepareCompressedDocument(std::string bytes, bool binary);

// After tinygltf parsed it: every compressed buffer view and Draco
// primitive becomes a plain buffer that its accessors point at. The decoded
// bytes together may not exceed `max_decoded_bytes` (RESOURCE_EXHAUSTED);
// a malformed stream is INVALID_ARGUMENT naming its buffer view or primitive.
[[nodiscard]] Status DecodeCompressedGeometry(tinygltf::Model& model, uint64_t max_decoded_bytes);

}  // namespace visq
