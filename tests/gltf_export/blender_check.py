# Imports a baked .glb (visq obscurance-export) into Blender and checks that
# the bake arrived on the mesh: every material's occlusion texture is read
# through a UV layer the meshes have, and W read there at each triangle's
# centre equals what the test expected.
#   blender -b --factory-startup --python-exit-code 1 --python blender_check.py -- INPUT BAKED.glb EXPECTED.json
# INPUT: the file that was baked, imported first for its face count.
# EXPECTED.json: {"triangles": [[cx, cy, cz, triangle_w, its own bound, W atlas at the atlas UVs' centre], ...]
# (centres in glTF's axes, in the answer's triangle order), "bound": the
# bake's error_bound, "atlas_texcoord": the TEXCOORD set of the atlas}.
# Prints one "blender_check: ..." line of figures; exits 1 (an exception,
# with --python-exit-code 1) when a check fails.
import json
import math
import sys

# Debian's Blender 3.4 runs on Debian's numpy 1.24, which removed the
# deprecated alias numpy.bool; Blender 3.4's glTF importer still uses it
# (io_import_scene_gltf2's mesh import), and fails on the first primitive
# without this. Blender 3.5's importer no longer needs it.
import warnings
import numpy
with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)  # numpy 1.24 warns on the name's look-up
    if not hasattr(numpy, "bool"):
        numpy.bool = bool

import bpy
from mathutils import Vector
from mathutils.kdtree import KDTree

argv = sys.argv[sys.argv.index("--") + 1:]
input_path, glb_path, expected_path = argv
with open(expected_path) as f:
    expected = json.load(f)


def import_gltf(path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.import_scene.gltf(filepath=path)
    assert result == {"FINISHED"}, f"the glTF import of {path} ended {result}"
    return [o for o in bpy.context.scene.objects if o.type == "MESH"]


# Blender's importer drops a triangle over the same three vertices as one it
# already made (the Cornell box's boxes: 12 triangles, 10 faces): the input
# says how many faces the export should make.
input_faces = sum(len(o.data.polygons) for o in import_gltf(input_path))
meshes = import_gltf(glb_path)

assert meshes, "the import made no mesh"


def occlusion_image_and_uv_map(material):
    """The occlusion image of a material the importer made, and the UV map
    its texture node reads (the importer puts the occlusion texture into its
    'glTF Settings' / 'glTF Material Output' group input 'Occlusion')."""
    tree = material.node_tree
    for node in tree.nodes:
        if node.type != "GROUP" or "Occlusion" not in node.inputs:
            continue
        links = node.inputs["Occlusion"].links
        if not links:
            continue
        source = links[0].from_node
        while source.type != "TEX_IMAGE":  # a Separate RGB between: occlusion is the R channel
            inputs = [i for i in source.inputs if i.links]
            assert inputs, f"{material.name}: the occlusion input comes from no image"
            source = inputs[0].links[0].from_node
        vector = source.inputs["Vector"].links
        if not vector:  # the importer leaves TEXCOORD_0 unlinked: the mesh's active render UV map
            return source.image, None
        uv_node = vector[0].from_node
        assert uv_node.type == "UVMAP", f"{material.name}: the occlusion image's vector comes from {uv_node.type}"
        return source.image, uv_node.uv_map
    raise AssertionError(f"{material.name}: no occlusion texture in the imported material")


# The occlusion texture on every material, through a UV layer each mesh has.
image = None
layer_name = None
for obj in meshes:
    for slot in obj.material_slots:
        img, uv_map = occlusion_image_and_uv_map(slot.material)
        if uv_map is None:
            render = [l.name for l in obj.data.uv_layers if l.active_render]
            assert render, f"{obj.name}: the occlusion reads the default UV map, and the mesh has none"
            uv_map = render[0]
        assert uv_map in obj.data.uv_layers, (f"{obj.name}: the occlusion reads UV map '{uv_map}', the mesh has "
                                               f"{[l.name for l in obj.data.uv_layers]}")
        assert image is None or img == image, "the materials read different occlusion images"
        assert layer_name is None or uv_map == layer_name, "the materials read different UV maps"
        image, layer_name = img, uv_map
    layers = [l.name for l in obj.data.uv_layers]
    # The importer names the layers in TEXCOORD order: the atlas is its set.
    assert layers.index(layer_name) == expected["atlas_texcoord"], (layers, layer_name, expected["atlas_texcoord"])

width, height = image.size
pixels = numpy.empty(width * height * image.channels, dtype=numpy.float32)
image.pixels.foreach_get(pixels)
pixels = pixels.reshape(height, width, image.channels)  # row 0 at the bottom, as Blender stores it


# Each triangle of the import: its centre in glTF's axes (Blender's importer
# turns +Y up into +Z up: glTF (x, y, z) is Blender (x, -z, y)) and W at the
# centre of its atlas UVs, nearest texel (Blender's importer flips v).
faces = []
for obj in meshes:
    mesh = obj.data
    matrix = obj.matrix_world
    uv = mesh.uv_layers[layer_name].data
    for poly in mesh.polygons:
        c = matrix @ poly.center
        u = sum(uv[i].uv[0] for i in poly.loop_indices) / poly.loop_total
        v = sum(uv[i].uv[1] for i in poly.loop_indices) / poly.loop_total
        x = min(width - 1, max(0, int(math.floor(u * width))))
        y = min(height - 1, max(0, int(math.floor(v * height))))
        faces.append(((c.x, c.z, -c.y), float(pixels[y, x, 0])))
triangles = expected["triangles"]
assert len(faces) == input_faces, f"the export imports as {len(faces)} faces, the input as {input_faces}"
dropped = len(triangles) - len(faces)

tree = KDTree(len(faces))
for i, (centre, _) in enumerate(faces):
    tree.insert(centre, i)
tree.balance()

# Per triangle of the answer: the imported face at its centre (coincident
# faces, as double walls, may swap: their W is then the other's, and count
# among the few allowed), W read there against the atlas (exact to 8 bits)
# and against triangle_w (within the bounds).
quantum = 1.0 / 255.0
bound = expected["bound"]
unmatched = atlas_off = judged = beyond = 0
total_difference = 0.0
worst = 0.0
for cx, cy, cz, triangle_w, own_bound, atlas_w in triangles:
    _, index, distance = tree.find((cx, cy, cz))
    scale = max(1.0, abs(cx), abs(cy), abs(cz))
    if distance > 1e-4 * scale:
        unmatched += 1
        continue
    w = faces[index][1]
    atlas_off += abs(w - atlas_w) > quantum
    if own_bound >= 1.0:  # a triangle no sample reached: its W is its texels', with no bound
        continue
    judged += 1
    difference = abs(w - triangle_w)
    total_difference += difference
    worst = max(worst, difference)
    beyond += difference > own_bound + bound + quantum
n = len(triangles)
mean = total_difference / max(judged, 1)
print(f"blender_check: {n} triangles on UV map '{layer_name}' of {len(meshes)} meshes ({width}x{height} image): "
      f"{unmatched} unmatched, {atlas_off} differ from the atlas beyond 1/255, W against triangle_w over {judged} "
      f"with a bound: mean {mean:.4f}, worst {worst:.4f}, {beyond} beyond their own bound + {bound:.4f}",
      flush=True)
assert unmatched <= dropped + n // 100, f"{unmatched} of {n} triangle centres have no imported face"
# The exact check: the texel under each centre is the atlas's (a centre on a
# texel's edge may round to its neighbour).
assert atlas_off <= n // 50, f"{atlas_off} of {n} triangles read W other than the atlas's at their centre"
# Against triangle_w, within the bounds: a texel's W and a triangle's are two
# estimates, each within its bound of the truth (texels: the bake's
# error_bound; a triangle, its own), so each triangle within their sum (and
# the PNG's 8 bits), all but a few. On average closer: an estimate's spread
# is at most 0.37 of its Hoeffding half-width (0.5 / sqrt(n) against
# sqrt(ln(2 / 0.05) / 2n)), so the mean distance of two is under half the
# bound unless W is read at the wrong place.
assert beyond <= judged // 20, f"{beyond} of {judged} triangles are beyond their bound"
assert mean < bound / 2, f"W at the triangle centres is {mean:.4f} from triangle_w on average (bound {bound:.4f})"
