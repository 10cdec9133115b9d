# The visq add-on in Blender's background mode against a real visq-server.
#   blender -b --factory-startup --python-exit-code 1 --python blender_test.py -- \
#     --address HOST:PORT --package DIR_WITH_visq --addon client/blender/visq_blender --scratch DIR \
#     --token-file FILE
# (tests/blender/run_blender_test.sh runs it). It installs the add-on from a
# zip as an artist would, builds a scene (a floor grid, two cubes, a lid
# parented to one of them, a lamp plane above), and checks, against the
# server's own answers:
#   bake: every object gets the 'visq_atlas' UV map (the server's atlas UVs at
#     each corner), the 'visq_w' colour attribute (each face's area-weighted
#     triangle_w) and the W image (the atlas at each triangle's UVs); the
#     floor under the cube is darker than the floor far away;
#   move and update, three times: a cube; a parent whose child moves with it
#     (the parent alone sent, in glTF's Y-up frame; the server carries the
#     child); the parent back after the .blend was saved and opened again
#     with the add-on imported afresh (the session lives in the file, not in
#     the module). The child turned on its moved parent is refused before
#     anything is sent (the server would drop the bake). Each time the
#     server's scene bounds equal Blender's world bounds turned Y up, W rises
#     where the object left and falls where it went, faces with no changed
#     triangle keep their colours bit for bit, changed faces are the
#     area-weighted triangle_w the server answered, changed texels are the
#     update's and no other texel changed;
#   a server that lost the scene (reloaded it from its repository: another
#     version; or not found): Move and update says to bake again, no move sent;
#   the modal shell (TaskRunner, what the modal operator's invoke() / modal()
#     run) driven with timer and Esc events: a depth-peeling bake's progress
#     bar and status never go back and it finishes; Esc on a long bake fires
#     visq.Cancellation, the modal ends CANCELLED with a warning, the server
#     ends its call, and the replaced scene's saved bake is dropped;
#   show visibility: a hidden-sample map from the lamp to a floor face under
#     the cube (hidden) and far away (seen), as an image;
#   hostile inputs: a bad address, a server that is down, nothing to bake,
#     nothing moved, one face selected: each a clear error report, fast;
#   the server's token, from the add-on's token file; a wrong one refused.
# Background mode has no window and no event loop: the operators run through
# execute() (the same task and TaskRunner.conclude() as the modal), and the
# modal shell gets its events from this script instead of Blender's window
# manager. Blender delivering the timer and the Esc key to modal() is
# blender_window_test.py's, under Xvfb.
import math
import os
import shutil
import socket
import sys
import tempfile
import time

import bpy
import numpy as np
from mathutils import Vector
from mathutils.kdtree import KDTree

argv = sys.argv[sys.argv.index("--") + 1:]
args = dict(zip(argv[0::2], argv[1::2]))
ADDRESS, PACKAGE, ADDON, SCRATCH = args["--address"], args["--package"], args["--addon"], args["--scratch"]
TOKEN_FILE = args["--token-file"]
started = time.monotonic()
figures = []


def log(message):
    print(f"blender_test [{time.monotonic() - started:5.1f} s]: {message}", flush=True)


def check(condition, message):
    if not condition:
        raise AssertionError(message)


# -- install and enable the add-on from a zip, as Preferences > Add-ons > Install does
archive = shutil.make_archive(os.path.join(SCRATCH, "visq_blender"), "zip", os.path.dirname(ADDON),
                              os.path.basename(ADDON))
check(bpy.ops.preferences.addon_install(filepath=archive) == {"FINISHED"}, "addon_install failed")
bpy.ops.preferences.addon_enable(module="visq_blender")
bpy.ops.preferences.addon_disable(module="visq_blender")  # unregister() runs clean
bpy.ops.preferences.addon_enable(module="visq_blender")
import visq_blender  # noqa: E402  (installed just now)
from visq_blender import core  # noqa: E402

check(os.path.abspath(visq_blender.__file__).startswith(os.path.abspath(SCRATCH)),
      f"the add-on was imported from {visq_blender.__file__}, not the installed copy")
prefs = bpy.context.preferences.addons["visq_blender"].preferences
prefs.address = ADDRESS
prefs.python_path = PACKAGE
prefs.timeout = 10.0
prefs.token_file = TOKEN_FILE
visq = visq_blender.import_visq(bpy.context)  # as the operators find it: PACKAGE from the preferences
with visq.Client(ADDRESS, token_file=TOKEN_FILE) as c:
    c.wait_until_serving(60)
log("add-on installed and enabled; server SERVING")

# -- the scene: Blender's Z up; the floor a 12 x 12 grid of 4 m
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.preferences.addon_enable(module="visq_blender")


def set_prefs():
    p = bpy.context.preferences.addons["visq_blender"].preferences
    p.address, p.python_path, p.timeout, p.token_file = ADDRESS, PACKAGE, 10.0, TOKEN_FILE


set_prefs()
scene = bpy.context.scene


def add(kind, name, **kw):
    getattr(bpy.ops.mesh, kind)(**kw)
    obj = bpy.context.active_object
    obj.name = obj.data.name = name
    return obj


floor = add("primitive_grid_add", "Floor", x_subdivisions=12, y_subdivisions=12, size=4.0)
cube = add("primitive_cube_add", "Cube", size=1.0, location=(0.0, 0.0, 0.55), rotation=(0, 0, math.radians(30)))
crate = add("primitive_cube_add", "Crate", size=0.6, location=(1.3, -1.3, 0.32))
lamp = add("primitive_plane_add", "Lamp", size=0.6, location=(0.0, 0.0, 3.0), rotation=(math.pi, 0, 0))
# Mirrored (a negative scale): the server flips its triangles' winding.
mirror = add("primitive_cube_add", "Mirror", size=0.5, location=(-1.4, -1.4, 0.25))
mirror.scale = (-1.0, 0.6, 1.0)
# A child of the crate, on its top, in the crate's frame: it moves with it.
lid = add("primitive_cube_add", "Lid", size=0.3, location=(0.0, 0.0, 0.0))
lid.parent = crate
lid.location, lid.rotation_euler = (0.05, 0.0, 0.45), (0.0, 0.0, math.radians(20))
objects = [floor, cube, crate, lamp, mirror, lid]
floor.data.materials.append(bpy.data.materials.new("FloorMaterial"))
floor.data.materials[0].use_nodes = True
bpy.context.view_layer.update()
settings = scene.visq
settings.scene_name = "blender_test"
NAMES = [o.name for o in objects]


def bind():
    """The scene's objects and the add-on's settings, looked up again (a
    reopened .blend makes the old references invalid)."""
    global scene, settings, prefs, objects, floor, cube, crate, lamp, mirror, lid
    scene = bpy.context.scene
    settings = scene.visq
    prefs = bpy.context.preferences.addons["visq_blender"].preferences
    objects = [bpy.data.objects[name] for name in NAMES]
    floor, cube, crate, lamp, mirror, lid = objects

settings.resolution = 64
settings.method = "raycast"
settings.rays_per_patch = 64
settings.d_max = 1.0
for o in objects:
    o.select_set(True)


def loop_triangles(obj):
    mesh = obj.data
    mesh.calc_loop_triangles()
    m = len(mesh.loop_triangles)
    loops = np.empty(3 * m, np.int64)
    verts = np.empty(3 * m, np.int64)
    poly = np.empty(m, np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    mesh.loop_triangles.foreach_get("vertices", verts)
    mesh.loop_triangles.foreach_get("polygon_index", poly)
    co = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", co)
    local = co.reshape(-1, 3)[verts].reshape(m, 3, 3)
    return loops.reshape(m, 3), poly, local


def colors(obj):
    attribute = obj.data.color_attributes["visq_w"]
    check(attribute.domain == "CORNER" and attribute.data_type == "FLOAT_COLOR",
          f"{obj.name}: visq_w is {attribute.domain} {attribute.data_type}")
    values = np.empty(4 * len(obj.data.loops), np.float32)
    attribute.data.foreach_get("color", values)
    return values.reshape(-1, 4)


def polygon_colors(obj):
    """Per polygon: its corners' colour (all equal)."""
    c = colors(obj)
    starts = np.empty(len(obj.data.polygons), np.int64)
    obj.data.polygons.foreach_get("loop_start", starts)
    return c[starts, :3]


def polygon_centres(obj):
    m = obj.matrix_world
    return np.array([tuple(m @ p.center) for p in obj.data.polygons])


def image_pixels(name):
    image = bpy.data.images[name]
    w, h = image.size
    p = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(p)
    return p.reshape(h, w, 4)


def server_triangles(info, glb):
    """{node name: (first, KDTree over its triangles' centres in the node's
    glTF frame, centres)}: the test's own match, independent of the add-on's."""
    nodes = core.glb_node_triangles(glb)
    out, first = {}, 0
    for (name, tris), node in zip(nodes, info.nodes):
        check(node.name == name and node.triangle_count == len(tris),
              f"node {node.name}: {node.triangle_count} triangles on the server, {len(tris)} in the file")
        centres = tris.mean(axis=1)
        tree = KDTree(len(centres))
        for i, c in enumerate(centres):
            tree.insert(c, i)
        tree.balance()
        out[name] = (first, tree, tris)
        first += len(tris)
    return out


def expect_error(operator, words, limit_s=15.0, **kw):
    t = time.monotonic()
    try:
        operator(**kw)
    except RuntimeError as error:
        elapsed = time.monotonic() - t
        text = str(error)
        check(all(w in text for w in words), f"the report '{text}' lacks {words}")
        check(elapsed < limit_s, f"'{text}' took {elapsed:.1f} s")
        log(f"refused in {elapsed:.2f} s: {text.strip()}")
        return text
    raise AssertionError(f"{operator} with {kw} did not fail (expected {words})")


# -- bake -------------------------------------------------------------------
t = time.monotonic()
check(bpy.ops.visq.bake() == {"FINISHED"}, "bake did not finish")
bake_s = time.monotonic() - t
result = dict(visq_blender.last_result)
bake, exported, info = result["bake"], result["export"], result["info"]
IMAGE = result["image"]
height, width = bake.w.shape[:2]
bound = bake.figures.accuracy.error_bound
log(f"baked {bake.triangle_w.shape[0]} triangles, {width}x{height} atlas in {bake_s:.2f} s "
    f"(bound {bound:.3f}, {bake.progress_messages} progress messages, {result['torn']} torn corners, "
    f"{result['unmatched']} unmatched)")
check(result["unmatched"] == 0, f"{result['unmatched']} Blender triangles matched no server triangle")
check((width, height) == (64, 64), f"atlas {width}x{height}")
# The floor's material reads the image through the atlas UV map.
tree = floor.data.materials[0].node_tree
texture = tree.nodes.get("visq W")
check(texture is not None and texture.image is bpy.data.images[result["image"]], "no 'visq W' node on the image")
vector = texture.inputs["Vector"].links
check(vector and vector[0].from_node.type == "UVMAP" and vector[0].from_node.uv_map == "visq_atlas",
      "'visq W' does not read the visq_atlas UV map")
mapping = server_triangles(info, result["glb"])
pixels = image_pixels(result["image"])
check(pixels.shape[:2] == (height, width), f"image {pixels.shape}")

matched = {}
shear_worst = {}
uv_worst = color_worst = texel_worst = 0.0
texel_vs_triangle = []
for obj in objects:
    mesh = obj.data
    check("visq_atlas" in mesh.uv_layers, f"{obj.name}: no visq_atlas UV map")
    check(bpy.data.images.get(obj.get("visq_image", "")) is not None, f"{obj.name}: no image named")
    loops, poly, local = loop_triangles(obj)
    gltf_local = np.stack([local[..., 0], local[..., 2], -local[..., 1]], axis=-1)  # Blender -> glTF axes
    first, tree, tris = mapping[obj.name]
    mw = np.array(obj.matrix_world)
    world = local @ mw[:3, :3].T + mw[:3, 3]
    mirrored = np.linalg.det(mw[:3, :3]) < 0
    check(mirrored == (obj is mirror), f"{obj.name}: mirrored {mirrored}")
    index = np.empty(len(loops), np.int64)
    for j, tri in enumerate(gltf_local):
        _, i, distance = tree.find(tri.mean(axis=0))
        check(distance < 1e-5, f"{obj.name} triangle {j}: no server triangle at its centre ({distance})")
        index[j] = first + i
    matched[obj.name] = (index, poly, local)
    # The UV map: the server's atlas UVs at each corner (v flipped).
    uv = np.empty(2 * len(mesh.loops), np.float32)
    mesh.uv_layers["visq_atlas"].data.foreach_get("uv", uv)
    uv = uv.reshape(-1, 2)
    for j, tri in enumerate(gltf_local):
        server_tri = tris[index[j] - first]
        for k in range(3):
            corner = int(np.linalg.norm(server_tri - tri[k], axis=1).argmin())
            if mirrored:  # the server flips a mirrored node's winding (docs/scenes.md): corners 1, 2 swap
                corner = (0, 2, 1)[corner]
            a = exported.atlas_uv[index[j], corner]
            uv_worst = max(uv_worst, float(np.abs(uv[loops[j, k]] - (a[0], 1 - a[1])).max()))
        # The atlas maps a triangle without shear: each UV edge is its 3D
        # edge scaled alike (corners put back in the wrong order, as a
        # mirrored node's flipped winding would, break it on scalene ones).
        p3 = world[j]  # the atlas is laid out in world space (the mirror's scale is not uniform)
        p2 = np.array([uv[loops[j, k]] for k in range(3)], np.float64)
        ratios = [np.linalg.norm(p2[(k + 1) % 3] - p2[k]) / max(np.linalg.norm(p3[(k + 1) % 3] - p3[k]), 1e-12)
                  for k in range(3)]
        shear_worst[obj.name] = max(shear_worst.get(obj.name, 0.0), (max(ratios) - min(ratios)) / np.mean(ratios))
        # The image at the triangle's UV centre is the atlas texel there.
        cu, cv = uv[loops[j]].mean(axis=0)
        x, y = min(width - 1, int(cu * width)), min(height - 1, int((1 - cv) * height))
        image_w = pixels[height - 1 - y, x, :3]
        texel_worst = max(texel_worst, float(np.abs(image_w - bake.w[y, x]).max()))
        texel_vs_triangle.append(abs(float(image_w[0]) - float(bake.triangle_w[index[j], 0])))
    # The colour attribute: each face's area-weighted triangle_w.
    areas = 0.5 * np.linalg.norm(np.cross(local[:, 1] - local[:, 0], local[:, 2] - local[:, 0]), axis=1)
    expected = np.zeros((len(mesh.polygons), 3))
    np.add.at(expected, poly, bake.triangle_w[index] * areas[:, None])
    total = np.zeros(len(mesh.polygons))
    np.add.at(total, poly, areas)
    expected /= total[:, None]
    color_worst = max(color_worst, float(np.abs(polygon_colors(obj) - expected).max()))
log(f"atlas shear per object: { {k: round(v, 4) for k, v in shear_worst.items()} }")
log(f"UVs vs the atlas: worst {uv_worst:.2e}; colours vs triangle_w: worst {color_worst:.2e}; "
    f"image vs atlas texels: worst {texel_worst:.2e}; image vs triangle_w: mean {np.mean(texel_vs_triangle):.3f}")
torn_allowed = result["torn"]
check(max(shear_worst.values()) < 1e-3, f"atlas UVs on the wrong corners (shear {shear_worst})")
check(uv_worst < 1e-6 or torn_allowed, f"visq_atlas differs from the server's atlas UVs by {uv_worst}")
check(color_worst < 1e-5, f"visq_w differs from the area-weighted triangle_w by {color_worst}")
check(texel_worst < 1e-6, f"the image differs from the atlas by {texel_worst}")
check(np.mean(texel_vs_triangle) < max(bound, 0.05) + 0.05,
      f"the image at triangle UV centres is {np.mean(texel_vs_triangle):.3f} from triangle_w on average")

# The floor under the cube is darker than the floor far from both cubes.
centres = polygon_centres(floor)
floor_w = polygon_colors(floor)[:, 0]
under = (np.abs(centres[:, 0]) < 0.3) & (np.abs(centres[:, 1]) < 0.3)
far = np.hypot(centres[:, 0], centres[:, 1]) > 1.2
far &= np.hypot(centres[:, 0] - 1.3, centres[:, 1] + 1.3) > 1.0
check(under.any() and far.any(), "the floor grid has no face under the cube or far away")
log(f"floor W: under the cube {floor_w[under].mean():.3f} ({under.sum()} faces), far {floor_w[far].mean():.3f} "
    f"({far.sum()} faces)")
check(floor_w[under].mean() < floor_w[far].mean() - 0.3, "the floor under the cube is not darker than far away")
figures.append(f"bake {bake_s:.2f} s")

# -- move and update ---------------------------------------------------------
server_w = bake.triangle_w.copy()  # the server's triangle_w, as the updates answer it (in place)


def move_and_update(move, expect_moved, expect_sent):
    """move() places objects; Move and update; everything checked against
    the server's answer: expect_moved, the objects Blender moved;
    expect_sent, the nodes sent (a child that kept its place on its parent
    is not). Returns each object's polygon colours before and after."""
    before = {o.name: polygon_colors(o).copy() for o in objects}
    pixels_before = image_pixels(IMAGE).copy()
    move()
    bpy.context.view_layer.update()
    t = time.monotonic()
    check(bpy.ops.visq.move_update() == {"FINISHED"}, "move_update did not finish")
    update_s = time.monotonic() - t
    result = dict(visq_blender.last_result)
    update, info = result["update"], result["info"]
    r = update.response
    log(f"update of {result['moved']} in {update_s:.2f} s: sent {result['sent']} ({r.moves_applied} moves applied), "
        f"{len(update.texels)} texels, {len(r.triangles)} triangles changed, {result['refreshed_objects']} "
        "object(s) refreshed")
    check(result["moved"] == expect_moved and result["sent"] == expect_sent and r.moves_applied == len(expect_sent),
          f"moved {result['moved']}, sent {result['sent']} ({r.moves_applied} applied), expected {expect_moved}, "
          f"{expect_sent}")
    check(len(update.texels) > 0 and len(r.triangles) > 0, "the update changed nothing")
    # The server's bounds (glTF axes) are Blender's world bounds turned Y up.
    corners = np.array([tuple(o.matrix_world @ Vector(c)) for o in objects for c in o.bound_box])
    low, high = corners.min(axis=0), corners.max(axis=0)
    expect_low, expect_high = (low[0], low[2], -high[1]), (high[0], high[2], -low[1])
    server_low = (info.bounds_min.x, info.bounds_min.y, info.bounds_min.z)
    server_high = (info.bounds_max.x, info.bounds_max.y, info.bounds_max.z)
    off = float(np.abs(np.subtract(server_low, expect_low)).max() + np.abs(np.subtract(server_high, expect_high)).max())
    log(f"server bounds {np.round(server_low, 4)} .. {np.round(server_high, 4)}, Blender's Y up: off by {off:.1e}")
    check(off < 1e-4, "the moved objects are not where Blender has them (Y-up conversion)")
    # Faces with no changed triangle keep their colours bit for bit; changed
    # ones are the area-weighted W of the server's triangles now.
    changed = np.array(r.triangles, np.int64)
    server_w[changed] = np.array(r.triangle_w, np.float32).reshape(-1, 3)
    after = {o.name: polygon_colors(o) for o in objects}
    unchanged_faces = changed_faces = 0
    for obj in objects:
        index, poly, local = matched[obj.name]
        hit = np.isin(index, changed)
        touched = np.zeros(len(obj.data.polygons), bool)
        touched[poly[hit]] = True
        check(np.array_equal(after[obj.name][~touched], before[obj.name][~touched]),
              f"{obj.name}: a face with no changed triangle changed colour")
        areas = 0.5 * np.linalg.norm(np.cross(local[:, 1] - local[:, 0], local[:, 2] - local[:, 0]), axis=1)
        expected = np.zeros((len(obj.data.polygons), 3))
        np.add.at(expected, poly, server_w[index] * areas[:, None])
        total = np.zeros(len(obj.data.polygons))
        np.add.at(total, poly, areas)
        expected /= total[:, None]
        check(np.abs(after[obj.name] - expected).max() < 1e-5,
              f"{obj.name}: colours differ from the server's updated triangle_w")
        unchanged_faces += int((~touched).sum())
        changed_faces += int(touched.sum())
    # The image: the texels the update named hold its W; no other changed.
    expected = pixels_before.copy()
    texels = np.asarray(update.texels, np.int64)
    expected[height - 1 - texels // width, texels % width, :3] = update.w.astype(np.float32)
    check(np.array_equal(image_pixels(IMAGE), expected), "the image differs from the update's texels")
    log(f"{changed_faces} faces refreshed, {unchanged_faces} kept bit for bit")
    figures.append(f"update {update_s:.2f} s")
    return before, after


def floor_under(obj):
    """The floor faces whose centre lies under obj's box as Blender has it now."""
    local = (np.array(obj.matrix_world.inverted()) @ np.c_[centres, np.ones(len(centres))].T).T[:, :3]
    half = np.abs(np.array(obj.bound_box)).max(axis=0)[:2]
    return (np.abs(local[:, :2]) < half * 0.9).all(axis=1)


def check_w_moves(name, before, after, left, went):
    """W rose on the floor where an object left and fell where it went."""
    b, a = before["Floor"][:, 0], after["Floor"][:, 0]
    check(left.any() and went.any(), f"no floor face under {name} before or after")
    log(f"floor W where {name} was {b[left].mean():.3f} -> {a[left].mean():.3f}; "
        f"where it went {b[went].mean():.3f} -> {a[went].mean():.3f}")
    check(a[left].mean() > b[left].mean() + 0.3, f"W did not rise where {name} left")
    check(a[went].mean() < b[went].mean() - 0.3, f"W did not fall where {name} went")


def top_face_w(obj, colors):
    """W of the polygon of obj facing up most."""
    normals = [tuple(obj.matrix_world.to_3x3() @ p.normal) for p in obj.data.polygons]
    return float(colors[obj.name][int(np.argmax([n[2] for n in normals])), 0])


expect_error(bpy.ops.visq.move_update, ["no baked object moved"])


def move_cube():
    cube.location = (-1.0, 0.9, 0.55)
    cube.rotation_euler = (0.0, 0.0, math.radians(45))


left = floor_under(cube)
before, after = move_and_update(move_cube, ["Cube"], ["Cube"])
check_w_moves("the cube", before, after, left, floor_under(cube))

# The parent moves and its child with it: only the crate is sent (visq moves
# a node's subtree with it, and refuses a node inside another moved one).
lid_before = lid.matrix_world.copy()


def move_crate():
    crate.location = (1.2, 1.3, 0.32)
    crate.rotation_euler = (0.0, 0.0, math.radians(60))


left = floor_under(crate)
before, after = move_and_update(move_crate, ["Crate", "Lid"], ["Crate"])
check((lid.matrix_world.translation - lid_before.translation).length > 2.0, "the lid did not follow the crate")
check_w_moves("the crate", before, after, left, floor_under(crate))
# The lid went with the crate on the server too: the crate's top face, under
# the lid, stays as dark as it was (left behind, the lid would uncover it).
top = (top_face_w(crate, before), top_face_w(crate, after))
lid_w = (float(before["Lid"][:, 0].mean()), float(after["Lid"][:, 0].mean()))
log(f"crate top face W {top[0]:.3f} -> {top[1]:.3f}; lid W {lid_w[0]:.3f} -> {lid_w[1]:.3f}")
check(abs(top[1] - top[0]) < 0.1 and abs(lid_w[1] - lid_w[0]) < 0.1, "the crate and its lid changed W moving together")

# -- the bake is saved with the .blend: save, forget the add-on's module
# (its globals go with it), open the file again, move the crate back ---------
blend = os.path.join(SCRATCH, "baked.blend")
saved_colors = {o.name: colors(o).copy() for o in objects}
saved_pixels = image_pixels(IMAGE).copy()
saved_session = visq_blender.load_session(scene)
check(bpy.ops.wm.save_as_mainfile(filepath=blend) == {"FINISHED"}, "save_as_mainfile failed")
old_module = visq_blender
bpy.ops.preferences.addon_disable(module="visq_blender")
for module in [m for m in sys.modules if m.split(".")[0] == "visq_blender"]:
    del sys.modules[module]
check(bpy.ops.wm.open_mainfile(filepath=blend) == {"FINISHED"}, "open_mainfile failed")
bpy.ops.preferences.addon_enable(module="visq_blender")
import visq_blender  # noqa: E402  (imported afresh)

check(visq_blender is not old_module and not visq_blender.last_result, "the add-on's module was not imported afresh")
set_prefs()
bind()
session = visq_blender.load_session(scene)
check(session["scene"] == "blender_test" and session["version"] == saved_session["version"],
      f"the reopened session {session['scene']} v{session['version']}, saved v{saved_session['version']}")
for name, data in session["objects"].items():
    check(data["object"] == bpy.data.objects[name], f"the saved session's '{name}' is not the object")
    check(np.array_equal(data["triangle_w"], saved_session["objects"][name]["triangle_w"], equal_nan=True),
          f"{name}: saved W differs")
check(all(np.array_equal(colors(o), saved_colors[o.name]) for o in objects), "colours changed in the file")
check(np.array_equal(image_pixels(IMAGE), saved_pixels), "the W image was not saved as it was (packed)")
log(f"reopened {os.path.getsize(blend) / 1e6:.1f} MB .blend: session v{session['version']}, colours and the "
    "W image as saved")


# The lid turned on the crate, which visq now moves as one object with the
# lid: refused before anything is sent, and the server's bake is intact.
lid.rotation_euler = (0.0, 0.0, math.radians(65))
bpy.context.view_layer.update()
expect_error(bpy.ops.visq.move_update, ["'Lid' is part of 'Crate'", "bake again"])
lid.rotation_euler = (0.0, 0.0, math.radians(20))


def move_crate_back():
    crate.location = (1.3, -1.3, 0.32)
    crate.rotation_euler = (0.0, 0.0, 0.0)


left = floor_under(crate)
before, after = move_and_update(move_crate_back, ["Crate", "Lid"], ["Crate"])
check_w_moves("the crate", before, after, left, floor_under(crate))

# The server lost the bake: Move and update says so, and sends no move. The
# scene unloaded (or the server restarted) comes back from the repository as
# it was uploaded, a version the saved session does not name; deleted from
# the repository too (a server restarted without it), it is not found.
cube.location.x += 0.2
bpy.context.view_layer.update()
with visq.Client(ADDRESS, token_file=TOKEN_FILE) as c:
    c.unload_scene("blender_test")
    expect_error(bpy.ops.visq.move_update, ["no longer has this bake", "FAILED_PRECONDITION", "version",
                                            "Bake obscurances again"])
    check(c.get_scene("blender_test", load_if_stored=True).version == 1, "a refused move was applied")
    c.unload_scene("blender_test", delete_from_repository=True)
    expect_error(bpy.ops.visq.move_update, ["no longer has this bake", "NOT_FOUND", "Bake obscurances again"])

# -- the modal shell, driven as Blender's window manager drives it: "TIMER"
# every tick, the key's name on Esc. A depth-peeling bake (the GPU's sends
# progress per direction; ray casting sends none) runs to the end.
reports = []


def report(kind, message):
    reports.append((set(kind), message))


def run_modal(runner, on_tick=None, limit_s=60.0):
    """Timer events until the modal ends: (its result, [(percent, status)] as shown)."""
    shown = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        result = runner.step(bpy.context, "TIMER")
        if result != {"PASS_THROUGH"}:
            return result, shown
        if not shown or shown[-1] != (runner.percent, runner.status):
            shown.append((runner.percent, runner.status))
        if on_tick is not None:
            on_tick(shown)
        time.sleep(0.005)  # Blender's timer ticks every 0.1 s; faster here, to see a fast bake's states
    raise AssertionError(f"the modal did not end in {limit_s} s; it showed {shown[-3:]}")


settings.method, settings.directions = "depth-peeling", 16
runner = visq_blender.TaskRunner(bpy.context, visq_blender.BakeTask, report).start(bpy.context)
check(visq_blender.TaskRunner.running is runner, "the running modal is not the one call")
expect_error(bpy.ops.visq.move_update, ["another visq call is running"])
check(runner.step(bpy.context, "MOUSEMOVE") == {"PASS_THROUGH"}, "the modal took an event not its own")
result, shown = run_modal(runner)
percents = [p for p, _ in shown]
states = [f"{p}% {s[len('visq: '):s.index(' (')]}" for p, s in shown]
log(f"modal depth-peeling bake: {result}, {runner.job.result['bake'].progress_messages} progress messages, "
    f"{len(shown)} states shown: {states}; {reports[-1]}")
check(result == {"FINISHED"} and reports[-1][0] == {"INFO"} and reports[-1][1].startswith("visq: baked"),
      f"the modal bake ended {result}: {reports[-1]}")
check(percents == sorted(percents) and len(set(percents)) >= 3, f"the progress bar went back or stood still: {shown}")
check(any(s.startswith("visq: baking ") and "/16 " in s and s.endswith("(Esc cancels)") for _, s in shown),
      f"no 'baking n/16' status shown: {shown}")
check(visq_blender.TaskRunner.running is None, "the ended modal still holds the one call")
check(visq_blender.load_session(scene)["scene"] == "blender_test", "the modal bake saved no session")
settings.method = "raycast"

# -- Esc on a long bake: the Cancellation fires, the modal ends CANCELLED, the
# server ends its call.
settings.resolution, settings.rays_per_patch = 512, 4096


def bake_calls():
    with visq.Client(ADDRESS, token_file=TOKEN_FILE) as c:
        methods = {m.method.rsplit("/", 1)[-1]: m for m in c.stats().methods}
    m = methods.get("ComputeObscurances")
    return (m.calls, m.errors) if m else (0, 0)


runner = visq_blender.TaskRunner(bpy.context, visq_blender.BakeTask, report).start(bpy.context)
deadline = time.monotonic() + 20
while not (runner.status or "").startswith("visq: baking") and time.monotonic() < deadline:
    check(runner.step(bpy.context, "TIMER") == {"PASS_THROUGH"}, f"the long bake ended: {reports[-1:]}")
    time.sleep(0.02)
time.sleep(0.5)
check(not runner.job.done, f"the long bake ended before Esc ({runner.job.error!r})")
calls_before = bake_calls()
t = time.monotonic()
check(runner.step(bpy.context, "ESC") == {"RUNNING_MODAL"}, "Esc was not the modal's")
check(runner.task.cancellation.cancelled and runner.status == "visq: cancelling (Esc cancels)",
      f"Esc did not cancel: {runner.status}")
result, shown = run_modal(runner, limit_s=20.0)
cancel_s = time.monotonic() - t
check(result == {"CANCELLED"} and reports[-1] == ({"WARNING"}, "visq: cancelled"),
      f"the cancelled modal ended {result}: {reports[-1]}")
check(type(runner.job.error).__name__ == "Cancelled", f"the cancelled bake ended with {runner.job.error!r}")
log(f"Esc at '{runner.job.message}' ({runner.job.fraction:.0%}); the modal ended {cancel_s:.2f} s later")
check(cancel_s < 5.0, f"the bake took {cancel_s:.2f} s to stop")
# The server ended the call too (its stats count a call when it ends): the
# whole bake (512^2 texels x 4096 rays, ~10^9 rays) is far longer; 30 s leaves
# room for a loaded machine.
while bake_calls()[1] <= calls_before[1] and time.monotonic() - t < 30:
    time.sleep(0.05)
server_stop_s = time.monotonic() - t
log(f"ComputeObscurances calls/errors {calls_before} -> {bake_calls()}: the server ended it {server_stop_s:.2f} s "
    "after Esc")
check(bake_calls()[1] > calls_before[1], "the server did not end the cancelled bake within 30 s")
check(visq_blender.TaskRunner.running is None, "the cancelled modal still holds the one call")
figures.append(f"cancel {cancel_s:.2f} s")
settings.resolution, settings.rays_per_patch = 64, 64
# The cancelled bake replaced the server's scene: its saved bake went with it.
cube.location.x -= 0.2
bpy.context.view_layer.update()
expect_error(bpy.ops.visq.move_update, ["nothing baked", "run Bake obscurances first"])
check(bpy.ops.visq.bake() == {"FINISHED"}, "the bake after the cancel did not finish")

# -- show visibility: the lamp's face to floor faces -------------------------
def select_faces(pairs, active):
    for o in objects:
        o.select_set(False)
        for p in o.data.polygons:
            p.select = False
    for o, i in pairs:
        o.select_set(True)
        o.data.polygons[i].select = True
    bpy.context.view_layer.objects.active = active


settings.map_size, settings.map_samples = 16, 64
crate.location.z += 0.1
bpy.context.view_layer.update()
select_faces([(lamp, 0), (floor, 0)], floor)
expect_error(bpy.ops.visq.show_visibility, ["'Crate'", "'Lid'", "moved since the bake", "Move and update"])
crate.location.z -= 0.1
bpy.context.view_layer.update()
hidden_face = int(np.argmin(np.hypot(centres[:, 0] + 1.0, centres[:, 1] - 0.9)))  # under the moved cube
seen_face = int(np.argmax(np.where(far, -np.hypot(centres[:, 0], centres[:, 1]), -np.inf)))  # the nearest far face
fractions = []
for face in (hidden_face, seen_face):
    select_faces([(lamp, 0), (floor, face)], floor)
    t = time.monotonic()
    check(bpy.ops.visq.show_visibility() == {"FINISHED"}, "show_visibility did not finish")
    result = dict(visq_blender.last_result)
    check(result["faces"] == [("Lamp", 0), ("Floor", face)], f"faces {result['faces']}")
    image = image_pixels(result["image"])
    fraction = result["map"].visible_fraction
    check(image.shape[:2] == fraction.shape and np.array_equal(image[..., 0], fraction), "the map image is not the map")
    fractions.append(float(fraction.mean()))
    log(f"map Lamp -> Floor face {face} at {np.round(centres[face], 2)}: {fractions[-1]:.3f} visible "
        f"({time.monotonic() - t:.2f} s)")
check(fractions[0] < 0.35, f"the floor under the cube sees {fractions[0]:.2f} of the lamp")
check(fractions[1] > 0.95, f"the open floor sees {fractions[1]:.2f} of the lamp")
select_faces([(floor, hidden_face)], floor)
expect_error(bpy.ops.visq.show_visibility, ["select exactly two faces", "1 selected"])

# -- hostile inputs -----------------------------------------------------------
for o in objects:
    o.select_set(True)
prefs.address = "no such host"
expect_error(bpy.ops.visq.bake, ["server address", "is not HOST[:PORT]"])
prefs.address = "localhost:99999"
expect_error(bpy.ops.visq.bake, ["port '99999'"])
probe = socket.socket()
probe.bind(("127.0.0.1", 0))
closed_port = probe.getsockname()[1]
probe.close()
prefs.address = f"127.0.0.1:{closed_port}"
expect_error(bpy.ops.visq.bake, ["cannot be reached"])
# A server that accepts connections and never answers: the health call's
# deadline (the preferences' timeout) ends it.
silent = socket.socket()
silent.bind(("127.0.0.1", 0))
silent.listen(8)
prefs.address, prefs.timeout = f"127.0.0.1:{silent.getsockname()[1]}", 2.0
expect_error(bpy.ops.visq.bake, ["did not answer in time"], limit_s=8.0)
silent.close()
prefs.address, prefs.timeout = ADDRESS, 10.0
prefs.python_path = os.path.join(SCRATCH, "no-such-folder")
expect_error(bpy.ops.visq.bake, ["Python package folder", "does not exist"])
prefs.python_path = PACKAGE
prefs.token_file = os.path.join(SCRATCH, "no-such-token")
expect_error(bpy.ops.visq.bake, ["token file"])
prefs.token_file, prefs.token = "", "not-the-token"
expect_error(bpy.ops.visq.bake, ["refused the token"])
prefs.token_file, prefs.token = TOKEN_FILE, ""
for o in objects:
    o.select_set(False)
expect_error(bpy.ops.visq.bake, ["no mesh object"])
bpy.ops.object.empty_add()
bpy.context.active_object.select_set(True)
expect_error(bpy.ops.visq.bake, ["no mesh object"])
# The add-on keeps one uploaded .glb per Blender scene (the last bake's), no
# more; disabling it removes that too.
leftovers = [n for n in os.listdir(tempfile.gettempdir()) if n.startswith("visq-blender-")]
check(len(leftovers) <= 1, f"the add-on left {leftovers} in {tempfile.gettempdir()}")
bpy.ops.preferences.addon_disable(module="visq_blender")
leftovers = [n for n in os.listdir(tempfile.gettempdir()) if n.startswith("visq-blender-")]
check(not leftovers, f"disabled, the add-on left {leftovers}")
log("PASSED: " + ", ".join(figures))
