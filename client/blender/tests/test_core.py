"""client/blender/visq_blender/core.py without Blender (plain python3 with
numpy): frames, the .glb reader, triangle matching, W per corner, texels,
patches and the worker job."""
import importlib.util
import json
import os
import shutil
import struct
import tempfile
import threading
import unittest

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
_spec = importlib.util.spec_from_file_location("visq_blender_core",
                                               os.path.join(HERE, "..", "visq_blender", "core.py"))
core = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(core)
try:
    import visq
except ImportError:
    visq = None


def write_glb(path, doc, binary):
    binary += b"\0" * (-len(binary) % 4)
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    with open(path, "wb") as f:
        f.write(struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text) + 8 + len(binary)))
        f.write(struct.pack("<I4s", len(text), b"JSON") + text)
        f.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)


class Frames(unittest.TestCase):
    def test_points_turn_z_up_into_y_up(self):
        np.testing.assert_array_equal(core.to_gltf_points([1, 2, 3]), [1, 3, -2])

    def test_a_matrix_moves_the_exported_points_as_blender_moves_the_object(self):
        # A Blender placement: rotate 30 degrees about Z, then translate.
        a = np.radians(30)
        m = np.eye(4)
        m[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        m[:3, 3] = (1.0, 2.0, 3.0)
        local = np.array([0.3, -0.2, 0.5])
        blender_world = (m @ np.append(local, 1))[:3]
        # The exporter writes the point in glTF axes; the node's world matrix
        # must take it to the world point in glTF axes.
        gltf_world = core.to_gltf_matrix(m) @ np.append(core.to_gltf_points(local), 1)
        np.testing.assert_allclose(gltf_world[:3], core.to_gltf_points(blender_world), atol=1e-12)

    def test_a_bad_matrix_is_refused(self):
        with self.assertRaisesRegex(ValueError, "matrix_world"):
            core.to_gltf_matrix(np.eye(3))
        bad = np.eye(4)
        bad[0, 0] = np.nan
        with self.assertRaisesRegex(ValueError, "finite"):
            core.to_gltf_matrix(bad)


class Glb(unittest.TestCase):
    def setUp(self):
        self.folder = tempfile.mkdtemp(prefix="visq-blender-core-")

    def tearDown(self):
        shutil.rmtree(self.folder, ignore_errors=True)

    def test_nodes_in_the_servers_order_with_their_triangles(self):
        positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
        indices = np.array([0, 1, 2, 2, 1, 3], np.uint16)
        binary = positions.tobytes() + indices.tobytes()
        doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [1, 0]}],
               "nodes": [{"name": "b", "mesh": 0}, {"name": "a", "children": [2]}, {"name": "c", "mesh": 0}],
               "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
               "buffers": [{"byteLength": len(binary)}],
               "bufferViews": [{"buffer": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
               "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
                             {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]}
        path = os.path.join(self.folder, "s.glb")
        write_glb(path, doc, binary)
        nodes = core.glb_node_triangles(path)
        # Depth first: a, its child c, then b.
        self.assertEqual([n for n, _ in nodes], ["a", "c", "b"])
        self.assertEqual([len(t) for _, t in nodes], [0, 2, 2])
        np.testing.assert_array_equal(nodes[1][1][1], positions[[2, 1, 3]])
        ranges = core.node_ranges(nodes, [("a", 0), ("c", 2), ("b", 2)])
        self.assertEqual(ranges["c"][0], 0)
        self.assertEqual(ranges["b"][0], 2)
        with self.assertRaisesRegex(core.GlbError, "node 'c' has 3 triangles on the server"):
            core.node_ranges(nodes, [("a", 0), ("c", 3), ("b", 2)])

    def test_not_a_glb(self):
        path = os.path.join(self.folder, "x.glb")
        with open(path, "wb") as f:
            f.write(b"not a glb at all, really")
        with self.assertRaisesRegex(core.GlbError, "not a binary glTF"):
            core.glb_node_triangles(path)


class Matching(unittest.TestCase):
    def test_triangles_and_corners_found_in_any_order(self):
        rng = np.random.default_rng(1)
        server = rng.uniform(-5, 5, (200, 3, 3))
        order = rng.permutation(200)
        rotate = np.array([1, 2, 0])
        blender = server[order][:, rotate]  # shuffled triangles, corners rotated
        index, corner = core.match_triangles(blender, server)
        np.testing.assert_array_equal(index, order)
        np.testing.assert_array_equal(corner, np.tile(rotate, (200, 1)))

    def test_a_triangle_with_no_twin_is_minus_one(self):
        server = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
        index, corner = core.match_triangles(server + 0.5, server)
        self.assertEqual(index[0], -1)
        self.assertTrue((corner[0] == -1).all())

    def test_a_mirrored_nodes_corners_swap(self):
        np.testing.assert_array_equal(core.server_corners([[0, 1, 2], [-1, -1, -1]], True), [[0, 2, 1], [-1, -1, -1]])
        np.testing.assert_array_equal(core.server_corners([[2, 0, 1]], False), [[2, 0, 1]])

    def test_loop_uvs_flip_v_and_count_torn_corners(self):
        atlas = np.array([[[0.1, 0.2], [0.3, 0.2], [0.1, 0.4]], [[0.5, 0.5], [0.6, 0.5], [0.5, 0.6]]], np.float32)
        loops = np.array([[0, 1, 2], [2, 1, 3]])
        uvs, written, torn = core.loop_uvs(atlas, np.array([0, 1]), np.array([[0, 1, 2], [0, 1, 2]]), loops, 4)
        self.assertTrue(written.all())
        self.assertEqual(torn, 2)  # loops 1 and 2 are in both triangles, at other UVs
        np.testing.assert_allclose(uvs[0], (0.1, 0.8))
        np.testing.assert_allclose(uvs[3], (0.5, 0.4))


class W(unittest.TestCase):
    def test_polygon_w_is_area_weighted(self):
        w = np.array([[0.2] * 3, [0.8] * 3, [0.5] * 3])
        result = core.polygon_w(w, np.array([0, 0, 1]), np.array([1.0, 3.0, 2.0]), 3)
        np.testing.assert_allclose(result[0], 0.65)
        np.testing.assert_allclose(result[1], 0.5)
        self.assertTrue(np.isnan(result[2]).all())
        colors = core.corner_colors(result, np.array([0, 1, 2]))
        np.testing.assert_allclose(colors[2], (1, 1, 1, 1))  # no value: white, not NaN

    def test_texels_land_on_blender_rows(self):
        atlas = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
        pixels = core.atlas_to_pixels(atlas)
        np.testing.assert_array_equal(pixels[1, :, :3], atlas[0])  # atlas row 0 is Blender's top row
        core.apply_texels(pixels, [4], [[9, 9, 9]])  # y 1, x 1
        np.testing.assert_array_equal(pixels[0, 1, :3], (9, 9, 9))
        with self.assertRaisesRegex(ValueError, "texels"):
            core.apply_texels(pixels, [6], [[0, 0, 0]])

    def test_an_update_refreshes_only_the_changed_triangles(self):
        server = np.array([5, -1, 2, 9, 2])
        before = np.arange(15, dtype=np.float64).reshape(5, 3)
        after, hit = core.refresh_triangle_w(server, before, [9, 2, 7], [[0.1] * 3, [0.2] * 3, [0.3] * 3])
        np.testing.assert_array_equal(hit, [False, False, True, True, True])
        np.testing.assert_allclose(after[[2, 3, 4]], [[0.2] * 3, [0.1] * 3, [0.2] * 3])
        np.testing.assert_array_equal(after[:2], before[:2])
        self.assertEqual(before[2, 0], 6.0)  # a copy: the saved W changes only when the caller stores it
        np.testing.assert_array_equal(core.loop_polygons([[0, 1, 2], [0, 2, 3]], [0, 0], 5), [0, 0, 0, 0, 0])

    def test_face_patch_faces_the_face_front(self):
        # A floor quad facing up (+Z in Blender, +Y in glTF).
        origin, u, v = core.face_patch([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
        self.assertGreater(np.cross(u, v)[1], 0)
        with self.assertRaisesRegex(ValueError, "degenerate"):
            core.face_patch([(0, 0, 0), (1, 0, 0), (2, 0, 0)])


def translate(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


class Moves(unittest.TestCase):
    def test_the_servers_hierarchy_between_baked_nodes(self):
        # root (empty) > a > b (empty) > c; d alone.
        nodes = [("root", -1), ("a", 0), ("b", 1), ("c", 2), ("d", -1)]
        self.assertEqual(core.node_parents(nodes, {"a", "c", "d"}), {"a": "", "c": "a", "d": ""})

    def test_a_child_that_moves_with_its_parent_is_carried_not_sent(self):
        parents = {"p": "", "c": "p", "x": ""}
        placed = {"p": np.eye(4), "c": translate(0, 0, 1), "x": translate(5, 0, 0)}
        turn = np.array([[0, -1, 0, 2], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float)  # 90 degrees, then +2 x
        target = {"p": turn, "c": turn @ placed["c"], "x": placed["x"]}
        calls, after = core.moves_to_send(target, placed, parents)
        self.assertEqual([name for name, _ in calls], ["p"])
        self.assertTrue(all(np.array_equal(after[k], target[k]) for k in target))
        calls, _ = core.moves_to_send(target, placed, parents, dynamic=["p"])  # p again: still one object
        self.assertEqual([name for name, _ in calls], ["p"])
        self.assertEqual(core.moves_to_send(placed, placed, parents)[0], [])

    def test_moves_the_server_would_refuse_are_named_before_any_is_sent(self):
        parents = {"p": "", "c": "p"}
        placed = {"p": np.eye(4), "c": translate(0, 0, 1)}
        # The child moved on its moving parent: two objects, one inside the other.
        with self.assertRaisesRegex(core.MoveError, "'c' moved on 'p'.*put 'c' back"):
            core.moves_to_send({"p": translate(3, 0, 0), "c": translate(3, 1, 1)}, placed, parents)
        # The child alone, after its parent moved once: inside that object.
        with self.assertRaisesRegex(core.MoveError, "'c' is part of 'p'.*bake again"):
            core.moves_to_send({"p": np.eye(4), "c": translate(0, 1, 1)}, placed, parents, dynamic=["p"])
        # The parent, after the child moved on its own once.
        with self.assertRaisesRegex(core.MoveError, "'p' holds 'c'.*bake again"):
            core.moves_to_send({"p": translate(3, 0, 0), "c": translate(3, 0, 1)}, placed, parents, dynamic=["c"])
        calls, _ = core.moves_to_send({"p": np.eye(4), "c": translate(0, 1, 1)}, placed, parents)
        self.assertEqual([name for name, _ in calls], ["c"])


class Session(unittest.TestCase):
    def test_the_saved_record_reads_back_as_it_was(self):
        marker = object()  # Blender's object, opaque to core
        w = np.array([[0.25, 0.5, 0.75], [np.nan] * 3], np.float32)
        matrix = np.arange(16.0).reshape(4, 4)
        record = core.session_record("s", 2 ** 40 + 3, "visq_w_s", {"Cube": {
            "object": marker, "parent": "Crate", "dynamic": True, "matrix": matrix, "loop_count": 8, "polygon_count": 2,
            "server": [7, -1], "triangle_w": w}})
        # As Blender stores it: int32, float32 and float64 arrays, the version as text.
        cube = record["objects"]["Cube"]
        self.assertEqual((cube["server"].dtype, cube["triangle_w"].dtype, cube["matrix"].dtype),
                         (np.int32, np.float32, np.float64))
        self.assertEqual(record["version"], str(2 ** 40 + 3))
        session = core.read_session(record)
        self.assertEqual((session["scene"], session["version"], session["image"]), ("s", 2 ** 40 + 3, "visq_w_s"))
        cube = session["objects"]["Cube"]
        self.assertIs(cube["object"], marker)
        self.assertEqual((cube["parent"], cube["dynamic"]), ("Crate", True))
        np.testing.assert_array_equal(cube["matrix"], matrix)
        np.testing.assert_array_equal(cube["server"], [7, -1])
        np.testing.assert_array_equal(cube["triangle_w"], w)  # NaN rows kept
        cube["server"][0] = 0
        self.assertEqual(record["objects"]["Cube"]["server"][0], 7)  # copies, not views of the record

    def test_a_record_it_cannot_read_says_bake_again(self):
        with self.assertRaisesRegex(core.SessionError, "format None.*run Bake obscurances again"):
            core.read_session({"scene": "s"})
        record = core.session_record("s", 1, "i", {"C": {
            "object": None, "parent": "", "dynamic": False, "matrix": np.eye(4), "loop_count": 3, "polygon_count": 1,
            "server": [0], "triangle_w": [1, 1, 1]}})
        record["objects"]["C"]["triangle_w"] = np.zeros(2, np.float32)
        with self.assertRaisesRegex(core.SessionError, "object 'C': 16 matrix entries, 1 triangles with 2 W"):
            core.read_session(record)
        del record["objects"]["C"]["server"]
        with self.assertRaisesRegex(core.SessionError, "KeyError"):
            core.read_session(record)


class JobTest(unittest.TestCase):
    def test_result_error_and_cancel(self):
        self.assertEqual(core.Job(lambda job: 42).run_here().result, 42)
        failed = core.Job(lambda job: 1 / 0).start()
        self.assertTrue(failed.wait(5))
        self.assertIsInstance(failed.error, ZeroDivisionError)
        stop = threading.Event()

        class Cancellation:
            def cancel(self):
                stop.set()

        def work(job):
            job.report_progress(0.5, "waiting")
            stop.wait(5)
            raise RuntimeError("stopped")

        job = core.Job(work, Cancellation()).start()
        job.cancel()
        self.assertTrue(job.wait(5))
        self.assertTrue(job.cancel_requested)
        self.assertEqual(str(job.error), "stopped")

    def test_modal_steps_show_progress_and_esc_cancels_once(self):
        stop = threading.Event()

        class Cancellation:
            cancels = 0

            def cancel(self):
                Cancellation.cancels += 1
                stop.set()

        def work(job):
            job.report_progress(0.25, "baking 4/16")
            stop.wait(5)
            raise RuntimeError("stopped")

        job = core.Job(work, Cancellation())
        job.started = 100.0
        job.start()  # the modal path: a worker thread
        while job.fraction < 0.25:
            threading.Event().wait(0.001)
        step = core.modal_step(job, "TIMER", now=103.0)
        self.assertEqual((step.action, step.percent, step.status),
                         ("WAIT", 25, "visq: baking 4/16 25%, 3 s (Esc cancels)"))
        self.assertEqual(core.modal_step(job, "MOUSEMOVE").action, "PASS")
        self.assertEqual(core.modal_step(job, "ESC").action, "CANCEL")
        self.assertEqual(core.modal_step(job, "ESC").action, "PASS")  # a second Esc is the artist's
        self.assertEqual(Cancellation.cancels, 1)
        self.assertTrue(job.wait(5))
        self.assertEqual(core.modal_step(job, "TIMER").action, "DONE")
        self.assertEqual(str(job.error), "stopped")

    def test_describe_error(self):
        self.assertEqual(core.describe_error(ValueError("address: bad")), "visq: address: bad")
        self.assertEqual(core.describe_error(RuntimeError("x")), "visq: RuntimeError: x")

    @unittest.skipIf(visq is None, "the visq package is not importable (run_blender_test.sh puts it on PYTHONPATH)")
    def test_describe_the_clients_errors(self):
        import grpc
        down = visq.VisqError(grpc.StatusCode.UNAVAILABLE, "failed to connect")
        self.assertIn("cannot be reached", core.describe_error(down))
        gone = visq.VisqError(grpc.StatusCode.FAILED_PRECONDITION, "scene 'x' has no full bake to update")
        self.assertIn("run Bake obscurances again", core.describe_error(gone))
        bad = visq.VisqError(grpc.StatusCode.INVALID_ARGUMENT, "d_max: -1 must be > 0")
        self.assertEqual(core.describe_error(bad), f"visq: {bad}")
        self.assertEqual(core.describe_error(visq.Cancelled()), "visq: cancelled")


if __name__ == "__main__":
    unittest.main()
