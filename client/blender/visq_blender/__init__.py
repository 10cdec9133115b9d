"""visq in Blender: bake obscurances onto the selected objects, update them
after a move, and show a hidden-sample map between two faces.

The Blender side is thin: it exports with Blender's own glTF exporter, reads
and writes mesh data, and runs each call of the visq Python client
(client/python) on a worker thread that a modal operator polls, so Blender's
UI never waits on the network; Esc cancels. What needs no Blender is in
core.py. Installing: README.md, "In Blender".

The bake is saved with the .blend: what Move and update needs of it (the
server's scene name and version, and per baked object its placement as last
sent, its triangles' server indices and W) is an ID property of the Blender
scene (SESSION_KEY), and the W image is packed into the file. After a
reopen, Move and update goes on against the server's resident scene; a
server that no longer holds it (restarted without its repository, the scene
unloaded, replaced or moved by someone else: a new version) answers
NOT_FOUND or FAILED_PRECONDITION, reported as "the server no longer has this
bake ...; run Bake obscurances again".
"""
import os
import shutil
import sys
import tempfile

import bpy
import numpy as np

from . import core

bl_info = {
    "name": "visq",
    "author": "visq",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D Viewport > Sidebar > visq",
    "description": "Obscurance bakes, updates after moves and visibility maps from a visq server",
    "category": "Render",
}

UV_LAYER = "visq_atlas"
COLOR_ATTRIBUTE = "visq_w"
MAP_IMAGE = "visq_visibility"

SESSION_KEY = "_visq_session"  # on bpy.types.Scene; "_": not listed among the custom properties
# Per Blender scene name: the folder of the .glb the last bake uploaded, a
# file of this process (scripts and the test read it), removed when a bake
# replaces it, when a bake fails and when the add-on is disabled.
_uploads = {}
# The last finished call's numbers, for scripts and the headless test.
last_result = {}


def _drop_upload(key):
    shutil.rmtree(_uploads.pop(key, ""), ignore_errors=True)


def load_session(scene):
    """The bake saved in the Blender scene (core.read_session's dict), or None."""
    record = scene.get(SESSION_KEY)
    return None if record is None else core.read_session(record)


def _store_session(scene, session):
    scene[SESSION_KEY] = core.session_record(session["scene"], session["version"], session["image"],
                                             session["objects"])


def _drop_session(scene):
    if scene is not None and SESSION_KEY in scene:
        del scene[SESSION_KEY]


class VisqAddonError(Exception):
    """A problem the artist can fix, reported as is."""


def _prefs(context):
    addon = context.preferences.addons.get(__name__)
    if addon is None:
        raise VisqAddonError("the visq add-on is not enabled")
    return addon.preferences


def import_visq(context):
    """The visq package, from the folder the preferences name or sys.path."""
    folder = _prefs(context).python_path
    if folder:
        folder = bpy.path.abspath(folder)
        if not os.path.isdir(folder):
            raise VisqAddonError(f"Python package folder '{folder}' does not exist (add-on preferences)")
        if folder not in sys.path:
            sys.path.insert(0, folder)
    try:
        import visq
    except ImportError as error:
        raise VisqAddonError(
            f"cannot import the visq Python package ({error}); install client/python into a venv made with "
            "--system-site-packages and set its site-packages folder in the add-on's preferences") from None
    return visq


def _connection(context):
    """The preferences as plain values, read on the main thread (a worker
    thread must not touch Blender's data), checked."""
    prefs = _prefs(context)
    address = prefs.address.strip()
    if not address or any(c.isspace() for c in address):
        raise VisqAddonError(f"server address '{prefs.address}' is not HOST[:PORT] (add-on preferences)")
    token_file = bpy.path.abspath(prefs.token_file) if prefs.token_file else None
    if token_file and not os.path.isfile(token_file):
        raise VisqAddonError(f"token file '{token_file}' does not exist")
    return {"address": address, "token": prefs.token or None, "token_file": token_file,
            "timeout": float(prefs.timeout)}


def _client(visq, connection):
    return visq.Client(connection["address"], token=connection["token"], token_file=connection["token_file"],
                       timeout=connection["timeout"])


def _check_server(client, connection):
    """One short health call first: an address that swallows packets fails
    here within the timeout instead of stalling the upload."""
    status = client.health(timeout=min(connection["timeout"], 10.0))
    if status != "SERVING":
        raise VisqAddonError(f"the server at {client.address} is {status}, not SERVING")


def _server_scene_name(context):
    name = context.scene.visq.scene_name.strip()
    if not name:
        raise VisqAddonError("server scene name is empty (visq panel)")
    return name


# ---------------------------------------------------------------------------
# Reading Blender's meshes.

def _mesh_objects(context, selected_only):
    objects = context.selected_objects if selected_only else context.scene.objects
    for o in objects:
        if o.type == "MESH" and o.mode == "EDIT":
            o.update_from_editmode()  # edit mode's changes into the mesh the exporter and the bake read
    meshes = [o for o in objects if o.type == "MESH" and o.data is not None and len(o.data.polygons)]
    if not meshes:
        where = "selected" if selected_only else "in the scene"
        raise VisqAddonError(f"no mesh object with faces {where}: select meshes to bake")
    return meshes


def _loop_triangles(obj):
    """(loops (m, 3), polygon (m,), corners in the object's frame as glTF
    axes (m, 3, 3)) of the triangles Blender's exporter writes."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    m = len(mesh.loop_triangles)
    loops = np.empty(m * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    vertices = np.empty(m * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", vertices)
    polygon = np.empty(m, dtype=np.int64)
    mesh.loop_triangles.foreach_get("polygon_index", polygon)
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", co)
    corners = co.reshape(-1, 3)[vertices].reshape(m, 3, 3)
    return loops.reshape(m, 3), polygon, core.to_gltf_points(corners)


def _export_glb(context, objects, path):
    """Blender's own glTF exporter over exactly these objects (node names
    are object names), Y up, modifiers not applied: the mesh data as is."""
    view_layer = context.view_layer
    before = [o for o in context.scene.objects if o.select_get()]
    active = view_layer.objects.active
    try:
        for o in before:
            o.select_set(False)
        for o in objects:
            o.select_set(True)
        options = dict(export_format="GLB", use_selection=True, export_yup=True, export_apply=False,
                       export_animations=False, export_cameras=False, export_lights=False, export_extras=False,
                       export_skins=False, export_morph=False, export_image_format="NONE", export_colors=False)
        # Only the options this Blender's exporter has (they change between versions).
        known = bpy.ops.export_scene.gltf.get_rna_type().properties.keys()
        result = bpy.ops.export_scene.gltf(filepath=path, **{k: v for k, v in options.items() if k in known})
    finally:
        for o in objects:
            o.select_set(False)
        for o in before:
            o.select_set(True)
        view_layer.objects.active = active
    if result != {"FINISHED"} or not os.path.isfile(path):
        raise VisqAddonError(f"Blender's glTF exporter ended {result}")


def _matrix(obj):
    return np.array(obj.matrix_world, dtype=np.float64)


def _new_image(name, width, height, pixels):
    image = bpy.data.images.get(name)
    if image is not None and tuple(image.size) != (width, height):
        bpy.data.images.remove(image)
        image = None
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=False, float_buffer=True)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(np.ascontiguousarray(pixels, dtype=np.float32).reshape(-1))
    _keep_image(image)
    return image


def _keep_image(image):
    """Saved with the .blend as written: a generated image's pixels are not
    saved unless packed (OpenEXR, float32: bit for bit), nor an image no
    material uses unless it has a fake user."""
    image.update()
    image.use_fake_user = True
    image.pack()


def _write_colors(obj, colors):
    mesh = obj.data
    attribute = mesh.color_attributes.get(COLOR_ATTRIBUTE)
    if attribute is not None and (attribute.domain != "CORNER" or attribute.data_type != "FLOAT_COLOR"):
        mesh.color_attributes.remove(attribute)
        attribute = None
    if attribute is None:
        attribute = mesh.color_attributes.new(COLOR_ATTRIBUTE, "FLOAT_COLOR", "CORNER")
    attribute.data.foreach_set("color", np.ascontiguousarray(colors, dtype=np.float32).reshape(-1))
    # The viewport's Solid mode with Color: Attribute shows the active one.
    mesh.color_attributes.active_color = attribute
    mesh.update()


def _show_colors(context):
    """Solid shading by colour attribute in the 3D views, so W shows at once
    (Blender's renderers ignore glTF's occlusion; the attribute they see)."""
    screen = context.screen if context.window is not None else None
    for area in (screen.areas if screen else ()):
        if area.type == "VIEW_3D":
            shading = area.spaces.active.shading
            if shading.type == "SOLID":
                shading.color_type = "VERTEX"


def _node_named(nodes, kind, name, location):
    """The material's node called `name`, made (of `kind`, at `location`) if absent."""
    node = nodes.get(name)
    if node is None:
        node = nodes.new(kind)
        node.name = node.label = name
        node.location = location
    return node


def _wire_materials(obj, image):
    """In each node material of the object, an Image Texture node 'visq W'
    reading the image through the 'visq_atlas' UV map, left unconnected:
    the artist links it where the look wants W (Blender's renderers have no
    glTF occlusion input). Materials are shared between objects, and all
    read the same image and UV map name."""
    for slot in obj.material_slots:
        material = slot.material
        if material is None or not material.use_nodes or material.node_tree is None:
            continue
        nodes, links = material.node_tree.nodes, material.node_tree.links
        texture = _node_named(nodes, "ShaderNodeTexImage", "visq W", (-600, -400))
        texture.image = image
        uv = _node_named(nodes, "ShaderNodeUVMap", "visq UV", (-800, -400))
        uv.uv_map = UV_LAYER
        if not texture.inputs["Vector"].links:
            links.new(uv.outputs["UV"], texture.inputs["Vector"])


def _show_image(context, image):
    screen = context.screen if context.window is not None else None
    for area in (screen.areas if screen else ()):
        if area.type == "IMAGE_EDITOR":
            area.spaces.active.image = image
            return


# ---------------------------------------------------------------------------
# The three tasks: prepare on the main thread, work on a worker thread,
# finish on the main thread. An operator's execute() runs them in a row
# (scripts and background mode); invoke() runs work() off the main thread.

class BakeTask:
    def __init__(self, context, cancellation=None):
        settings = context.scene.visq
        self.visq = import_visq(context)
        self.connection = _connection(context)
        self.scene_name = _server_scene_name(context)
        self.blender_scene = context.scene.name
        self.settings = {"d_max": settings.d_max, "resolution": settings.resolution, "method": settings.method,
                         "rays_per_patch": settings.rays_per_patch, "directions": settings.directions}
        objects = _mesh_objects(context, settings.selected_only)
        self.folder = tempfile.mkdtemp(prefix="visq-blender-")
        self.glb = os.path.join(self.folder, f"{self.scene_name}.glb")
        try:
            _export_glb(context, objects, self.glb)
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise
        self.objects = {}
        for obj in objects:
            loops, polygon, corners = _loop_triangles(obj)
            self.objects[obj.name] = {"loops": loops, "polygon": polygon, "corners": corners,
                                      "areas": core.triangle_areas(corners), "loop_count": len(obj.data.loops),
                                      "polygon_count": len(obj.data.polygons), "matrix": _matrix(obj)}
        self.replaced = False
        self.cancellation = cancellation or self.visq.Cancellation()

    def work(self, job):
        try:
            return self._work(job)
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise

    def _work(self, job):
        visq = self.visq
        with _client(visq, self.connection) as client:
            job.report_progress(0.0, "connecting")
            _check_server(client, self.connection)
            job.report_progress(0.01, "uploading")
            client.upload_gltf(self.glb, name=self.scene_name, replace=True)
            self.replaced = True  # the server's earlier bake went with the replaced scene
            info = client.get_scene(self.scene_name, include_nodes=True)
            ranges = core.node_ranges(core.glb_node_triangles(self.glb),
                                      [(n.name, n.triangle_count) for n in info.nodes])

            def progress(p):
                if p.directions_total:
                    job.report_progress(0.02 + 0.93 * p.directions_done / p.directions_total,
                                        f"baking {p.directions_done}/{p.directions_total}")

            s = self.settings
            job.report_progress(0.02, "baking")
            bake = client.compute_obscurances(
                self.scene_name, s["d_max"], resolution=s["resolution"], method=s["method"],
                rays_per_patch=s["rays_per_patch"], directions=s["directions"], want_averages=True,
                progress=progress, cancel=job.cancellation)
            job.report_progress(0.96, "reading the atlas")
            exported = client.export_obscurances(self.scene_name, atlas_uvs=True, cancel=job.cancellation)
        # Each Blender triangle's server triangle, by position.
        maps = {}
        for name, data in self.objects.items():
            if name not in ranges:
                raise VisqAddonError(f"object '{name}' is not a node of the uploaded scene")
            first, triangles = ranges[name]
            local, corner = core.match_triangles(data["corners"], triangles)
            corner = core.server_corners(corner, np.linalg.det(data["matrix"][:3, :3]) < 0)
            maps[name] = {"server": np.where(local >= 0, local + first, -1), "corner": corner,
                          "unmatched": int((local < 0).sum())}
        # Which baked node carries which when it moves: the server's hierarchy.
        parents = core.node_parents([(n.name, n.parent) for n in info.nodes], set(maps))
        for name in maps:
            maps[name]["parent"] = parents[name]
        return {"bake": bake, "export": exported, "maps": maps, "info": info}

    def failed(self, context):
        """The bake ended without finish(): a scene it replaced on the server
        took the saved bake with it."""
        shutil.rmtree(self.folder, ignore_errors=True)
        if self.replaced:
            _drop_session(bpy.data.scenes.get(self.blender_scene))

    def finish(self, context, result):
        bake, exported = result["bake"], result["export"]
        height, width = bake.w.shape[:2]
        image = _new_image(f"visq_w_{self.scene_name}", width, height, core.atlas_to_pixels(bake.w))
        torn = unmatched = 0
        for name, data in self.objects.items():
            obj = bpy.data.objects.get(name)
            if obj is None or obj.type != "MESH" or len(obj.data.loops) != data["loop_count"]:
                raise VisqAddonError(f"object '{name}' changed during the bake; bake again")
            m = result["maps"][name]
            mesh = obj.data
            # The atlas as a UV map of its own.
            layer = mesh.uv_layers.get(UV_LAYER)
            if layer is None:
                if len(mesh.uv_layers) >= 8:
                    raise VisqAddonError(f"'{name}' has 8 UV maps, Blender's most: remove one for '{UV_LAYER}'")
                layer = mesh.uv_layers.new(name=UV_LAYER, do_init=False)
            uvs, written, object_torn = core.loop_uvs(exported.atlas_uv, m["server"], m["corner"], data["loops"],
                                                      data["loop_count"])
            layer.data.foreach_set("uv", uvs.reshape(-1))
            torn += object_torn
            unmatched += m["unmatched"]
            # W per corner: each polygon's area-weighted triangle W.
            triangle_w = np.full((len(m["server"]), 3), np.nan)
            ok = m["server"] >= 0
            triangle_w[ok] = bake.triangle_w[m["server"][ok]]
            data.update(object=obj, parent=m["parent"], dynamic=False, server=m["server"], triangle_w=triangle_w)
            polygons = core.polygon_w(triangle_w, data["polygon"], data["areas"], data["polygon_count"])
            loop_polygon = core.loop_polygons(data["loops"], data["polygon"], data["loop_count"])
            _write_colors(obj, core.corner_colors(polygons, loop_polygon))
            obj["visq_image"] = image.name
            _wire_materials(obj, image)
        _show_colors(context)
        # What Move and update needs, saved with the scene; the version the
        # bake matched is the one the next move must find on the server.
        _store_session(bpy.data.scenes[self.blender_scene],
                       {"scene": self.scene_name, "version": bake.figures.scene_version, "image": image.name,
                        "objects": self.objects})
        _drop_upload(self.blender_scene)
        _uploads[self.blender_scene] = self.folder
        last_result.clear()
        last_result.update(kind="bake", bake=bake, export=exported, info=result["info"], torn=torn,
                           unmatched=unmatched, image=image.name, glb=self.glb)
        f = bake.figures
        message = (f"visq: baked {len(self.objects)} object(s), {width}x{height} atlas, "
                   f"error bound {f.accuracy.error_bound:.3f}" if f.HasField("accuracy") else
                   f"visq: baked {len(self.objects)} object(s), {width}x{height} atlas")
        if unmatched:
            message += f"; {unmatched} triangle(s) matched none of the server's"
        if torn:
            message += f"; {torn} corner(s) where the atlas cut a face apart"
        meshes = [bpy.data.objects[name].data for name in self.objects]
        shared = sorted({m.name for m in meshes if meshes.count(m) > 1})
        if shared:
            message += (f"; mesh data {', '.join(shared)} is shared by several baked objects: its UV map and "
                        "colours hold the last one's W (make the objects single user to keep each one's)")
        return message


def _placements(context, objects):
    """({node name: matrix_world} of a saved bake's objects, [the names of
    those placed otherwise than the session saved]), each object checked to
    be the mesh it was: a deleted or edited one means bake again."""
    out = {}
    for name, data in objects.items():
        obj = data["object"]
        if obj is None or obj.name not in context.scene.objects:
            raise VisqAddonError(f"baked object '{name}' is gone from the scene; bake again")
        if obj.type != "MESH" or len(obj.data.loops) != data["loop_count"] or \
                len(obj.data.polygons) != data["polygon_count"]:
            raise VisqAddonError(f"'{obj.name}' was edited, not only moved; bake again")
        out[name] = _matrix(obj)
    moved = [name for name, matrix in out.items()
             if not np.allclose(matrix, objects[name]["matrix"], rtol=0, atol=core.PLACEMENT_TOLERANCE)]
    return out, moved


def _saved_session(context):
    session = load_session(context.scene)
    if session is None:
        raise VisqAddonError("nothing baked in this scene: run Bake obscurances first")
    return session


class UpdateTask:
    def __init__(self, context, cancellation=None):
        self.visq = import_visq(context)
        self.connection = _connection(context)
        self.blender_scene = context.scene.name
        self.session = _saved_session(context)
        objects = self.session["objects"]
        target, self.moved = _placements(context, objects)
        if not self.moved:
            raise VisqAddonError("no baked object moved since the bake")
        # A child that kept its place on its moved parent goes with it.
        self.calls, self.placed = core.moves_to_send(
            target, {name: o["matrix"] for name, o in objects.items()},
            {name: o["parent"] for name, o in objects.items()}, [name for name, o in objects.items() if o["dynamic"]])
        self.version = self.session["version"]
        self.sent = []
        self.cancellation = cancellation or self.visq.Cancellation()

    def work(self, job):
        scene = self.session["scene"]
        with _client(self.visq, self.connection) as client:
            _check_server(client, self.connection)
            # Each call names the version the last one made: the first finds
            # the version the saved W matches, or fails (another upload, a
            # move from elsewhere, a restart) instead of mixing two scenes.
            for i, (name, matrix) in enumerate(self.calls):
                job.report_progress(0.5 * i / len(self.calls), f"moving {name}")
                self.version = client.set_node_transform(scene, name, core.to_gltf_matrix(matrix),
                                                         version=self.version).version
                self.sent.append(name)
            job.report_progress(0.5, "updating")
            update = client.update_obscurances(scene, version=self.version)
            info = client.get_scene(scene)
        return {"update": update, "info": info}

    def _mark_sent(self):
        for name in self.sent:
            self.session["objects"][name]["dynamic"] = True

    def failed(self, context):
        """Moves the server took before a call failed: the saved version and
        the nodes it now moves on their own follow them (the placements do
        not: Move and update again sends the moves, and the update applies
        them)."""
        scene = bpy.data.scenes.get(self.blender_scene)
        if self.sent and scene is not None:
            self._mark_sent()
            self.session["version"] = self.version
            _store_session(scene, self.session)

    def finish(self, context, result):
        update = result["update"]
        session = self.session
        image = bpy.data.images.get(session["image"])
        texels = 0
        if image is not None:
            width, height = image.size
            pixels = np.empty(width * height * 4, dtype=np.float32)
            image.pixels.foreach_get(pixels)
            pixels = pixels.reshape(height, width, 4)
            texels = core.apply_texels(pixels, update.texels, update.w)
            image.pixels.foreach_set(pixels.reshape(-1))
            _keep_image(image)
        # Only the polygons with a changed triangle get new colours.
        r = update.response
        refreshed = 0
        for name, data in session["objects"].items():
            data["matrix"] = self.placed[name]
            data["triangle_w"], hit = core.refresh_triangle_w(data["server"], data["triangle_w"], r.triangles,
                                                              r.triangle_w)
            if hit.any():
                _refresh_colors(data, hit)
                refreshed += 1
        self._mark_sent()
        session["version"] = r.scene_version
        _store_session(bpy.data.scenes[self.blender_scene], session)
        last_result.clear()
        last_result.update(kind="update", update=update, info=result["info"], texels=texels, moved=self.moved,
                           sent=list(self.sent), refreshed_objects=refreshed)
        return (f"visq: moved {len(self.moved)} object(s); {texels} texels and {len(r.triangles)} triangles changed "
                f"on {refreshed} object(s)")


def _refresh_colors(data, hit):
    """The colour attribute of a saved session's object, rewritten on the
    polygons of the triangles `hit` from its W."""
    obj = data["object"]
    loops, polygon, corners = _loop_triangles(obj)
    if len(polygon) != len(data["server"]):
        raise VisqAddonError(f"'{obj.name}' was edited, not only moved; bake again")
    polygons = core.polygon_w(data["triangle_w"], polygon, core.triangle_areas(corners), data["polygon_count"])
    loop_polygon = core.loop_polygons(loops, polygon, data["loop_count"])
    colors = core.corner_colors(polygons, loop_polygon)
    attribute = obj.data.color_attributes.get(COLOR_ATTRIBUTE)
    if attribute is not None and len(attribute.data) == data["loop_count"]:
        kept = np.empty(data["loop_count"] * 4, dtype=np.float32)
        attribute.data.foreach_get("color", kept)
        kept = kept.reshape(-1, 4)
        touched = np.isin(loop_polygon, np.unique(polygon[hit]))
        kept[touched] = colors[touched]
        colors = kept
    _write_colors(obj, colors)


def _selected_faces(context):
    """(object, polygon index) of every selected face of the selected meshes,
    the active object's last."""
    faces = []
    objects = sorted((o for o in context.selected_objects if o.type == "MESH"),
                     key=lambda o: (o == context.view_layer.objects.active, o.name))
    for obj in objects:
        if obj.mode == "EDIT":
            obj.update_from_editmode()
        for polygon in obj.data.polygons:
            if polygon.select:
                faces.append((obj, polygon.index))
    return faces


def _face_corners(obj, index):
    matrix = obj.matrix_world
    polygon = obj.data.polygons[index]
    return np.array([tuple(matrix @ obj.data.vertices[v].co) for v in polygon.vertices], dtype=np.float64)


class VisibilityTask:
    """A hidden-sample map: source the first selected face, receiver the
    second (the active object's, when the faces are on two objects)."""

    def __init__(self, context, cancellation=None):
        self.visq = import_visq(context)
        self.connection = _connection(context)
        settings = context.scene.visq
        faces = _selected_faces(context)
        if len(faces) != 2:
            raise VisqAddonError(f"select exactly two faces (source, then receiver); {len(faces)} selected")
        if settings.swap_faces:
            faces.reverse()
        self.faces = [(o.name, i) for o, i in faces]
        self.source = core.face_patch(_face_corners(*faces[0]))
        self.receiver = core.face_patch(_face_corners(*faces[1]))
        session = _saved_session(context)
        # The server answers for the placements it has.
        _, moved = _placements(context, session["objects"])
        if moved:
            raise VisqAddonError(f"{', '.join(map(repr, moved))} moved since the bake: run Move and update first")
        self.scene_name, self.version = session["scene"], session["version"]
        self.size = settings.map_size
        self.samples = settings.map_samples
        self.cancellation = cancellation or self.visq.Cancellation()

    def work(self, job):
        with _client(self.visq, self.connection) as client:
            _check_server(client, self.connection)
            job.report_progress(0.1, "hidden-sample map")
            return client.hidden_sample_map(self.scene_name, source=self.visq.Patch(*self.source),
                                            receiver=self.visq.Patch(*self.receiver), width=self.size,
                                            height=self.size, samples=self.samples, version=self.version,
                                            cancel=job.cancellation)

    def finish(self, context, result):
        fraction = result.visible_fraction
        image = _new_image(MAP_IMAGE, fraction.shape[1], fraction.shape[0], core.map_to_pixels(fraction))
        _show_image(context, image)
        last_result.clear()
        last_result.update(kind="map", map=result, faces=self.faces, source=self.source, receiver=self.receiver,
                           image=image.name)
        return (f"visq: '{image.name}': {self.faces[1][0]} face {self.faces[1][1]} sees "
                f"{float(fraction.mean()):.1%} of {self.faces[0][0]} face {self.faces[0][1]}")


# ---------------------------------------------------------------------------
# Operators: a modal shell around a task.

def _report_error(report, error):
    if type(error).__name__ == "Cancelled":
        report({"WARNING"}, core.describe_error(error))
    else:
        report({"ERROR"}, f"visq: {error}" if isinstance(error, VisqAddonError) else core.describe_error(error))
    return {"CANCELLED"}


class TaskRunner:
    """The modal shell around a task, apart from the operator: invoke()
    starts one, modal() hands it each event (core.modal_step decides), and
    execute() runs the same work on the calling thread and ends through the
    same conclude(). Background mode has no window to send a modal events:
    the background test drives step() with the timer's and Esc's names, the
    window test (under Xvfb) lets Blender deliver them.
    report: the operator's report(type, message)."""
    running = None  # one call at a time: Blender's data is written when it ends

    def __init__(self, context, task_type, report):
        if TaskRunner.running is not None:
            raise VisqAddonError("another visq call is running; wait for it or press Esc")
        self.task = task_type(context)
        self.report = report
        self.job = core.Job(self.task.work, self.task.cancellation)
        self.percent, self.status = 0, None  # what the progress bar and the status bar show

    def start(self, context):
        TaskRunner.running = self
        self.job.start()
        context.window_manager.progress_begin(0, 100)
        return self

    def step(self, context, event):
        """One event ("TIMER", "ESC" or another name): the set modal() returns."""
        step = core.modal_step(self.job, event)
        if step.action == "PASS":
            return {"PASS_THROUGH"}
        if step.action != "DONE":
            self.percent, self.status = step.percent, step.status
            context.window_manager.progress_update(step.percent)
            if context.workspace is not None:
                context.workspace.status_text_set(step.status)
            return {"RUNNING_MODAL"} if step.action == "CANCEL" else {"PASS_THROUGH"}
        self.end(context)
        return self.conclude(context)

    def end(self, context):
        context.window_manager.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        if TaskRunner.running is self:
            TaskRunner.running = None

    def run_here(self, context):
        self.job.run_here()
        return self.conclude(context)

    def conclude(self, context):
        """The ended job's result into Blender (finish), or its error as a
        report after the task's failed() has tidied up."""
        error = self.job.error
        if error is None:
            try:
                self.report({"INFO"}, self.task.finish(context, self.job.result))
                return {"FINISHED"}
            except Exception as finish_error:
                error = finish_error
        try:
            getattr(self.task, "failed", lambda context: None)(context)
        except Exception as tidy_error:  # the first error is the one to report
            print(f"visq: tidying up after '{error}' failed too: {tidy_error!r}")
        return _report_error(self.report, error)


class _TaskOperator:
    task = None

    def execute(self, context):
        try:
            runner = TaskRunner(context, type(self).task, self.report)
        except Exception as error:  # every failure is a report, never a traceback in the artist's face
            return _report_error(self.report, error)
        return runner.run_here(context)

    def invoke(self, context, event):
        if context.window is None or bpy.app.background:
            return self.execute(context)
        try:
            self._runner = TaskRunner(context, type(self).task, self.report).start(context)
        except Exception as error:
            return _report_error(self.report, error)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        # Esc counts as the key goes down; its release is another event.
        name = event.type if event.type != "ESC" or event.value == "PRESS" else "ESC_RELEASE"
        result = self._runner.step(context, name)
        if result & {"FINISHED", "CANCELLED"}:
            context.window_manager.event_timer_remove(self._timer)
        return result

    def cancel(self, context):
        """Blender ends the modal (the window closes): stop the call too."""
        self._runner.job.cancel()
        self._runner.end(context)
        context.window_manager.event_timer_remove(self._timer)


class VISQ_OT_bake(_TaskOperator, bpy.types.Operator):
    """Bake obscurances of the selected meshes (or the scene) on the visq server: W comes back as an image on a new UV map and a colour attribute"""
    bl_idname = "visq.bake"
    bl_label = "Bake obscurances"
    task = BakeTask


class VISQ_OT_move_update(_TaskOperator, bpy.types.Operator):
    """Send the baked objects' new placements to the server and refresh only the W that changed"""
    bl_idname = "visq.move_update"
    bl_label = "Move and update"
    task = UpdateTask


class VISQ_OT_show_visibility(_TaskOperator, bpy.types.Operator):
    """Hidden-sample map from the first selected face (source) to the second (receiver), as an image"""
    bl_idname = "visq.show_visibility"
    bl_label = "Show visibility"
    task = VisibilityTask


# ---------------------------------------------------------------------------
# Preferences, settings, panel.

class VisqPreferences(bpy.types.AddonPreferences):
    bl_idname = __name__
    address: bpy.props.StringProperty(name="Server address", default="127.0.0.1:50051",
                                      description="HOST[:PORT] of visq-server")
    token: bpy.props.StringProperty(name="Token", subtype="PASSWORD", default="",
                                    description="Bearer token, where the server asks for one")
    token_file: bpy.props.StringProperty(name="Token file", subtype="FILE_PATH", default="",
                                         description="A file whose first line is the token (instead of Token)")
    python_path: bpy.props.StringProperty(
        name="visq package folder", subtype="DIR_PATH", default="",
        description="Folder holding the installed visq Python package (a venv's site-packages)")
    timeout: bpy.props.FloatProperty(name="Timeout (s)", default=30.0, min=1.0, max=3600.0,
                                     description="Deadline of the short calls (health, moves, update)")

    def draw(self, context):
        layout = self.layout
        for name in ("address", "token", "token_file", "python_path", "timeout"):
            layout.prop(self, name)


class VisqSettings(bpy.types.PropertyGroup):
    scene_name: bpy.props.StringProperty(name="Server scene", default="blender",
                                         description="Name of the scene on the server")
    selected_only: bpy.props.BoolProperty(name="Selected only", default=True,
                                          description="Bake the selected meshes (else every mesh of the scene)")
    d_max: bpy.props.FloatProperty(name="Distance", default=1.0, min=1e-4, description="Obscurance range d_max")
    resolution: bpy.props.IntProperty(name="Atlas size", default=256, min=8, max=8192)
    method: bpy.props.EnumProperty(name="Method", default="raycast", items=(
        ("auto", "Auto", "The server's faster estimator at the same bound"),
        ("raycast", "Ray casting", "Embree rays per patch"),
        ("depth-peeling", "Depth peeling", "The GPU bake over directions")))
    rays_per_patch: bpy.props.IntProperty(name="Rays per patch", default=64, min=1, max=65536)
    directions: bpy.props.IntProperty(name="Directions", default=64, min=1, max=65536)
    map_size: bpy.props.IntProperty(name="Map size", default=64, min=1, max=4096)
    map_samples: bpy.props.IntProperty(name="Map samples", default=256, min=1, max=65536)
    swap_faces: bpy.props.BoolProperty(name="Swap faces", default=False,
                                       description="Use the second selected face as the source")


class VISQ_PT_panel(bpy.types.Panel):
    bl_label = "visq"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "visq"

    def draw(self, context):
        layout = self.layout
        prefs = context.preferences.addons[__name__].preferences
        box = layout.box()
        box.prop(prefs, "address")
        box.prop(prefs, "token")
        box.prop(prefs, "token_file")
        settings = context.scene.visq
        layout.prop(settings, "scene_name")
        layout.prop(settings, "selected_only")
        layout.prop(settings, "d_max")
        layout.prop(settings, "resolution")
        layout.prop(settings, "method")
        layout.prop(settings, "rays_per_patch" if settings.method == "raycast" else "directions")
        layout.operator(VISQ_OT_bake.bl_idname, icon="RENDER_STILL")
        layout.operator(VISQ_OT_move_update.bl_idname, icon="ORIENTATION_GLOBAL")
        col = layout.column(align=True)
        col.prop(settings, "map_size")
        col.prop(settings, "map_samples")
        col.prop(settings, "swap_faces")
        layout.operator(VISQ_OT_show_visibility.bl_idname, icon="HIDE_OFF")


_classes = (VisqPreferences, VisqSettings, VISQ_OT_bake, VISQ_OT_move_update, VISQ_OT_show_visibility, VISQ_PT_panel)


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.visq = bpy.props.PointerProperty(type=VisqSettings)


def unregister():
    # The saved bakes stay with their scenes; the uploaded files go.
    for key in list(_uploads):
        _drop_upload(key)
    del bpy.types.Scene.visq
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
