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

    def test_face_patch_faces_the_face_front(self):
        # A floor quad facing up (+Z in Blender, +Y in glTF).
        origin, u, v = core.face_patch([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
        self.assertGreater(np.cross(u, v)[1], 0)
        with self.assertRaisesRegex(ValueError, "degenerate"):
            core.face_patch([(0, 0, 0), (1, 0, 0), (2, 0, 0)])


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
