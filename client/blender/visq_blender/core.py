"""What the visq add-on does that needs no Blender: frames, the uploaded
glTF's triangles, matching them to Blender's, the moves to send, W per
corner, patches, the worker that runs a call off Blender's main thread and
the modal operator's steps around it, and the bake session as the .blend
keeps it. numpy only (visq is
imported where a call is made), so it is tested with plain python3
(client/blender/tests/test_core.py).

Frames. Blender's glTF exporter (export_yup, its default) writes a Blender
point (x, y, z) as glTF (x, z, -y): positions in a mesh's own frame, and
node transforms as C @ M @ C^-1 with C that rotation. visq flattens the file
to world space in glTF's frame, so everything sent to the server (a node's
world matrix, a patch) goes through C, and everything read back (positions)
through C^-1.
"""
import json
import math
import struct
import threading
import time

import numpy as np

# Blender (x, y, z) -> glTF (x, z, -y), as 4x4 acting on column vectors.
BLENDER_TO_GLTF = np.array([[1.0, 0.0, 0.0, 0.0],
                            [0.0, 0.0, 1.0, 0.0],
                            [0.0, -1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])
GLTF_TO_BLENDER = BLENDER_TO_GLTF.T


def to_gltf_points(points):
    """(..., 3) Blender coordinates -> glTF's (x, z, -y)."""
    p = np.asarray(points, dtype=np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def to_gltf_matrix(blender_world):
    """A Blender object's matrix_world (4x4, column vectors, as
    np.array(obj.matrix_world) gives it) as the world matrix of its node in
    the file Blender's exporter wrote: the matrix SetNodeTransform takes."""
    m = np.asarray(blender_world, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"matrix_world: expected a finite 4x4 matrix, got shape {m.shape}")
    return BLENDER_TO_GLTF @ m @ GLTF_TO_BLENDER


# ---------------------------------------------------------------------------
# The uploaded .glb's triangles, node by node, in the server's order.

class GlbError(ValueError):
    pass


_COMPONENTS = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def read_glb(path):
    """(json document, BIN chunk bytes) of a binary glTF."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 20 or data[:4] != b"glTF":
        raise GlbError(f"{path}: not a binary glTF")
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON" or 20 + length > len(data):
        raise GlbError(f"{path}: the first chunk is not JSON")
    doc = json.loads(data[20:20 + length].decode("utf-8"))
    binary = b""
    offset = 20 + length
    if offset + 8 <= len(data):
        size, kind = struct.unpack_from("<I4s", data, offset)
        if kind == b"BIN\x00":
            binary = data[offset + 8:offset + 8 + size]
    return doc, binary


def _accessor(doc, binary, index, what):
    try:
        accessor = doc["accessors"][index]
        view = doc["bufferViews"][accessor["bufferView"]]
        dtype = _COMPONENTS[accessor["componentType"]]
        width = _WIDTH[accessor["type"]]
    except (KeyError, IndexError, TypeError):
        raise GlbError(f"accessors[{index}] ({what}): not a plain accessor this add-on reads") from None
    if view.get("buffer", 0) != 0 or "sparse" in accessor:
        raise GlbError(f"accessors[{index}] ({what}): external or sparse data")
    count = int(accessor["count"])
    item = np.dtype(dtype).itemsize * width
    stride = int(view.get("byteStride", item))
    start = int(view.get("byteOffset", 0)) + int(accessor.get("byteOffset", 0))
    if count and start + stride * (count - 1) + item > len(binary):
        raise GlbError(f"accessors[{index}] ({what}): runs past the binary chunk")
    raw = np.frombuffer(binary, dtype=np.uint8, count=stride * (count - 1) + item if count else 0, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, item), strides=(stride, 1)) if count else \
        np.zeros((0, item), np.uint8)
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width)


def glb_node_triangles(path):
    """[(node name, (n, 3, 3) float64 corner positions in the node's own glTF
    frame)] for every node of the default scene, depth first with children
    in order: the order visq-server flattens a file in (its triangles are
    numbered node after node, a node's primitives in order)."""
    doc, binary = read_glb(path)
    nodes, meshes = doc.get("nodes", []), doc.get("meshes", [])
    scenes = doc.get("scenes", [])
    roots = scenes[doc.get("scene", 0)].get("nodes", []) if scenes else list(range(len(nodes)))
    out = []
    stack = list(reversed(roots))
    while stack:
        index = stack.pop()
        node = nodes[index]
        triangles = []
        if "mesh" in node:
            for p, primitive in enumerate(meshes[node["mesh"]].get("primitives", [])):
                what = f"meshes[{node['mesh']}].primitives[{p}]"
                if primitive.get("mode", 4) != 4:
                    raise GlbError(f"{what}: mode {primitive.get('mode')}, only triangle lists are read here")
                positions = _accessor(doc, binary, primitive["attributes"]["POSITION"], what).astype(np.float64)
                if "indices" in primitive:
                    indices = _accessor(doc, binary, primitive["indices"], what).reshape(-1).astype(np.int64)
                else:
                    indices = np.arange(len(positions))
                triangles.append(positions[indices[: len(indices) // 3 * 3]].reshape(-1, 3, 3))
        out.append((node.get("name", ""), np.concatenate(triangles) if triangles else np.zeros((0, 3, 3))))
        stack.extend(reversed(node.get("children", [])))
    return out


def node_ranges(glb_nodes, server_nodes):
    """{node name: (first triangle, (n, 3, 3) positions)}: each named node's
    triangles and where the server's numbering of them starts.
    server_nodes: [(name, triangle_count)] as SceneInfo.nodes lists them.
    Refuses a file the server read otherwise (a triangle it dropped, another
    order): the W it answers could not be put on the right faces."""
    if len(glb_nodes) != len(server_nodes):
        raise GlbError(f"the server has {len(server_nodes)} nodes, the exported file {len(glb_nodes)}")
    ranges, first = {}, 0
    for (name, triangles), (server_name, count) in zip(glb_nodes, server_nodes):
        if name != server_name or len(triangles) != count:
            raise GlbError(f"node '{server_name}' has {count} triangles on the server, '{name}' {len(triangles)} "
                           "in the exported file")
        if count:
            if name in ranges:
                raise GlbError(f"two nodes are named '{name}'")
            ranges[name] = (first, triangles)
        first += count
    return ranges


def node_parents(server_nodes, names):
    """{name: the nearest ancestor in `names`, or ""} for each of `names`:
    server_nodes [(name, parent index or -1)] as SceneInfo.nodes lists them.
    The hierarchy that counts for a move is the server's (a Blender parent
    that was not exported is no node there)."""
    index = {name: i for i, (name, _) in enumerate(server_nodes)}
    parents = {}
    for name in names:
        parent = server_nodes[index[name]][1]
        while parent >= 0 and server_nodes[parent][0] not in names:
            parent = server_nodes[parent][1]
        parents[name] = server_nodes[parent][0] if parent >= 0 else ""
    return parents


PLACEMENT_TOLERANCE = 1e-5  # world-matrix entries (metres): Blender's matrices are float32


class MoveError(ValueError):
    pass


def moves_to_send(target, placed, parents, dynamic=(), tolerance=PLACEMENT_TOLERANCE):
    """The SetNodeTransform calls that put the server's nodes where Blender
    has them: the topmost nodes that moved, each carrying its subtree
    rigidly as the server moves it. visq's update moves a node's subtree as
    one object, for as long as the bake lives, and refuses (and drops the
    bake) where one object holds another: so a node that moved on its moved
    ancestor, or a node inside or above one the server already moves on its
    own (`dynamic`, the nodes sent since the bake), is a MoveError that names
    both, found before anything is sent.
    target {name: the world matrix Blender has}, placed {name: the one the
    server has}, parents {name: parent name or ""}, for the same names; any
    one frame (Blender's or glTF's), 4x4. Returns ([(name, matrix)] to send,
    every node's placement after them: the target where within tolerance)."""
    target = {name: np.asarray(m, dtype=np.float64) for name, m in target.items()}
    placed = {name: np.asarray(m, dtype=np.float64) for name, m in placed.items()}

    def ancestors(name):
        parent = parents.get(name, "")
        while parent:
            yield parent
            parent = parents.get(parent, "")

    def close(a, b):
        return np.allclose(a, b, rtol=0, atol=tolerance)

    misplaced = [name for name in target if not close(target[name], placed[name])]
    sent = [name for name in misplaced if not any(a in misplaced for a in ancestors(name))]
    after = dict(placed)
    for name in sent:
        carry = target[name] @ np.linalg.inv(placed[name])
        for other in placed:
            if name in ancestors(other):
                after[other] = carry @ placed[other]
        after[name] = target[name]
    for name in misplaced:
        if not close(target[name], after[name]):
            carrier = next(a for a in ancestors(name) if a in sent)
            raise MoveError(f"'{name}' moved on '{carrier}', and visq moves '{carrier}' with what it holds as one "
                            f"object: put '{name}' back where it was on '{carrier}', or bake again")
    for name in sent:
        for other in set(dynamic) | set(sent):
            if other in ancestors(name):
                raise MoveError(f"'{name}' is part of '{other}', which visq moves as one object with what it holds "
                                f"since '{other}' moved: bake again to move '{name}' on its own")
            if name in ancestors(other):
                raise MoveError(f"'{name}' holds '{other}', which visq moves as an object of its own since it moved: "
                                f"bake again to move '{name}' with it")
    after.update({name: target[name] for name in target if close(target[name], after[name])})
    return [(name, target[name]) for name in sent], after


# ---------------------------------------------------------------------------
# Blender's loop triangles against the file's.

def _corner_order(blender, server):
    """Per triangle pair ((k, 3, 3) each): which server corner is nearest each
    Blender corner, and the worst such distance."""
    distance = np.linalg.norm(blender[:, :, None, :] - server[:, None, :, :], axis=3)  # (k, 3, 3)
    return distance.argmin(axis=2), distance.min(axis=2).max(axis=1)


def match_triangles(blender, server, tolerance=None):
    """For each Blender triangle ((m, 3, 3) corners, glTF frame), the index of
    the server triangle with the same corners ((n, 3, 3)) and, per Blender
    corner, which of that triangle's corners it is: (index (m,), corner
    (m, 3)); -1 where none matches. Matched by centre on a hash grid: in one
    vectorized pass where the centres fall in the same cell, then one by one
    over the neighbouring cells for the rest."""
    blender = np.asarray(blender, dtype=np.float64).reshape(-1, 3, 3)
    server = np.asarray(server, dtype=np.float64).reshape(-1, 3, 3)
    index = np.full(len(blender), -1, dtype=np.int64)
    corner = np.full((len(blender), 3), -1, dtype=np.int64)
    if not len(blender) or not len(server):
        return index, corner
    if tolerance is None:
        extent = float(np.ptp(server.reshape(-1, 3), axis=0).max())
        tolerance = max(extent, 1.0) * 1e-5
    cell = tolerance * 4
    server_keys = np.floor(server.mean(axis=1) / cell).astype(np.int64)
    blender_keys = np.floor(blender.mean(axis=1) / cell).astype(np.int64)

    # Same cell: sort the server's cells, look each Blender cell up.
    def packed(keys):  # one int64 per cell; a collision only costs a look in the slow pass
        with np.errstate(over="ignore"):
            return keys[:, 0] * 73856093 ^ keys[:, 1] * 19349663 ^ keys[:, 2] * 83492791

    order = np.argsort(packed(server_keys), kind="stable")
    sorted_keys = packed(server_keys)[order]
    position = np.searchsorted(sorted_keys, packed(blender_keys))
    found = position < len(sorted_keys)
    found[found] = sorted_keys[position[found]] == packed(blender_keys)[found]
    candidates = np.nonzero(found)[0]
    if len(candidates):
        chosen = order[position[candidates]]
        corners, error = _corner_order(blender[candidates], server[chosen])
        good = error < tolerance * 3
        index[candidates[good]] = chosen[good]
        corner[candidates[good]] = corners[good]

    # The rest (a centre near a cell's edge, coincident triangles): the
    # neighbouring cells, one triangle at a time.
    rest = np.nonzero(index < 0)[0]
    if len(rest):
        grid = {}
        for i, key in enumerate(map(tuple, server_keys)):
            grid.setdefault(key, []).append(i)
        offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]
        for j in rest:
            kx, ky, kz = blender_keys[j]
            near = [i for a, b, d in offsets for i in grid.get((kx + a, ky + b, kz + d), ())]
            if not near:
                continue
            corners, error = _corner_order(np.repeat(blender[j][None], len(near), axis=0), server[near])
            best = int(error.argmin())
            if error[best] < tolerance * 3:
                index[j], corner[j] = near[best], corners[best]
    return index, corner


def server_corners(corner, mirrored):
    """Corner indices in the file's order -> the server's: visq flips the
    winding of a mirrored node's triangles (corners 1 and 2 swap), and its
    atlas UVs follow its own order."""
    corner = np.asarray(corner, dtype=np.int64)
    if not mirrored:
        return corner
    swapped = np.array([0, 2, 1])[np.clip(corner, 0, 2)]
    return np.where(corner >= 0, swapped, corner)


def loop_uvs(atlas_uv, server_index, corner, loops, loop_count):
    """Blender UVs (loop_count, 2) for the atlas layer: each loop triangle's
    corners from the atlas UVs ((N, 3, 2) glTF UVs, v down) of the server
    triangle it matched (server_index: global indices, -1 unmatched), flipped
    to Blender's v up. Returns (uvs, written mask per loop, corners where two
    triangles of one face disagree on a shared loop: the atlas cut it apart)."""
    uvs = np.zeros((loop_count, 2), dtype=np.float32)
    written = np.zeros(loop_count, dtype=bool)
    valid = np.nonzero(np.asarray(server_index) >= 0)[0]
    if not len(valid):
        return uvs, written, 0
    atlas_uv = np.asarray(atlas_uv, dtype=np.float32)
    values = atlas_uv[np.asarray(server_index)[valid][:, None], np.asarray(corner)[valid]].reshape(-1, 2)
    values = np.stack([values[:, 0], 1.0 - values[:, 1]], axis=1)
    targets = np.asarray(loops)[valid].reshape(-1)
    # A loop in two triangles (a quad's diagonal) with two different UVs.
    order = np.argsort(targets, kind="stable")
    same = targets[order][1:] == targets[order][:-1]
    differ = np.abs(values[order][1:] - values[order][:-1]).max(axis=1) > 1e-6
    torn = int((same & differ).sum())
    uvs[targets] = values
    written[targets] = True
    return uvs, written, torn


def triangle_areas(corners):
    corners = np.asarray(corners, dtype=np.float64)
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)


def polygon_w(triangle_w, polygon, areas, polygon_count):
    """Per polygon, the area-weighted mean of its loop triangles' W
    ((m, 3) per triangle, NaN rows skipped): what its corners show.
    Returns (polygon_count, 3), NaN where no triangle had a value."""
    triangle_w = np.asarray(triangle_w, dtype=np.float64)
    ok = np.isfinite(triangle_w).all(axis=1)
    weights = np.where(ok, np.maximum(areas, 1e-30), 0.0)
    sums = np.zeros((polygon_count, 3))
    np.add.at(sums, polygon, np.where(ok[:, None], triangle_w, 0.0) * weights[:, None])
    total = np.zeros(polygon_count)
    np.add.at(total, polygon, weights)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / total[:, None]


def loop_polygons(loops, polygon, loop_count):
    """Per loop (corner), its polygon: from the loop triangles' loops (m, 3)
    and polygons (m,)."""
    loop_polygon = np.zeros(loop_count, dtype=np.int64)
    loop_polygon[np.asarray(loops, dtype=np.int64).reshape(-1)] = np.repeat(np.asarray(polygon, dtype=np.int64), 3)
    return loop_polygon


def corner_colors(per_polygon_w, loop_polygon):
    """RGBA per loop (corner) from per-polygon W: the colour attribute."""
    w = np.nan_to_num(np.asarray(per_polygon_w, dtype=np.float32), nan=1.0)[loop_polygon]
    return np.concatenate([w, np.ones((len(w), 1), np.float32)], axis=1)


# ---------------------------------------------------------------------------
# Images: the atlas is indexed [y, x] with row 0 at v = 0 (glTF's top);
# Blender stores rows from the bottom.

def atlas_to_pixels(w):
    """(height, width, 3) atlas W -> Blender image pixels (height, width, 4)
    float32, rows bottom up."""
    w = np.asarray(w, dtype=np.float32)
    pixels = np.ones(w.shape[:2] + (4,), dtype=np.float32)
    pixels[..., :3] = w[::-1]
    return pixels


def apply_texels(pixels, texels, w):
    """Writes changed texels (y * width + x) into Blender pixels in place."""
    height, width = pixels.shape[:2]
    texels = np.asarray(texels, dtype=np.int64)
    if texels.size and (texels.min() < 0 or texels.max() >= width * height):
        raise ValueError(f"texels: index beyond the {width}x{height} atlas")
    y, x = texels // width, texels % width
    pixels[height - 1 - y, x, :3] = np.asarray(w, dtype=np.float32).reshape(-1, 3)
    return len(texels)


def map_to_pixels(fraction):
    """(height, width) visible fraction, row y along the receiver's edge_v,
    -> grey Blender pixels: Blender's row 0 is the image's bottom, which is
    where a receiver face's edge_v starts: no flip."""
    f = np.asarray(fraction, dtype=np.float32)
    pixels = np.ones(f.shape + (4,), dtype=np.float32)
    pixels[..., 0] = pixels[..., 1] = pixels[..., 2] = f
    return pixels


def face_patch(corners):
    """A Blender face's world corners ((k, 3), k >= 3, counter-clockwise seen
    from its front) as a visq patch in glTF's frame: origin the first corner,
    edge_u to the second, edge_v to the last, so edge_u x edge_v faces the
    face's front (a quad's parallelogram; a triangle's spans its bounds)."""
    c = to_gltf_points(np.asarray(corners, dtype=np.float64))
    if c.ndim != 2 or len(c) < 3 or not np.isfinite(c).all():
        raise ValueError("face: expected three or more finite corners")
    origin, u, v = c[0], c[1] - c[0], c[-1] - c[0]
    if not np.linalg.norm(np.cross(u, v)) > 0:
        raise ValueError("face: its first edges are parallel (a degenerate face)")
    return tuple(origin), tuple(u), tuple(v)


# ---------------------------------------------------------------------------
# A call off Blender's main thread.

class Job:
    """Runs work(job) on a thread; Blender's modal operator polls it on a
    timer (done, fraction, message) and calls cancel() on Esc. work() reads
    job.cancellation (a visq.Cancellation, or None before visq is imported)
    and reports with job.report_progress(fraction, message)."""

    def __init__(self, work, cancellation=None):
        self._work = work
        self.cancellation = cancellation
        self.fraction = 0.0
        self.message = ""
        self.result = None
        self.error = None
        self.cancel_requested = False
        self.started = time.monotonic()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="visq-blender-job", daemon=True)

    def start(self):
        self._thread.start()
        return self

    def run_here(self):
        """The same work on the calling thread (scripts, background mode)."""
        self._run()
        return self

    def _run(self):
        try:
            self.result = self._work(self)
        except BaseException as error:  # shown to the artist, never lost on the thread
            self.error = error
        finally:
            self._done.set()

    def report_progress(self, fraction, message=""):
        if math.isfinite(fraction):
            self.fraction = min(1.0, max(0.0, float(fraction)))
        self.message = message

    def cancel(self):
        self.cancel_requested = True
        if self.cancellation is not None:
            self.cancellation.cancel()

    @property
    def done(self):
        return self._done.is_set()

    def wait(self, timeout=None):
        return self._done.wait(timeout)


# What the modal operator does with one event, without Blender: the
# operator's modal() turns Blender's event into one of these names and
# applies the step (client/blender/visq_blender/__init__.py, TaskRunner).

class ModalStep:
    """action: "CANCEL" (Esc: the job was told to stop; the modal keeps
    running until the worker ends), "PASS" (not the modal's event), "WAIT"
    (a timer tick while the job runs: show percent and status), "DONE" (the
    worker ended: finish or report its error)."""

    def __init__(self, action, percent=None, status=None):
        self.action, self.percent, self.status = action, percent, status

    def __repr__(self):
        return f"ModalStep({self.action!r}, {self.percent!r}, {self.status!r})"


def modal_step(job, event, now=None):
    """One step of the modal shell around `job` (a Job) for `event`: "ESC"
    (the key pressed), "TIMER" (the operator's timer) or any other name."""
    if event == "ESC" and not job.cancel_requested:
        job.cancel()
        return ModalStep("CANCEL", round(job.fraction * 100), "visq: cancelling (Esc cancels)")
    if event != "TIMER":
        return ModalStep("PASS")
    if job.done:
        return ModalStep("DONE", 100)
    # A ray-cast bake may send no progress: the elapsed time shows it is alive.
    elapsed = (time.monotonic() if now is None else now) - job.started
    state = "cancelling" if job.cancel_requested else f"{job.message} {job.fraction:.0%}, {elapsed:.0f} s"
    return ModalStep("WAIT", round(job.fraction * 100), f"visq: {state} (Esc cancels)")


# ---------------------------------------------------------------------------
# The bake session as it is saved in the .blend: plain values and typed
# arrays that Blender keeps as ID properties (numpy arrays become int32,
# float32 and float64 arrays there; 64-bit integers do not fit one, so the
# scene version is text).

SESSION_FORMAT = 1


class SessionError(ValueError):
    pass


def session_record(scene, version, image, objects):
    """The record to store: scene (the server's scene name), version (the
    server's scene version that the W below matches), image (the W image's
    name) and objects {node name: {"object": the Blender object (opaque
    here), "parent": its nearest baked ancestor on the server ("" for none),
    "dynamic": whether it was sent since the bake (see moves_to_send),
    "matrix": its world matrix (4x4) as last sent, "loop_count",
    "polygon_count", "server": (m,) the server triangle of each of its loop
    triangles (-1: none), "triangle_w": (m, 3) their W}}."""
    record = {"format": SESSION_FORMAT, "scene": str(scene), "version": str(int(version)), "image": str(image),
              "objects": {}}
    for name, o in objects.items():
        server = np.asarray(o["server"], dtype=np.int64)
        if server.size and server.max() >= 2 ** 31:
            raise SessionError(f"object '{name}': triangle {server.max()} beyond what the .blend stores")
        record["objects"][name] = {
            "object": o["object"], "parent": str(o["parent"]), "dynamic": int(bool(o["dynamic"])),
            "matrix": np.asarray(o["matrix"], dtype=np.float64).reshape(16),
            "loop_count": int(o["loop_count"]), "polygon_count": int(o["polygon_count"]),
            "server": server.astype(np.int32),
            "triangle_w": np.asarray(o["triangle_w"], dtype=np.float32).reshape(-1)}
    return record


def read_session(record):
    """A stored record (a dict, or Blender's ID property group) back as
    session_record's arguments, with numpy arrays copied out of it. A record
    this add-on did not write, or wrote in another format, is a SessionError
    that says to bake again."""
    def fail(what):
        return SessionError(f"the bake saved in this file is unreadable ({what}); run Bake obscurances again")

    try:
        if int(record.get("format", 0)) != SESSION_FORMAT:
            raise fail(f"format {record.get('format')}, this add-on reads {SESSION_FORMAT}")
        session = {"scene": str(record["scene"]), "version": int(str(record["version"])),
                   "image": str(record["image"]), "objects": {}}
        for name, o in record["objects"].items():
            server = np.array(np.asarray(o["server"]), dtype=np.int64)
            triangle_w = np.array(np.asarray(o["triangle_w"]), dtype=np.float64)
            matrix = np.array(np.asarray(o["matrix"]), dtype=np.float64)
            if matrix.size != 16 or triangle_w.size != 3 * server.size:
                raise fail(f"object '{name}': {matrix.size} matrix entries, {server.size} triangles with "
                           f"{triangle_w.size} W values")
            session["objects"][name] = {
                "object": o.get("object"), "parent": str(o["parent"]), "dynamic": bool(o["dynamic"]),
                "matrix": matrix.reshape(4, 4),
                "loop_count": int(o["loop_count"]),
                "polygon_count": int(o["polygon_count"]), "server": server, "triangle_w": triangle_w.reshape(-1, 3)}
    except SessionError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise fail(f"{type(error).__name__}: {error}") from None
    return session


def refresh_triangle_w(server, triangle_w, changed, changed_w):
    """An object's loop triangles after UpdateObscurances: server (m,) their
    server triangles (-1: none), triangle_w (m, 3) their W before; changed
    (k,) the update's triangles and changed_w (k, 3) their W. Returns (W
    after, a copy; the mask of triangles that changed)."""
    server = np.asarray(server, dtype=np.int64)
    changed = np.asarray(changed, dtype=np.int64)
    changed_w = np.asarray(changed_w, dtype=np.float64).reshape(-1, 3)
    after = np.array(triangle_w, dtype=np.float64).reshape(-1, 3)
    order = np.argsort(changed, kind="stable")
    at = np.searchsorted(changed[order], server)
    found = at < len(changed)
    found[found] = changed[order][at[found]] == server[found]
    hit = found & (server >= 0)
    after[hit] = changed_w[order][at[hit]]
    return after, hit


def describe_error(error):
    """One line for Blender's report: what failed, and what to do."""
    name = type(error).__name__
    code = getattr(error, "code", None)
    text = str(error) or name
    if name == "Cancelled":
        return "visq: cancelled"
    if code is not None and getattr(code, "name", "") == "UNAVAILABLE":
        return f"visq: the server cannot be reached ({text}); check the address in the add-on's preferences"
    if code is not None and getattr(code, "name", "") == "UNAUTHENTICATED":
        return f"visq: the server refused the token ({text}); check the token in the add-on's preferences"
    if code is not None and getattr(code, "name", "") in ("NOT_FOUND", "FAILED_PRECONDITION"):
        return f"visq: the server no longer has this bake ({text}); run Bake obscurances again"
    if code is not None and getattr(code, "name", "") == "DEADLINE_EXCEEDED":
        return f"visq: the server did not answer in time ({text})"
    if code is not None or isinstance(error, (OSError, ValueError)):
        return f"visq: {text}"  # a server's status names its code: "INVALID_ARGUMENT: d_max: ..."
    return f"visq: {name}: {text}"
