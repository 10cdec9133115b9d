"""visq.Client: every visq.v1 RPC as a Python method, numpy in and out.

A call returns numpy arrays (and the response's figures as the protobuf
message) or raises visq.VisqError, which carries the gRPC status code and the
field the server named. Unary calls have a deadline (Client(timeout=60));
streams, bakes and uploads have none unless given (stream_timeout= or a
call's timeout=), since their length depends on the scene. Streams take a
progress callback and a visq.Cancellation.
"""
import json
import math
import os
import struct
import threading
import urllib.parse
from dataclasses import dataclass
from typing import Any, List, NamedTuple, Optional, Sequence

import grpc
import numpy as np

from . import _health
from .errors import Cancelled, VisqError, from_rpc_error
from .v1 import visq_pb2 as pb
from .v1 import visq_pb2_grpc as pb_grpc

# visq-server's default --address port (server/service/server.h).
DEFAULT_PORT = 50051
# Points per LightVisibilityStream message: ~70 bytes each on the wire, so a
# batch stays far below the server's 16 MiB message limit (and its cap of
# 1,000,000 points per message).
LIGHT_BATCH_POINTS = 65536
_UNSET = object()


class Patch(NamedTuple):
    """origin + s * edge_u + t * edge_v, s, t in [0, 1]; front faces edge_u x edge_v."""
    origin: Sequence[float]
    edge_u: Sequence[float]
    edge_v: Sequence[float]


class Progress(NamedTuple):
    """An obscurance bake's progress message."""
    directions_done: int
    directions_total: int
    elapsed_s: float
    estimated_s_left: float


class Cancellation:
    """Cancels a running call from any thread: pass it as `cancel=`, then call
    cancel(). The call raises visq.Cancelled; the server stops a bake within
    one direction."""

    def __init__(self):
        self._lock = threading.Lock()
        self._call = None
        self._cancelled = False

    @property
    def cancelled(self):
        return self._cancelled

    def cancel(self):
        with self._lock:
            self._cancelled = True
            call = self._call
        if call is not None:
            call.cancel()

    def _attach(self, call):
        with self._lock:
            self._call = call
            cancelled = self._cancelled
        if cancelled:
            call.cancel()

    def _detach(self):
        with self._lock:
            self._call = None


def normalize_address(address):
    """HOST[:PORT] with the server's default port when none is given."""
    if not address:
        raise ValueError("address: empty")
    if address.startswith(("unix:", "dns:", "ipv4:", "ipv6:")):
        return address
    if address.startswith("["):  # [v6] or [v6]:port
        return address if "]:" in address else f"{address}:{DEFAULT_PORT}"
    if address.count(":") > 1:  # a bare IPv6 address
        return f"[{address}]:{DEFAULT_PORT}"
    host, sep, port = address.rpartition(":")
    if not sep:
        return f"{address}:{DEFAULT_PORT}"
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"address: port '{port}' of '{address}' is not a number in 1..65535")
    return address


# ---------------------------------------------------------------------------
# Results. Arrays are numpy; `figures` / `response` is the visq.v1 protobuf
# message (SceneInfo, ServerStats and the like are returned as such too).

@dataclass
class HiddenSampleMap:
    """visible_fraction[y, x]: the fraction of source samples visible from
    receiver texel (x, y), y along the receiver's edge_v (row 0 at its origin)."""
    visible_fraction: np.ndarray               # (height, width) float32
    visible_rgb: Optional[np.ndarray]          # (height, width, 3) float32, coloured lights
    blocked_bits: Optional[np.ndarray]         # (height, width, words_per_texel) uint32; bit i: sample i hidden
    lookup_error: Optional[np.ndarray]         # (height, width) float32, HOUGH lookup only
    texel_error: Optional[np.ndarray]          # (height, width) float32, each texel's bound (texel_error=True)
    source_samples: np.ndarray                 # (samples, 3) float64 world positions
    figures: Any                               # HiddenSampleMapResponse without the arrays
    # (height, width) float32, each texel's estimate beside its bound, not a
    # bound (texel_error=True, JITTERED samples)
    texel_estimate: Optional[np.ndarray] = None

    @property
    def accuracy(self):
        return self.figures.accuracy

    def blocked(self):
        """(height, width, samples) bool: True where the sample is hidden."""
        if self.blocked_bits is None:
            raise ValueError("blocked(): ask with bitmasks=True")
        bits = np.unpackbits(self.blocked_bits.astype("<u4").view(np.uint8), axis=-1, bitorder="little")
        return bits[..., : self.figures.sample_count].astype(bool)


@dataclass
class PatchVisibility:
    mutual_visible_fraction: float
    source_visible: np.ndarray    # (rows, columns) float32 per source sample (1-D if the server chose the grid)
    receiver_visible: np.ndarray  # (rows, columns) float32 per receiver sample
    unblocked: np.ndarray         # (k, 2) uint32 (source sample, receiver sample) pairs
    response: Any


@dataclass
class LightVisibility:
    """Per point (or per receiver texel, shaped (height, width))."""
    visible_fraction: np.ndarray
    visible_solid_angle_fraction: np.ndarray
    irradiance: np.ndarray
    polygons: Optional[List[List[np.ndarray]]]  # per point: visible parts of the light, (k, 3) arrays
    responses: List[Any]                        # one LightVisibilityResponse per batch (tree, cache, timing)
    # Per point, what occluders left out under shadow_tolerance could have
    # hidden: the true figure lies at most this far below the one above.
    visible_fraction_error: Optional[np.ndarray] = None
    irradiance_error: Optional[np.ndarray] = None

    @property
    def accuracy(self):
        return self.responses[0].accuracy if self.responses else None


@dataclass
class VoxelGrid:
    bits: np.ndarray                   # (height, width, words_per_column) uint32; slice k: bit k % 32 of word k / 32
    column_near: Optional[np.ndarray]  # (height, width) float32, local precision: fractions of the box depth
    column_far: Optional[np.ndarray]
    figures: Any                       # VoxelizeResponse without the arrays (box, counts, accuracy, timing)

    def occupancy(self):
        """(height, width, slices) bool."""
        bits = np.unpackbits(self.bits.astype("<u4").view(np.uint8), axis=-1, bitorder="little")
        return bits[..., : self.figures.slices].astype(bool)

    def column_counts(self):
        """(height, width) occupied voxels per column."""
        return self.occupancy().sum(axis=-1, dtype=np.uint32)


@dataclass
class Transmittance:
    """1-D arrays over the points, then the receiver's texels (row-major)."""
    transmittance: np.ndarray
    optical_depth: np.ndarray
    optical_depth_error: np.ndarray
    lateral_offset: np.ndarray
    point_count: int
    receiver_shape: Optional[tuple]  # (height, width)
    response: Any

    def at_points(self, values):
        return values[: self.point_count]

    def on_receiver(self, values):
        """The receiver's part of `values`, shaped (height, width)."""
        if self.receiver_shape is None:
            raise ValueError("on_receiver(): the request had no receiver")
        return values[self.point_count:].reshape(self.receiver_shape)


@dataclass
class VolumetricImage:
    inscattering: np.ndarray        # (height, width, 3) float32, row 0 at the top
    combined: Optional[np.ndarray]  # the same with the lit surfaces (combined=True)
    figures: Any


@dataclass
class ObscuranceBake:
    """Atlas arrays are indexed [y, x]; texel (x, y) of the atlas."""
    w: Optional[np.ndarray]               # (height, width, 3) float32
    intensity: Optional[np.ndarray]       # (height, width, 3) float32
    estimated: Optional[np.ndarray]       # (height, width) bool: estimated, not filled from neighbours
    triangle_w: Optional[np.ndarray]      # (triangles, 3), want_averages
    vertex_w: Optional[np.ndarray]        # (vertices, 3), want_averages
    partial_sums: Optional[np.ndarray]    # (height, width, channels) uint64, partial_only
    partial_counts: Optional[np.ndarray]  # (height, width) uint64, partial_only
    figures: Any                          # ObscuranceFigures
    progress_messages: int = 0
    w_error: Optional[np.ndarray] = None           # (height, width): each texel's own bound, want_errors
    triangle_w_error: Optional[np.ndarray] = None  # (triangles,), want_errors and want_averages
    vertex_w_error: Optional[np.ndarray] = None    # (vertices,), want_errors and want_averages


@dataclass
class ObscuranceUpdate:
    texels: np.ndarray            # changed texels, y * width + x
    w: np.ndarray                 # (len(texels), 3)
    full_w: Optional[np.ndarray]  # (height, width, 3), want_full_w
    response: Any
    # Each changed element's own half-width at response.accuracy.confidence
    # (1 where its W rests on no sample of its own): per texel of `texels`,
    # per response.triangles, per response.vertices.
    w_error: Optional[np.ndarray] = None
    triangle_w_error: Optional[np.ndarray] = None
    vertex_w_error: Optional[np.ndarray] = None


@dataclass
class ObscurancePreview:
    rgb: np.ndarray      # (height, width, 3) float32 linear, row 0 at the top
    covered: np.ndarray  # (height, width) bool
    figures: Any


@dataclass
class ObscuranceExport:
    atlas_uv: Optional[np.ndarray]  # (triangles, 3, 2) float32 glTF UVs, the order of triangle_w (want_atlas_uvs)
    glb: Optional[bytes]            # the baked scene as binary glTF (want_gltf)
    figures: Any


# ---------------------------------------------------------------------------
# Request building: every value is checked here, naming the argument.

def _vec3(value, name, out=None):
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected 3 numbers, got {value!r}") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"{name}: {value!r} is not finite")
    out = pb.Vec3() if out is None else out
    out.x, out.y, out.z = x, y, z
    return out


def _patch(value, name, out):
    if isinstance(value, dict):
        value = (value.get("origin"), value.get("edge_u"), value.get("edge_v"))
    try:
        origin, edge_u, edge_v = value
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (origin, edge_u, edge_v), got {value!r}") from None
    _vec3(origin, f"{name}.origin", out.origin)
    _vec3(edge_u, f"{name}.edge_u", out.edge_u)
    _vec3(edge_v, f"{name}.edge_v", out.edge_v)
    return out


def _choice(value, name, allowed):
    key = str(value).lower()
    if key not in allowed:
        raise ValueError(f"{name}: '{value}' is not one of {', '.join(allowed)}")
    return allowed[key]


def _count(value, name, low=1, high=(1 << 32) - 1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    if not low <= int(value) <= high:
        raise ValueError(f"{name}: {value} is not in {low}..{high}")
    return int(value)


def _points(values, name):
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name}: expected an (n, 3) array, got shape {array.shape}")
    if not np.isfinite(array).all():
        bad = int(np.argwhere(~np.isfinite(array))[0][0])
        raise ValueError(f"{name}[{bad}]: not finite")
    return array


def _target(target, out):
    """target: a dict (or visq.v1 AccuracyTarget) of max_error, confidence, time_budget_ms and guarantee
    ("rigorous": max_error on the stated bound, the default; "estimate": on the estimate beside it)."""
    if isinstance(target, pb.AccuracyTarget):
        out.CopyFrom(target)
        return
    unknown = set(target) - {"max_error", "confidence", "time_budget_ms", "guarantee"}
    if unknown:
        raise ValueError(f"target: unknown key(s) {', '.join(sorted(unknown))}; "
                         "allowed: max_error, confidence, time_budget_ms, guarantee")
    out.max_error = float(target.get("max_error", 0.0))
    out.confidence = float(target.get("confidence", 0.0))
    out.time_budget_ms = float(target.get("time_budget_ms", 0.0))
    if "guarantee" in target:
        out.guarantee = _choice(target["guarantee"], "target.guarantee", _GUARANTEES)


_GUARANTEES = {"rigorous": pb.AccuracyTarget.RIGOROUS, "estimate": pb.AccuracyTarget.ESTIMATE}
_METHODS = {"auto": pb.METHOD_UNSPECIFIED, "raster": pb.RASTER, "raycast": pb.RAYCAST, "exact": pb.PLUCKER_EXACT, "plucker-exact": pb.PLUCKER_EXACT, "gpu-raycast": pb.GPU_RAYCAST}
# "fast" was the Hough lookup's first name.
_LOOKUPS = {"exact": pb.EXACT, "hough": pb.HOUGH, "fast": pb.HOUGH}


def _array(field, dtype):
    return np.array(field, dtype=dtype)


class _Chunks:
    """Streamed arrays reassembled in order; `offset` proves none is missing."""

    def __init__(self):
        self.parts = {}
        self.sizes = {}

    def add(self, name, values, offset, dtype, unit=1):
        if len(values) == 0:
            return
        have = self.sizes.get(name, 0)
        if offset * unit != have:
            raise VisqError(grpc.StatusCode.DATA_LOSS, f"{name} chunk at {offset}, expected {have // unit}", name)
        array = np.frombuffer(values, dtype=np.uint8) if isinstance(values, bytes) else _array(values, dtype)
        self.parts.setdefault(name, []).append(array)
        self.sizes[name] = have + len(array)

    def get(self, name, dtype, shape, required=False):
        if name not in self.parts:
            if required:
                raise VisqError(grpc.StatusCode.DATA_LOSS, f"{name}: stream ended without it", name)
            return None
        array = np.concatenate(self.parts[name]).astype(dtype, copy=False)
        expected = int(np.prod(shape))
        if array.size != expected:
            raise VisqError(grpc.StatusCode.DATA_LOSS,
                            f"{name}: {array.size} values for shape {tuple(shape)}", name)
        return array.reshape(shape)


# ---------------------------------------------------------------------------

class Client:
    """A channel to one visq-server.

        with visq.Client("127.0.0.1:50051") as c:
            c.upload_gltf("box.gltf")
            m = c.hidden_sample_map("box", source=..., receiver=..., width=64, height=64)
            m.visible_fraction  # (64, 64) float32
    """

    def __init__(self, address="127.0.0.1:50051", *, token=None, token_file=None, tls_ca=None, tls_cert=None,
                 tls_key=None, tls_server_name=None, timeout=60.0, stream_timeout=None, request_id=None,
                 route_by_scene=True, upload_chunk_bytes=1 << 20):
        self.address = normalize_address(address)
        self.timeout = timeout
        self.stream_timeout = stream_timeout
        if not 1 <= int(upload_chunk_bytes) <= 8 << 20:
            raise ValueError("upload_chunk_bytes: must be in 1..8 MiB (messages stay below the server's limit)")
        self.upload_chunk_bytes = int(upload_chunk_bytes)
        self.route_by_scene = route_by_scene
        if token_file is not None:
            with open(token_file, encoding="utf-8") as f:
                token = f.readline().strip()
        self._metadata = []
        if token:
            self._metadata.append(("authorization", f"Bearer {token}"))
        if request_id:
            self._metadata.append(("x-request-id", str(request_id)))
        options = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]
        if tls_ca or tls_cert:
            def read(path):
                if path is None:
                    return None
                with open(path, "rb") as f:
                    return f.read()
            if bool(tls_cert) != bool(tls_key):
                raise ValueError("tls_cert, tls_key: give both for mutual TLS")
            credentials = grpc.ssl_channel_credentials(read(tls_ca), read(tls_key), read(tls_cert))
            if tls_server_name:
                options.append(("grpc.ssl_target_name_override", tls_server_name))
            self._channel = grpc.secure_channel(self.address, credentials, options=options)
        else:
            self._channel = grpc.insecure_channel(self.address, options=options)
        self._stub = pb_grpc.VisibilityServiceStub(self._channel)
        self._health = self._channel.unary_unary(_health.METHOD, request_serializer=lambda b: b,
                                                 response_deserializer=lambda b: b)

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def stub(self):
        """The generated VisibilityServiceStub, for fields this class does not expose."""
        return self._stub

    # -- plumbing ----------------------------------------------------------

    def _meta(self, scene=""):
        metadata = list(self._metadata)
        # Metadata must be printable ASCII; an odd name goes unrouted and the
        # server refuses it by name.
        if self.route_by_scene and scene and all(0x20 <= ord(c) < 0x7F for c in scene):
            metadata.append(("x-visq-scene", scene))
        return metadata

    def _deadline(self, timeout, stream):
        if timeout is _UNSET:
            return self.stream_timeout if stream else self.timeout
        return timeout

    def _unary(self, rpc, request, scene="", timeout=_UNSET):
        try:
            return rpc(request, timeout=self._deadline(timeout, False), metadata=self._meta(scene))
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None

    def _server_stream(self, rpc, request, scene, timeout, cancel, on_message):
        call = rpc(request, timeout=self._deadline(timeout, True), metadata=self._meta(scene))
        return self._drain(call, cancel, on_message)

    def _chunked_stream(self, rpc, name, request, scene, timeout, cancel, arrays):
        """A streamed answer: each array reassembled from its chunks by offset,
        and the first message (its figures) with the arrays cleared.
        `arrays`: (field, offset field, dtype, elements per offset unit)."""
        chunks, first = _Chunks(), []

        def on_message(m):
            for field, offset, dtype, unit in arrays:
                chunks.add(field, getattr(m, field), getattr(m, offset), dtype, unit=unit)
            if not first:
                for field, _, _, _ in arrays:
                    m.ClearField(field)
                first.append(m)
            else:
                # Figures that need the whole answer (a map's accuracy, a
                # grid's counts, the timing) come in the last message.
                for field, offset, _, _ in arrays:
                    m.ClearField(field)
                    m.ClearField(offset)
                # A later accuracy (an error estimate) replaces the first one
                # whole: merged, an estimate of exactly 0 would keep its -1.
                if "accuracy" in m.DESCRIPTOR.fields_by_name and m.HasField("accuracy"):
                    first[0].accuracy.CopyFrom(m.accuracy)
                    m.ClearField("accuracy")
                first[0].MergeFrom(m)

        self._server_stream(rpc, request, scene, timeout, cancel, on_message)
        if not first:
            raise VisqError(grpc.StatusCode.DATA_LOSS, f"{name}: empty stream")
        return chunks, first[0]

    @staticmethod
    def _drain(call, cancel, on_message):
        if cancel is not None:
            cancel._attach(call)
        try:
            for message in call:
                on_message(message)
        except grpc.RpcError as error:
            if error.code() == grpc.StatusCode.CANCELLED and cancel is not None and cancel.cancelled:
                raise Cancelled() from None
            raise from_rpc_error(error) from None
        except BaseException:
            # Ctrl-C, a callback's exception or a DATA_LOSS of ours: stop the
            # server's work too.
            call.cancel()
            raise
        finally:
            if cancel is not None:
                cancel._detach()

    # -- health and scenes ---------------------------------------------------

    def health(self, service="", timeout=_UNSET) -> str:
        """'SERVING', 'NOT_SERVING', ... of `service` ('' = the whole server)."""
        try:
            data = self._health(_health.encode_request(service), timeout=self._deadline(timeout, False),
                                metadata=self._metadata)
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None
        return _health.decode_response(data)

    def wait_until_serving(self, timeout=30.0) -> None:
        import time
        end = time.monotonic() + timeout
        last = "not tried"
        while time.monotonic() < end:
            try:
                status = self.health(timeout=2.0)
                if status == "SERVING":
                    return
                last = f"server is {status}"
            except VisqError as error:
                last = str(error)
            time.sleep(0.05)
        raise VisqError(grpc.StatusCode.DEADLINE_EXCEEDED, f"server at {self.address} not SERVING in time: {last}")

    def list_scenes(self, timeout=_UNSET) -> List[Any]:
        """SceneInfo messages (without nodes)."""
        return list(self._unary(self._stub.ListScenes, pb.ListScenesRequest(), timeout=timeout).scenes)

    def get_scene(self, name, include_nodes=False, load_if_stored=False, timeout=_UNSET) -> Any:
        request = pb.GetSceneRequest(name=name, include_nodes=include_nodes, load_if_stored=load_if_stored)
        return self._unary(self._stub.GetScene, request, name, timeout)

    def unload_scene(self, name, delete_from_repository=False, timeout=_UNSET) -> bool:
        """True when it was also deleted from the repository."""
        request = pb.UnloadSceneRequest(name=name, delete_from_repository=delete_from_repository)
        return self._unary(self._stub.UnloadScene, request, name, timeout).deleted_from_repository

    def load_from_repository(self, name, replace=False, timeout=_UNSET) -> Any:
        header = pb.LoadSceneHeader(name=name, from_repository=True, replace=replace)
        return self._load(iter([pb.LoadSceneRequest(header=header)]), name, timeout)

    def upload_gltf(self, path, name=None, replace=False, timeout=_UNSET) -> Any:
        """Uploads a .gltf with its buffer files, or a .glb (and any external
        buffer it names): only what the geometry needs, not images. `name`
        defaults to the file's stem. Returns the SceneInfo."""
        path = os.fspath(path)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{path}: no such file")
        if not path.lower().endswith((".gltf", ".glb")):
            raise ValueError(f"{path}: not a .gltf or .glb file")
        name = name if name is not None else os.path.splitext(os.path.basename(path))[0]
        files = [(os.path.basename(path), path)] + geometry_files(path)
        total = sum(os.path.getsize(p) for _, p in files)
        header = pb.LoadSceneHeader(name=name, upload_main_file=os.path.basename(path), replace=replace,
                                    expected_bytes=total)
        chunk_bytes = self.upload_chunk_bytes

        def messages():
            yield pb.LoadSceneRequest(header=header)
            for relative, file in files:
                with open(file, "rb") as f:
                    while True:
                        data = f.read(chunk_bytes)
                        if not data:
                            break
                        yield pb.LoadSceneRequest(chunk=pb.FileChunk(file=relative, data=data))

        return self._load(messages(), name, timeout)

    def _load(self, messages, name, timeout):
        try:
            return self._stub.LoadScene(messages, timeout=self._deadline(timeout, True), metadata=self._meta(name))
        except grpc.RpcError as error:
            raise from_rpc_error(error) from None

    def stats(self, timeout=_UNSET) -> Any:
        """The ServerStats message: per-RPC latencies, queues, memory, GPU."""
        return self._unary(self._stub.GetStats, pb.GetStatsRequest(), timeout=timeout)

    # -- hidden-sample maps and patch visibility ------------------------------

    def hidden_sample_map(self, scene, source, receiver, width=128, height=128, samples=256, method="auto",
                          lookup="exact", seed=1, decorrelate=False, watertight=False, bitmasks=False, target=None,
                          confidence=0.0, texel_error=False, version=0, timeout=_UNSET,
                          cancel=None) -> HiddenSampleMap:
        """Per receiver texel, the fraction of the source's samples visible.

        target: {"max_error": e, "confidence": c, "time_budget_ms": t} instead
        of samples and method: the server chooses."""
        request = pb.HiddenSampleMapRequest()
        request.scene.name, request.scene.version = scene, version
        _patch(source, "source", request.source)
        _patch(receiver, "receiver", request.receiver)
        request.width = _count(width, "width", 1, 4096)
        request.height = _count(height, "height", 1, 4096)
        request.samples.seed = int(seed)
        if target is not None:
            _target(target, request.target)
        else:
            request.samples.count = _count(samples, "samples", 1, 65536)
            request.method = _choice(method, "method", _METHODS)
        request.lookup = _choice(lookup, "lookup", _LOOKUPS)
        request.decorrelate, request.watertight, request.want_bitmasks = decorrelate, watertight, bitmasks
        request.confidence = float(confidence)
        request.want_texel_error = bool(texel_error)
        chunks, f = self._chunked_stream(self._stub.HiddenSampleMap, "HiddenSampleMap", request, scene, timeout, cancel,
                                         [("visible_fraction", "offset", np.float32, 1),
                                          ("visible_rgb", "offset", np.float32, 3),
                                          ("blocked_bits", "offset", np.uint32, 1),
                                          ("lookup_error", "offset", np.float32, 1),
                                          ("texel_error", "offset", np.float32, 1),
                                          ("texel_estimate", "offset", np.float32, 1)])
        h, w = f.height, f.width
        lookup_error = chunks.get("lookup_error", np.float32, (h, w))
        texel_error = chunks.get("texel_error", np.float32, (h, w))
        texel_estimate = chunks.get("texel_estimate", np.float32, (h, w))
        samples_xyz = np.array([(p.x, p.y, p.z) for p in f.source_samples], dtype=np.float64).reshape(-1, 3)
        return HiddenSampleMap(
            visible_fraction=chunks.get("visible_fraction", np.float32, (h, w), required=True),
            visible_rgb=chunks.get("visible_rgb", np.float32, (h, w, 3)),
            blocked_bits=chunks.get("blocked_bits", np.uint32, (h, w, f.words_per_texel)),
            lookup_error=lookup_error, texel_error=texel_error, source_samples=samples_xyz, figures=f,
            texel_estimate=texel_estimate)

    def patch_visibility(self, scene, source, receiver, source_grid=32, receiver_grid=32, method="auto",
                         lookup="exact", watertight=False, unblocked_limit=0, target=None, version=0,
                         timeout=_UNSET) -> PatchVisibility:
        """Mutual visibility of two sampled patches. Grids are (columns, rows)
        or one number for both."""
        def grid(value, name):
            columns, rows = (value, value) if isinstance(value, (int, np.integer)) else value
            return _count(columns, f"{name}[0]", 1, 4096), _count(rows, f"{name}[1]", 1, 4096)

        request = pb.PatchVisibilityRequest()
        request.scene.name, request.scene.version = scene, version
        _patch(source, "source", request.source)
        _patch(receiver, "receiver", request.receiver)
        request.receiver_columns, request.receiver_rows = grid(receiver_grid, "receiver_grid")
        if target is not None:
            _target(target, request.target)
        else:
            request.source_columns, request.source_rows = grid(source_grid, "source_grid")
            request.method = _choice(method, "method", _METHODS)
        request.lookup = _choice(lookup, "lookup", _LOOKUPS)
        request.watertight = watertight
        request.unblocked_limit = _count(unblocked_limit, "unblocked_limit", 0)
        r = self._unary(self._stub.PatchVisibility, request, scene, timeout)

        def shaped(values, rows, columns):
            array = _array(values, np.float32)
            return array.reshape(rows, columns) if array.size == rows * columns and rows else array

        return PatchVisibility(
            mutual_visible_fraction=r.mutual_visible_fraction,
            source_visible=shaped(r.source_visible, request.source_rows, request.source_columns),
            receiver_visible=shaped(r.receiver_visible, request.receiver_rows, request.receiver_columns),
            unblocked=np.array([(p.source_sample, p.receiver_sample) for p in r.unblocked],
                               dtype=np.uint32).reshape(-1, 2),
            response=r)

    # -- exact light visibility ----------------------------------------------

    def light_visibility(self, scene, light, points=None, normals=None, triangles=None, receiver=None, width=64,
                         height=64, radiance=1.0, polygons=False, exclude_nodes=(), receiver_region=None, version=0,
                         batch_points=LIGHT_BATCH_POINTS, progress=None, timeout=_UNSET, cancel=None,
                         shadow_tolerance=None) -> LightVisibility:
        """Exact visibility of an area light (an (n, 3) polygon, front side
        counter-clockwise) from points ((n, 3), with optional normals and
        triangle indices), or from the texel centres of a receiver patch
        (results shaped (height, width), row y along edge_v). Batches go over
        LightVisibilityStream, so any count fits; progress(done, total) is
        called after each batch. shadow_tolerance: per point, occluders with
        small shadows may be left out while their areas sum to at most this
        share of the light, stated per point in visible_fraction_error (0:
        every answer exact; None: the server's default)."""
        light = _points(light, "light")
        if receiver is not None:
            if points is not None:
                raise ValueError("points, receiver: give one, not both")
            patch = _patch(receiver, "receiver", pb.Patch())
            width, height = _count(width, "width", 1, 4096), _count(height, "height", 1, 4096)
            o = np.array([patch.origin.x, patch.origin.y, patch.origin.z])
            u = np.array([patch.edge_u.x, patch.edge_u.y, patch.edge_u.z])
            v = np.array([patch.edge_v.x, patch.edge_v.y, patch.edge_v.z])
            n = np.cross(u, v)
            if not np.linalg.norm(n) > 0:
                raise ValueError("receiver: edge_u and edge_v are parallel")
            s = (np.arange(width) + 0.5) / width
            t = (np.arange(height) + 0.5) / height
            points = (o + t[:, None, None] * v + s[None, :, None] * u).reshape(-1, 3)
            normals = np.broadcast_to(n / np.linalg.norm(n), points.shape)
            shape = (height, width)
        elif points is None:
            raise ValueError("points, receiver: give one")
        else:
            points = _points(points, "points")
            shape = (len(points),)
        if normals is not None:
            normals = _points(normals, "normals")
            if len(normals) != len(points):
                raise ValueError(f"normals: {len(normals)} for {len(points)} points")
        if triangles is not None:
            triangles = np.asarray(triangles, dtype=np.int64).reshape(-1)
            if len(triangles) != len(points) or (triangles < 0).any():
                raise ValueError(f"triangles: expected {len(points)} indices >= 0")
        if len(points) == 0:
            raise ValueError("points: empty")
        batch_points = _count(batch_points, "batch_points", 1, 1_000_000)

        template = pb.LightVisibilityRequest(radiance=float(radiance), want_polygons=polygons)
        template.scene.name, template.scene.version = scene, version
        for vertex in light:
            _vec3(vertex, "light", template.light.vertices.add())
        template.exclude_nodes.extend(exclude_nodes)
        if shadow_tolerance is not None:
            tolerance = float(shadow_tolerance)
            if not 0.0 <= tolerance <= 1.0:
                raise ValueError(f"shadow_tolerance: {shadow_tolerance} is not in [0, 1]")
            template.shadow_tolerance = tolerance
        if receiver_region is not None:
            low, high = receiver_region
            _vec3(low, "receiver_region[0]", template.receiver_region.min)
            _vec3(high, "receiver_region[1]", template.receiver_region.max)
        total = len(points)
        starts = list(range(0, total, batch_points))

        def batches():
            for start in starts:
                request = pb.LightVisibilityRequest()
                request.CopyFrom(template)
                end = min(total, start + batch_points)
                for i in range(start, end):
                    point = request.points.add()
                    p = points[i]
                    point.position.x, point.position.y, point.position.z = p
                    if normals is not None:
                        q = normals[i]
                        point.normal.x, point.normal.y, point.normal.z = q
                    if triangles is not None:
                        point.triangle = int(triangles[i])
                yield request

        fraction = np.empty(total, dtype=np.float64)
        solid = np.empty(total, dtype=np.float64)
        irradiance = np.empty(total, dtype=np.float64)
        fraction_error = np.empty(total, dtype=np.float64)
        irradiance_error = np.empty(total, dtype=np.float64)
        visible_polygons = [] if polygons else None
        responses = []

        def on_message(r):
            start = len(responses) * batch_points
            count = len(r.points)
            if start >= total or count != min(batch_points, total - start):
                raise VisqError(grpc.StatusCode.DATA_LOSS,
                                f"LightVisibilityStream: batch {len(responses)} answered {count} points")
            for i, p in enumerate(r.points):
                fraction[start + i] = p.visible_fraction
                solid[start + i] = p.visible_solid_angle_fraction
                irradiance[start + i] = p.irradiance
                fraction_error[start + i] = p.visible_fraction_error
                irradiance_error[start + i] = p.irradiance_error
                if polygons:
                    visible_polygons.append([np.array([(v.x, v.y, v.z) for v in poly.vertices]).reshape(-1, 3)
                                             for poly in p.visible_polygons])
            r.ClearField("points")
            responses.append(r)
            if progress is not None:
                progress(min(total, start + count), total)

        call = self._stub.LightVisibilityStream(batches(), timeout=self._deadline(timeout, True),
                                                metadata=self._meta(scene))
        self._drain(call, cancel, on_message)
        if len(responses) != len(starts):
            raise VisqError(grpc.StatusCode.DATA_LOSS, f"{len(responses)} answers for {len(starts)} batches")
        return LightVisibility(fraction.reshape(shape), solid.reshape(shape), irradiance.reshape(shape),
                               visible_polygons, responses, fraction_error.reshape(shape),
                               irradiance_error.reshape(shape))

    # -- voxels, transmittance, volumetric shadows -----------------------------

    def voxelize(self, scene, width=128, height=128, slices=128, axis=1, box=None, solid=False,
                 local_precision=False, conservative=False, nodes=(), version=0, timeout=_UNSET, cancel=None) -> VoxelGrid:
        """Slicemap voxelization. box: None (the scene's bounds, sliced along
        `axis`) or a dict of center, axis_u, axis_v, axis_w, half_extent."""
        request = pb.VoxelizeRequest()
        request.scene.name, request.scene.version = scene, version
        request.width = _count(width, "width", 1, 4096)
        request.height = _count(height, "height", 1, 4096)
        request.slices = _count(slices, "slices", 1, 4096)
        request.depth_axis = _count(axis, "axis", 0, 2)
        if box is not None:
            for key in ("center", "axis_u", "axis_v", "axis_w", "half_extent"):
                if key not in box:
                    raise ValueError(f"box.{key}: missing")
                _vec3(box[key], f"box.{key}", getattr(request.box, key))
        request.mode = pb.VoxelizeRequest.SOLID if solid else pb.VoxelizeRequest.SURFACE
        request.local_precision, request.conservative = local_precision, conservative
        request.nodes.extend(nodes)
        chunks, f = self._chunked_stream(self._stub.Voxelize, "Voxelize", request, scene, timeout, cancel,
                                         [("bits", "offset", np.uint32, 1), ("column_near", "offset", np.float32, 1),
                                          ("column_far", "offset", np.float32, 1)])
        h, w = f.height, f.width
        return VoxelGrid(bits=chunks.get("bits", np.uint32, (h, w, f.words_per_column), required=True),
                         column_near=chunks.get("column_near", np.float32, (h, w)),
                         column_far=chunks.get("column_far", np.float32, (h, w)), figures=f)

    def transmittance(self, scene, light, absorbers, light_kind="directional", points=None, receiver=None,
                      width=64, height=64, resolution=256, slices=256, version=0, timeout=_UNSET,
                      method=None) -> Transmittance:
        """Light reaching points (and/or a receiver patch's texels) through
        absorbing nodes. light: the direction light travels (directional) or
        the light's position (point). absorbers: {node: absorption}.
        method: None (the server runs the faster here; the answer's
        accuracy.method says which), "slicemap" (the paper's, on the GPU:
        each point's light-view texel's centre ray) or "ray-stabbing" (each
        point's own ray, cast on the server's CPU)."""
        request = pb.TransmittanceRequest()
        if method is not None:
            request.method = _choice(method, "method", {"slicemap": pb.TransmittanceRequest.SLICEMAP,
                                                        "ray-stabbing": pb.TransmittanceRequest.RAY_STABBING})
        request.scene.name, request.scene.version = scene, version
        kind = _choice(light_kind, "light_kind", {"directional": pb.TransmittanceRequest.DIRECTIONAL,
                                                  "point": pb.TransmittanceRequest.POINT})
        request.light_kind = kind
        _vec3(light, "light", request.light_position if kind == pb.TransmittanceRequest.POINT
              else request.light_direction)
        for node, absorption in dict(absorbers).items():
            request.absorbers.add(node=node, absorption=float(absorption))
        count = 0
        if points is not None:
            for p in _points(points, "points"):
                _vec3(p, "points", request.points.add())
                count += 1
        shape = None
        if receiver is not None:
            _patch(receiver, "receiver", request.receiver)
            request.receiver_width = _count(width, "width", 1, 4096)
            request.receiver_height = _count(height, "height", 1, 4096)
            shape = (request.receiver_height, request.receiver_width)
        request.resolution = _count(resolution, "resolution", 1, 8192)
        request.slices = _count(slices, "slices", 1, 4096)
        r = self._unary(self._stub.Transmittance, request, scene, timeout)
        return Transmittance(_array(r.transmittance, np.float32), _array(r.optical_depth, np.float32),
                             _array(r.optical_depth_error, np.float32), _array(r.lateral_offset, np.float32),
                             count, shape, r)

    def volumetric_shadow(self, scene, camera_position, camera_forward, camera_up=(0, 1, 0), fov=60.0, width=320,
                          height=240, sun=(0.3, -1.0, 0.2), light_kind="directional", light_position=None,
                          cone_angle_deg=30.0, light_color=(1, 1, 1), intensity=1.0, scattering=0.05,
                          extinction=0.05, hg_g=0.0, shadow_map_size=1024, method="min-max", combined=False,
                          medium_box=None, estimate_error=False, version=0, timeout=_UNSET,
                          cancel=None) -> VolumetricImage:
        """Single-scattering light shafts from a pinhole camera; RGB images
        shaped (height, width, 3), row 0 at the top. `medium_box`: where the
        medium is, ((min x, y, z), (max x, y, z)); None: the scene's bounds.
        `estimate_error`: figures.accuracy states the error the shadow map's
        resolution leaves, estimated from renders with a half and a quarter
        of the map (Richardson's estimate)."""
        request = pb.VolumetricShadowRequest()
        request.scene.name, request.scene.version = scene, version
        _vec3(camera_position, "camera_position", request.camera_position)
        _vec3(camera_forward, "camera_forward", request.camera_forward)
        _vec3(camera_up, "camera_up", request.camera_up)
        request.vertical_fov_deg = float(fov)
        request.width, request.height = _count(width, "width", 1, 4096), _count(height, "height", 1, 4096)
        request.light_kind = _choice(light_kind, "light_kind", {"directional": pb.VolumetricShadowRequest.DIRECTIONAL,
                                                                "spot": pb.VolumetricShadowRequest.SPOT})
        _vec3(sun, "sun", request.light_direction)
        if request.light_kind == pb.VolumetricShadowRequest.SPOT:
            if light_position is None:
                raise ValueError("light_position: required for a spot light")
            _vec3(light_position, "light_position", request.light_position)
            request.cone_angle_deg = float(cone_angle_deg)
        _vec3(light_color, "light_color", request.light_color)
        request.light_intensity = float(intensity)
        request.scattering, request.extinction, request.hg_g = float(scattering), float(extinction), float(hg_g)
        request.shadow_map_size = _count(shadow_map_size, "shadow_map_size", 16, 4096)
        request.method = _choice(method, "method", {"min-max": pb.VolumetricShadowRequest.MIN_MAX,
                                                    "ray-marching": pb.VolumetricShadowRequest.RAY_MARCHING})
        request.combined_image = combined
        request.estimate_error = bool(estimate_error)
        if medium_box is not None:
            low, high = medium_box
            _vec3(low, "medium_box", request.medium_box.min)
            _vec3(high, "medium_box", request.medium_box.max)
        chunks, f = self._chunked_stream(self._stub.VolumetricShadow, "VolumetricShadow", request, scene, timeout,
                                         cancel, [("inscattering", "offset", np.float32, 1),
                                                  ("combined", "offset", np.float32, 1)])
        shape = (f.height, f.width, 3)
        return VolumetricImage(chunks.get("inscattering", np.float32, shape, required=True),
                               chunks.get("combined", np.float32, shape), f)

    # -- obscurances -----------------------------------------------------------

    def compute_obscurances(self, scene, d_max, resolution=256, directions=256, seed=1, color_bleeding=False,
                            force_built_atlas=False, want_averages=False, first_direction=0, total_directions=0,
                            partial_only=False, method="auto", rays_per_patch=256, target=None,
                            bundle_resolution=0, version=0, want_errors=False, progress=None, timeout=_UNSET,
                            cancel=None) -> ObscuranceBake:
        """Bakes obscurances. progress(visq.Progress) is called for each
        progress message; cancel=visq.Cancellation() stops the bake.
        method 'raycast' is the Embree estimator (rays_per_patch),
        'depth-peeling' the paper's GPU bake, 'auto' the faster of the two
        here at the same bound (a shard range peels); target
        {max_error, confidence, time_budget_ms} lets the server choose."""
        request = pb.ComputeObscurancesRequest()
        request.scene.name, request.scene.version = scene, version
        if not (isinstance(d_max, (int, float)) and math.isfinite(d_max) and d_max > 0):
            raise ValueError(f"d_max: {d_max!r} must be a finite number > 0")
        request.d_max = float(d_max)
        request.resolution = _count(resolution, "resolution", 1, 8192)
        request.seed = int(seed)
        request.color_bleeding, request.force_built_atlas = color_bleeding, force_built_atlas
        request.want_averages, request.partial_only = want_averages, partial_only
        request.want_errors = bool(want_errors)
        request.bundle_resolution = _count(bundle_resolution, "bundle_resolution", 0)
        chosen = _choice(method, "method", {"auto": pb.ComputeObscurancesRequest.METHOD_UNSPECIFIED,
                                            "depth-peeling": pb.ComputeObscurancesRequest.DEPTH_PEELING,
                                            "raycast": pb.ComputeObscurancesRequest.RAYCAST,
                                            "gpu-raycast": pb.ComputeObscurancesRequest.GPU_RAYCAST})
        if target is not None:
            _target(target, request.target)
        elif chosen in (pb.ComputeObscurancesRequest.RAYCAST, pb.ComputeObscurancesRequest.GPU_RAYCAST):
            request.method = chosen
            request.rays_per_patch = _count(rays_per_patch, "rays_per_patch", 1, 65536)
        else:
            request.method = chosen
            request.direction_count = _count(directions, "directions", 1)
            request.first_direction = _count(first_direction, "first_direction", 0)
            request.total_directions = _count(total_directions, "total_directions", 0)
        chunks, figures = _Chunks(), []
        progress_messages = [0]

        def on_message(m):
            if m.HasField("progress"):
                progress_messages[0] += 1
                if progress is not None:
                    p = m.progress
                    progress(Progress(p.directions_done, p.directions_total, p.elapsed_s, p.estimated_s_left))
                return
            if m.HasField("figures"):
                figures.append(m.figures)
            for name, dtype in (("w", np.float32), ("intensity", np.float32), ("triangle_w", np.float32),
                                ("vertex_w", np.float32), ("w_error", np.float32), ("triangle_w_error", np.float32),
                                ("vertex_w_error", np.float32), ("partial_sums", np.uint64),
                                ("partial_counts", np.uint64)):
                chunks.add(name, getattr(m, name), m.offset, dtype)
            chunks.add("estimated", m.estimated, m.offset, np.uint8)

        self._server_stream(self._stub.ComputeObscurances, request, scene, timeout, cancel, on_message)
        if not figures:
            raise VisqError(grpc.StatusCode.DATA_LOSS, "ComputeObscurances: the stream carried no figures")
        f = figures[0]
        h, w = f.atlas.height, f.atlas.width

        def rows(name):
            array = chunks.get(name, np.float32, (chunks.sizes.get(name, 0),))
            return None if array is None else array.reshape(-1, 3)

        estimated = chunks.get("estimated", np.uint8, (h, w), required=not f.partial_only)
        return ObscuranceBake(
            w=chunks.get("w", np.float32, (h, w, 3), required=not f.partial_only),
            intensity=chunks.get("intensity", np.float32, (h, w, 3)),
            estimated=None if estimated is None else estimated.astype(bool),
            triangle_w=rows("triangle_w"), vertex_w=rows("vertex_w"),
            w_error=chunks.get("w_error", np.float32, (h, w)),
            triangle_w_error=chunks.get("triangle_w_error", np.float32, (chunks.sizes.get("triangle_w_error", 0),)),
            vertex_w_error=chunks.get("vertex_w_error", np.float32, (chunks.sizes.get("vertex_w_error", 0),)),
            partial_sums=chunks.get("partial_sums", np.uint64, (h, w, f.channels), required=f.partial_only),
            partial_counts=chunks.get("partial_counts", np.uint64, (h, w), required=f.partial_only),
            figures=f, progress_messages=progress_messages[0])

    def set_node_transform(self, scene, node, matrix, version=0, timeout=_UNSET) -> Any:
        """Moves a node and its subtree (in the server's memory only). node: a
        name or an index into SceneInfo.nodes. matrix: a 4x4 node-to-world
        matrix as numpy writes it (M @ [x, y, z, 1]), or 16 numbers
        column-major like glTF. Returns the new SceneInfo."""
        request = pb.SetNodeTransformRequest()
        request.scene.name, request.scene.version = scene, version
        if isinstance(node, (int, np.integer)) and not isinstance(node, bool):
            request.node_index = _count(node, "node", 0)
        else:
            request.node_name = str(node)
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape == (4, 4):
            m = m.flatten(order="F")
        if m.shape != (16,) or not np.isfinite(m).all():
            raise ValueError(f"matrix: expected a finite 4x4 matrix or 16 numbers, got shape {m.shape}")
        request.world_matrix.extend(m.tolist())
        return self._unary(self._stub.SetNodeTransform, request, scene, timeout)

    def update_obscurances(self, scene, want_full_w=False, version=0, timeout=_UNSET) -> ObscuranceUpdate:
        request = pb.UpdateObscurancesRequest(want_full_w=want_full_w)
        request.scene.name, request.scene.version = scene, version
        r = self._unary(self._stub.UpdateObscurances, request, scene, timeout)
        full = _array(r.full_w, np.float32)
        return ObscuranceUpdate(texels=_array(r.texels, np.uint32), w=_array(r.w, np.float32).reshape(-1, 3),
                                full_w=full.reshape(r.height, r.width, 3) if want_full_w and full.size else None,
                                response=r, w_error=_array(r.w_error, np.float32),
                                triangle_w_error=_array(r.triangle_w_error, np.float32),
                                vertex_w_error=_array(r.vertex_w_error, np.float32))

    def obscurance_preview(self, scene, camera_position, camera_forward, camera_up=(0, 1, 0), fov=60.0,
                           width=320, height=240, quantity="w", version=0, timeout=_UNSET, cancel=None) -> ObscurancePreview:
        """The scene's current obscurance solution seen from a camera."""
        request = pb.ObscurancePreviewRequest()
        request.scene.name, request.scene.version = scene, version
        _vec3(camera_position, "camera_position", request.camera_position)
        _vec3(camera_forward, "camera_forward", request.camera_forward)
        _vec3(camera_up, "camera_up", request.camera_up)
        request.vertical_fov_deg = float(fov)
        request.width, request.height = _count(width, "width", 1, 4096), _count(height, "height", 1, 4096)
        request.quantity = _choice(quantity, "quantity", {"w": pb.ObscurancePreviewRequest.W,
                                                          "intensity": pb.ObscurancePreviewRequest.INTENSITY,
                                                          "i": pb.ObscurancePreviewRequest.INTENSITY})
        chunks, f = self._chunked_stream(self._stub.RenderObscurancePreview, "RenderObscurancePreview", request, scene,
                                         timeout, cancel, [("rgb", "offset", np.float32, 1),
                                                           ("covered", "covered_offset", np.uint8, 1)])
        return ObscurancePreview(chunks.get("rgb", np.float32, (f.height, f.width, 3), required=True),
                                 chunks.get("covered", np.uint8, (f.height, f.width), required=True).astype(bool), f)

    def export_obscurances(self, scene, atlas_uvs=True, gltf=False, version=0, timeout=_UNSET,
                           cancel=None, vertex_colors=False) -> ObscuranceExport:
        """The current obscurance solution as a game mesh takes it: the atlas
        UV of every triangle corner, and/or the scene as binary glTF with
        its own normals and UV sets, the atlas UVs as the set after them (or
        its TEXCOORD_1 when the bake used it) and W as its occlusion texture;
        vertex_colors (with gltf) adds W per vertex as COLOR_0."""
        request = pb.ExportObscurancesRequest(want_atlas_uvs=bool(atlas_uvs), want_gltf=bool(gltf),
                                              want_vertex_colors=bool(vertex_colors))
        request.scene.name, request.scene.version = scene, version
        chunks, f = self._chunked_stream(self._stub.ExportObscurances, "ExportObscurances", request, scene, timeout,
                                         cancel, [("atlas_uv", "offset", np.float32, 1),
                                                  ("glb", "glb_offset", np.uint8, 1)])
        uv = chunks.get("atlas_uv", np.float32, (f.triangles, 3, 2), required=atlas_uvs)
        glb = chunks.get("glb", np.uint8, (chunks.sizes.get("glb", 0),), required=gltf)
        return ObscuranceExport(uv, None if glb is None else glb.tobytes(), f)


# ---------------------------------------------------------------------------
# Which files an upload sends.

def _gltf_json(path):
    with open(path, "rb") as f:
        data = f.read()
    if path.lower().endswith(".glb"):
        # 12-byte header, then the JSON chunk (length, 'JSON', bytes).
        if len(data) < 20 or data[:4] != b"glTF":
            raise ValueError(f"{path}: not a binary glTF (no 'glTF' magic)")
        length, kind = struct.unpack_from("<I4s", data, 12)
        if kind != b"JSON" or 20 + length > len(data):
            raise ValueError(f"{path}: the first GLB chunk is not JSON")
        data = data[20:20 + length]
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as error:
        raise ValueError(f"{path}: malformed glTF JSON ({error})") from None


def geometry_files(path):
    """(relative name, path) of the external buffers a .gltf/.glb names:
    what its geometry needs. Images are not sent: the server keeps no
    texture. A buffer URI that leaves the file's folder is refused here, so
    a hostile glTF cannot make the client send files from elsewhere."""
    path = os.fspath(path)
    doc = _gltf_json(path)
    folder = os.path.realpath(os.path.dirname(os.path.abspath(path)))
    files, seen = [], set()
    buffers = doc.get("buffers", []) if isinstance(doc, dict) else []
    for index, buffer in enumerate(buffers if isinstance(buffers, list) else []):
        if not isinstance(buffer, dict) or not isinstance(buffer.get("uri"), str):
            continue
        uri = buffer["uri"]
        if uri.startswith("data:"):
            continue
        relative = urllib.parse.unquote(uri)
        resolved = os.path.realpath(os.path.join(folder, relative))
        if os.path.isabs(relative) or os.path.commonpath([folder, resolved]) != folder:
            raise ValueError(f"buffers[{index}].uri: '{uri}' leaves the folder of {path}")
        if not os.path.isfile(resolved):
            raise FileNotFoundError(f"buffers[{index}].uri: '{uri}' ({resolved}) does not exist")
        if relative not in seen:
            seen.add(relative)
            files.append((relative, resolved))
    return files
