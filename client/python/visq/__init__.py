"""visq: a Python client of visq-server, numpy in and out.

    import visq
    with visq.Client("127.0.0.1:50051") as c:
        c.upload_gltf("scene.gltf")
        m = c.hidden_sample_map("scene", source=visq.Patch(o, u, v), receiver=visq.Patch(o2, u2, v2))
        m.visible_fraction  # (height, width) float32

Every failure raises visq.VisqError (.code: grpc.StatusCode, .field: the
request field or server flag the message names).
"""
from .client import (DEFAULT_PORT, Cancellation, Client, HiddenSampleMap, LightVisibility, ObscuranceBake,
                     ObscuranceExport, ObscurancePreview, ObscuranceUpdate, Patch, PatchVisibility, Progress, Transmittance,
                     VolumetricImage, VoxelGrid, geometry_files, normalize_address)
from .errors import Cancelled, VisqError

__all__ = ["DEFAULT_PORT", "Cancellation", "Cancelled", "Client", "HiddenSampleMap", "LightVisibility",
           "ObscuranceBake", "ObscuranceExport", "ObscurancePreview", "ObscuranceUpdate", "Patch", "PatchVisibility", "Progress",
           "Transmittance", "VisqError", "VolumetricImage", "VoxelGrid", "geometry_files", "normalize_address"]
__version__ = "0.1.0"
