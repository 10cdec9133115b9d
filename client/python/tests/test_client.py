"""The Python client against the real visq-server binary on loopback.

Environment: VISQ_SERVER_BINARY (required), VISQ_CLI_BINARY (the C++ CLI,
to compare answers), VISQ_SHARED_SCENES (optional real scenes).
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import unittest

import grpc
import numpy as np

import visq

HERE = os.path.dirname(os.path.abspath(__file__))
EXAMPLES = os.path.join(HERE, "..", "examples")
SCENE = "cornell_box_visq"
LIGHT_SOURCE = visq.Patch((-0.25, 1.99, -0.25), (0.5, 0, 0), (0, 0, 0.5))
# The floor, facing up (edge_u x edge_v = +y).
FLOOR = visq.Patch((-0.999, 0.001, -0.999), (0, 0, 1.998), (1.998, 0, 0))
LIGHT = [(-0.25, 1.99, -0.25), (0.25, 1.99, -0.25), (0.25, 1.99, 0.25), (-0.25, 1.99, 0.25)]


def read(path):
    try:
        with open(path) as f:
            return f.read().strip()
    except FileNotFoundError:
        return ""


def patch_text(p):
    return ";".join(",".join(repr(float(v)) for v in vector) for vector in p)


class Server:
    """visq-server on a free loopback port with a scratch repository."""

    def __init__(self, extra=()):
        self.dir = tempfile.mkdtemp(prefix="visq-python-")
        self.repo = os.path.join(self.dir, "repo")
        os.mkdir(self.repo)
        port_file = os.path.join(self.dir, "port")
        self.log = open(os.path.join(self.dir, "server.log"), "w")
        self.process = subprocess.Popen(
            [os.environ["VISQ_SERVER_BINARY"], "--address", "127.0.0.1:0", "--port-file", port_file,
             "--scene-repo", self.repo, "--seed-samples", *extra],
            stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while not read(port_file):
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"visq-server did not start:\n{self.log_text()}")
            time.sleep(0.05)
        self.address = f"127.0.0.1:{int(read(port_file))}"
        with visq.Client(self.address) as client:
            client.wait_until_serving(120)

    def log_text(self):
        return read(self.log.name)

    def stop(self):
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()


def setUpModule():
    global SERVER
    SERVER = Server()


def tearDownModule():
    SERVER.stop()
    shutil.rmtree(SERVER.dir, ignore_errors=True)


class ClientTest(unittest.TestCase):
    def setUp(self):
        self.client = visq.Client(SERVER.address)
        self.scratch = tempfile.mkdtemp(prefix="visq-python-test-")

    def tearDown(self):
        self.client.close()
        shutil.rmtree(self.scratch, ignore_errors=True)

    # -- scenes ----------------------------------------------------------------

    def test_health_list_get_stats(self):
        self.assertEqual(self.client.health(), "SERVING")
        names = [s.name for s in self.client.list_scenes()]
        self.assertIn(SCENE, names)
        info = self.client.get_scene(SCENE, include_nodes=True)
        self.assertEqual(info.triangle_count, 36)
        self.assertIn("short_box", [n.name for n in info.nodes])
        stats = self.client.stats()
        self.assertGreaterEqual(stats.scenes_resident, 1)
        self.assertTrue(stats.server_version)

    def test_upload_sends_the_buffers_not_the_images(self):
        folder = os.path.join(self.scratch, "tri")
        os.mkdir(folder)
        # One triangle in an external buffer, and a texture of 1 MiB that the
        # server would drop.
        positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4")
        with open(os.path.join(folder, "tri geometry.bin"), "wb") as f:
            f.write(positions.tobytes())
        with open(os.path.join(folder, "albedo.png"), "wb") as f:
            f.write(b"\x89PNG" + bytes(1 << 20))
        gltf = {
            "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "name": "tri"}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "buffers": [{"uri": "tri%20geometry.bin", "byteLength": 36}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
            "images": [{"uri": "albedo.png"}],
        }
        path = os.path.join(folder, "tri.gltf")
        with open(path, "w") as f:
            json.dump(gltf, f)
        self.assertEqual([name for name, _ in visq.geometry_files(path)], ["tri geometry.bin"])
        info = self.client.upload_gltf(path, name="py_tri", replace=True)
        self.assertEqual(info.name, "py_tri")
        self.assertEqual(info.triangle_count, 1)
        stored = [f for _, _, files in os.walk(SERVER.repo) for f in files]
        self.assertNotIn("albedo.png", stored, "the image was uploaded")
        self.assertTrue(self.client.unload_scene("py_tri", delete_from_repository=True))
        with self.assertRaises(visq.VisqError) as caught:
            self.client.get_scene("py_tri")
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_upload_refuses_a_buffer_outside_the_folder_and_a_missing_file(self):
        folder = os.path.join(self.scratch, "hostile")
        os.mkdir(folder)
        path = os.path.join(folder, "h.gltf")
        with open(path, "w") as f:
            json.dump({"asset": {"version": "2.0"}, "buffers": [{"uri": "../../etc/passwd", "byteLength": 1}]}, f)
        with self.assertRaisesRegex(ValueError, r"buffers\[0\]\.uri: '../../etc/passwd' leaves the folder"):
            self.client.upload_gltf(path)
        with open(path, "w") as f:
            json.dump({"asset": {"version": "2.0"}, "buffers": [{"uri": "gone.bin", "byteLength": 1}]}, f)
        with self.assertRaisesRegex(FileNotFoundError, r"buffers\[0\]\.uri: 'gone.bin'"):
            self.client.upload_gltf(path)
        with self.assertRaisesRegex(FileNotFoundError, "no such file"):
            self.client.upload_gltf(os.path.join(folder, "missing.gltf"))

    def test_upload_a_shared_scene(self):
        shared = os.environ.get("VISQ_SHARED_SCENES", "")
        path = os.path.join(shared, "cornell_box", "cornell_box.gltf")
        if not os.path.isfile(path):
            candidates = [os.path.join(d, f) for d, _, fs in os.walk(os.path.join(shared, "cornell_box"))
                          for f in fs if f.endswith((".gltf", ".glb"))] if shared else []
            if not candidates:
                self.skipTest("../shared/scenes/cornell_box is absent")
            path = sorted(candidates)[0]
        info = self.client.upload_gltf(path, name="py_shared_cornell", replace=True)
        self.assertGreater(info.triangle_count, 0)
        self.client.unload_scene("py_shared_cornell", delete_from_repository=True)

    # -- errors ------------------------------------------------------------------

    def test_errors_carry_code_and_field(self):
        with self.assertRaises(visq.VisqError) as caught:
            self.client.hidden_sample_map("", LIGHT_SOURCE, FLOOR, width=4, height=4)
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertEqual(caught.exception.field, "scene.name")
        with self.assertRaises(visq.VisqError) as caught:
            self.client.hidden_sample_map("no_such_scene", LIGHT_SOURCE, FLOOR, width=4, height=4)
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)
        with self.assertRaisesRegex(ValueError, "method: 'raycats' is not one of auto, raster, raycast, exact"):
            self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, method="raycats")
        with self.assertRaisesRegex(ValueError, r"receiver.edge_u: expected 3 numbers"):
            self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, ((0, 0, 0), (1, 0), (0, 0, 1)))

    def test_default_deadlines_and_an_explicit_one(self):
        self.assertEqual(self.client.timeout, 60.0)
        self.assertIsNone(self.client.stream_timeout, "streams and bakes have no fixed deadline")
        with self.assertRaises(visq.VisqError) as caught:
            self.client.compute_obscurances(SCENE, 0.5, resolution=64, directions=4096, timeout=0.3)
        self.assertEqual(caught.exception.code, grpc.StatusCode.DEADLINE_EXCEEDED)

    def test_addresses_default_to_the_server_port(self):
        self.assertEqual(visq.normalize_address("localhost"), f"localhost:{visq.DEFAULT_PORT}")
        self.assertEqual(visq.normalize_address("::1"), f"[::1]:{visq.DEFAULT_PORT}")
        self.assertEqual(visq.normalize_address("[::1]:7"), "[::1]:7")
        self.assertEqual(visq.normalize_address("unix:/tmp/s"), "unix:/tmp/s")
        with self.assertRaisesRegex(ValueError, "port 'x'"):
            visq.normalize_address("host:x")

    # -- algorithms ----------------------------------------------------------------

    def test_hidden_sample_map_matches_the_cpp_cli(self):
        m = self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=24, height=16, samples=64,
                                          bitmasks=True, method="raster")
        self.assertEqual(m.visible_fraction.shape, (16, 24))
        self.assertEqual(m.visible_fraction.dtype, np.float32)
        self.assertTrue(((m.visible_fraction >= 0) & (m.visible_fraction <= 1)).all())
        self.assertLess(m.visible_fraction.min(), 1.0, "the boxes shadow part of the floor")
        self.assertEqual(m.source_samples.shape, (m.figures.sample_count, 3))
        # The bitmasks say the same as the fractions.
        blocked = m.blocked()
        np.testing.assert_allclose(1.0 - blocked.mean(axis=-1), m.visible_fraction, atol=1e-6)
        # The accuracy comes in the stream's last message; HOUGH lookup errors
        # are chunks like the fractions.
        self.assertEqual(m.accuracy.method, "raster-exact-lookup")
        self.assertGreater(m.accuracy.error_bound, 0.0)
        self.assertIsNone(m.lookup_error)
        fast = self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=24, height=16, samples=64,
                                             lookup="hough")
        self.assertEqual(fast.accuracy.method, "raster-hough-lookup")
        self.assertEqual(fast.lookup_error.shape, (16, 24))
        self.assertTrue((fast.lookup_error >= 0).all())
        self.assertLessEqual(float(fast.lookup_error.max()), fast.accuracy.error_bound)
        # Jittered samples: each texel's own bound, the largest of which is the map's.
        bounded = self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=24, height=16, samples=64,
                                                texel_error=True)
        self.assertEqual(bounded.texel_error.shape, (16, 24))
        self.assertAlmostEqual(float(bounded.texel_error.max()), bounded.accuracy.error_bound, places=6)
        self.assertIn("Clopper-Pearson", bounded.accuracy.note)
        # Beside each bound, an estimate (not a bound), never above it.
        self.assertEqual(bounded.texel_estimate.shape, (16, 24))
        self.assertTrue((bounded.texel_estimate <= bounded.texel_error).all())
        self.assertTrue(bounded.accuracy.HasField("estimate"))
        self.assertAlmostEqual(float(bounded.texel_estimate.max()), bounded.accuracy.estimate, places=6)
        # A target may be on the estimate; the answer says whether it met it.
        on_estimate = self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=24, height=16,
                                                    target={"max_error": 0.05, "guarantee": "estimate"})
        self.assertEqual(on_estimate.accuracy.parameters["target_met"], 1.0)
        with self.assertRaises(ValueError):
            self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=24, height=16,
                                          target={"max_error": 0.05, "guarantee": "roughly"})
        cli = os.environ.get("VISQ_CLI_BINARY")
        if not cli:
            self.skipTest("VISQ_CLI_BINARY unset: no C++ answer to compare with")
        npy = os.path.join(self.scratch, "cli.npy")
        out = subprocess.run([cli, "hidden-map", "--server", SERVER.address, "--scene", SCENE, "--source",
                              patch_text(LIGHT_SOURCE), "--receiver", patch_text(FLOOR), "--width", "24",
                              "--height", "16", "--samples", "64", "--json", "--npy", npy], capture_output=True,
                             text=True, check=True).stdout
        self.assertAlmostEqual(json.loads(out)["mean_visible_fraction"], float(m.visible_fraction.mean()),
                               places=6)
        # The CLI's .npy is numpy's, laid out as this package's arrays.
        np.testing.assert_array_equal(np.load(npy), m.visible_fraction)

    def test_example_writes_the_visible_fractions(self):
        out = os.path.join(self.scratch, "map.npy")
        subprocess.run([sys.executable, os.path.join(EXAMPLES, "hidden_map.py"), "--server", SERVER.address,
                        "--scene", SCENE, "--out", out, "--width", "20", "--height", "10", "--samples", "64"],
                       check=True, capture_output=True)
        saved = np.load(out)
        self.assertEqual(saved.shape, (10, 20))
        self.assertEqual(saved.dtype, np.float32)
        direct = self.client.hidden_sample_map(SCENE, visq.Patch((-0.25, 1.99, -0.25), (0.5, 0, 0), (0, 0, 0.5)),
                                               visq.Patch((-0.999, 0.001, -0.999), (1.998, 0, 0), (0, 0, 1.998)),
                                               width=20, height=10, samples=64)
        np.testing.assert_array_equal(saved, direct.visible_fraction)

    def test_light_visibility_agrees_with_the_exact_hidden_map(self):
        lv = self.client.light_visibility(SCENE, LIGHT, receiver=FLOOR, width=12, height=8)
        self.assertEqual(lv.visible_fraction.shape, (8, 12))
        self.assertTrue(((lv.visible_fraction >= 0) & (lv.visible_fraction <= 1 + 1e-9)).all())
        self.assertGreater(lv.visible_fraction.max(), 0.5)
        self.assertLess(lv.visible_fraction.min(), 0.5)
        exact = self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=12, height=8, method="exact")
        np.testing.assert_allclose(exact.visible_fraction, lv.visible_fraction, atol=1e-4)
        # The same points in several stream batches give the same answers.
        o, u, v = (np.array(x, dtype=float) for x in FLOOR)
        s, t = (np.arange(12) + 0.5) / 12, (np.arange(8) + 0.5) / 8
        points = (o + t[:, None, None] * v + s[None, :, None] * u).reshape(-1, 3)
        normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
        seen = []
        batched = self.client.light_visibility(SCENE, LIGHT, points=points, normals=normals, batch_points=40,
                                               progress=lambda done, total: seen.append((done, total)))
        self.assertEqual(seen, [(40, 96), (80, 96), (96, 96)])
        self.assertEqual(len(batched.responses), 3)
        np.testing.assert_allclose(batched.visible_fraction.reshape(8, 12), lv.visible_fraction, atol=1e-12)
        # A shadow tolerance of 0 asks for every answer exact: no error stated.
        # On the Cornell box's boxes nothing is small enough to leave out at
        # the server's default either.
        strict = self.client.light_visibility(SCENE, LIGHT, points=points, normals=normals, shadow_tolerance=0)
        self.assertEqual(strict.visible_fraction_error.shape, (96,))
        self.assertTrue((strict.visible_fraction_error == 0).all())
        self.assertEqual(strict.accuracy.parameters["shadow_tolerance"], 0.0)
        np.testing.assert_allclose(strict.visible_fraction.reshape(8, 12), lv.visible_fraction, atol=1e-12)
        self.assertTrue((lv.visible_fraction_error <= 1e-6).all())
        with self.assertRaises(ValueError):
            self.client.light_visibility(SCENE, LIGHT, points=points, shadow_tolerance=2)

    def test_patch_visibility_and_transmittance(self):
        pv = self.client.patch_visibility(SCENE, LIGHT_SOURCE, FLOOR, source_grid=8, receiver_grid=(6, 4),
                                          method="raycast")
        self.assertEqual(pv.source_visible.shape, (8, 8))
        self.assertEqual(pv.receiver_visible.shape, (4, 6))
        self.assertTrue(0 < pv.mutual_visible_fraction < 1)
        tr = self.client.transmittance(SCENE, (0, -1, 0), {"short_box": 2.0}, points=[(0.4, 0.01, 0.35),
                                                                                   (-0.9, 0.01, 0.9)],
                                       resolution=64, slices=64)
        under, clear = tr.at_points(tr.transmittance)
        self.assertLess(under, 0.5, "under the absorbing box")
        self.assertAlmostEqual(float(clear), 1.0, places=5)
        # Named no method: the server ran the faster of the two and says which.
        self.assertIn(tr.response.accuracy.method, ("transmittance-slicemap", "transmittance-ray-stabbing"))
        # The points' own rays: inside the box at y = 0.01, 0.59 of it above.
        own = self.client.transmittance(SCENE, (0, -1, 0), {"short_box": 2.0}, points=[(0.4, 0.01, 0.35)],
                                        method="ray-stabbing")
        depth, = own.at_points(own.optical_depth)
        self.assertAlmostEqual(float(depth), 2.0 * 0.59, places=3)
        self.assertEqual(own.response.accuracy.method, "transmittance-ray-stabbing")
        with self.assertRaises(ValueError):
            self.client.transmittance(SCENE, (0, -1, 0), {"short_box": 2.0}, points=[(0, 0, 0)], method="rays")

    def test_voxelize(self):
        grid = self.client.voxelize(SCENE, width=16, height=8, slices=40, axis=1)
        self.assertEqual(grid.bits.shape, (8, 16, 2))
        occupancy = grid.occupancy()
        self.assertEqual(occupancy.shape, (8, 16, 40))
        self.assertEqual(int(occupancy.sum()), grid.figures.occupied_voxels)

    def test_volumetric_shadow(self):
        image = self.client.volumetric_shadow(SCENE, (0, 1, 3.5), (0, 0, -1), width=32, height=24,
                                              sun=(0.2, -1, 0.1), shadow_map_size=128, combined=True)
        self.assertEqual(image.inscattering.shape, (24, 32, 3))
        self.assertEqual(image.combined.shape, (24, 32, 3))
        self.assertTrue(np.isfinite(image.inscattering).all())
        boxed = self.client.volumetric_shadow(SCENE, (0, 1, 3.5), (0, 0, -1), width=32, height=24,
                                              sun=(0.2, -1, 0.1), shadow_map_size=128,
                                              medium_box=((-1, 0, -1), (1, 2, 1)), estimate_error=True)
        self.assertGreaterEqual(boxed.figures.accuracy.error_bound, 0.0)
        self.assertIn("an estimate", boxed.figures.accuracy.note)
        # Inside the closed box under a sun from above, the medium is all in
        # shadow: every map gives the same black image, and the estimate is
        # exactly 0 (it was read as -1, "none", when merged into the first
        # message's accuracy).
        dark = self.client.volumetric_shadow(SCENE, (0, 1, 0.5), (0, 0, -1), width=16, height=12,
                                             sun=(0.2, -1, 0.1), shadow_map_size=256,
                                             medium_box=((-0.9, 0.1, -0.9), (0.9, 1.8, 0.9)), estimate_error=True)
        self.assertEqual(float(np.abs(dark.inscattering).max()), 0.0)
        self.assertEqual(dark.figures.accuracy.error_bound, 0.0)
        self.assertIn("Richardson", dark.figures.accuracy.note)

    def test_obscurance_bake_with_progress_then_preview(self):
        progress = []
        bake = self.client.compute_obscurances(SCENE, 0.5, resolution=32, directions=8, progress=progress.append,
                                               method="depth-peeling")
        self.assertEqual(bake.w.shape, (32, 32, 3))
        self.assertEqual(bake.estimated.shape, (32, 32))
        self.assertTrue(bake.estimated.any())
        self.assertTrue(((bake.w[bake.estimated] >= 0) & (bake.w[bake.estimated] <= 1)).all())
        self.assertTrue(progress, "no progress callback")
        self.assertEqual(progress[-1].directions_total, 8)
        preview = self.client.obscurance_preview(SCENE, (0, 1, 3.5), (0, 0, -1), width=24, height=16)
        self.assertEqual(preview.rgb.shape, (16, 24, 3))
        self.assertTrue(preview.covered.any())
        exported = self.client.export_obscurances(SCENE, atlas_uvs=True, gltf=True)
        self.assertEqual(exported.atlas_uv.shape, (exported.figures.triangles, 3, 2))
        self.assertTrue(((exported.atlas_uv >= 0) & (exported.atlas_uv <= 1)).all())
        self.assertEqual(exported.glb[:4], b"glTF")
        # W per vertex as COLOR_0 on request; TEXCOORD_0 always (glTF wants set 0 before any other).
        coloured = self.client.export_obscurances(SCENE, atlas_uvs=False, gltf=True, vertex_colors=True)
        json_length = int.from_bytes(coloured.glb[12:16], "little")
        document = json.loads(coloured.glb[20:20 + json_length])
        for mesh in document["meshes"]:
            for primitive in mesh["primitives"]:
                self.assertIn("COLOR_0", primitive["attributes"])
                self.assertIn("TEXCOORD_0", primitive["attributes"])
        with self.assertRaises(visq.VisqError) as refused:
            self.client.export_obscurances(SCENE, atlas_uvs=True, gltf=False, vertex_colors=True)
        self.assertIn("want_vertex_colors", str(refused.exception))

    def test_obscurance_errors_per_element(self):
        bake = self.client.compute_obscurances(SCENE, 0.5, resolution=32, directions=8, want_averages=True,
                                               want_errors=True)
        self.assertEqual(bake.w_error.shape, (32, 32))
        self.assertEqual(bake.triangle_w_error.shape, (bake.triangle_w.shape[0],))
        self.assertEqual(bake.vertex_w_error.shape, (bake.vertex_w.shape[0],))
        # The stated bound is the widest own bound among the texels it covers
        # (those resting on a quarter of the directions); the rest are counted.
        stated = np.float32(bake.figures.accuracy.error_bound)
        own = bake.w_error[bake.estimated]
        covered = own <= stated
        self.assertGreater(covered.sum(), (~covered).sum())
        self.assertEqual(own[covered].max(), stated)
        self.assertEqual(bake.figures.accuracy.parameters["texels_outside_bound"], (~covered).sum())
        self.assertTrue((bake.w_error[~bake.estimated] == 1).all())
        self.assertIsNone(self.client.compute_obscurances(SCENE, 0.5, resolution=32, directions=8).w_error)

    def test_a_node_move_and_the_incremental_update(self):
        self.client.load_from_repository(SCENE, replace=True)
        self.client.compute_obscurances(SCENE, 0.5, resolution=32, directions=8)
        info = self.client.get_scene(SCENE, include_nodes=True)
        node = [n.name for n in info.nodes].index("short_box")
        moved = np.eye(4)
        moved[:3, 3] = (0.0, 0.0, -0.3)  # numpy's row-major M @ p; sent column-major
        after = self.client.set_node_transform(SCENE, "short_box", moved)
        self.assertGreater(after.version, info.version)
        update = self.client.update_obscurances(SCENE, want_full_w=True)
        self.assertEqual(update.response.moves_applied, 1)
        self.assertGreater(len(update.texels), 0)
        self.assertEqual(update.w.shape, (len(update.texels), 3))
        self.assertEqual(update.full_w.shape, (32, 32, 3))
        with self.assertRaisesRegex(ValueError, "matrix: expected a finite 4x4 matrix"):
            self.client.set_node_transform(SCENE, node, np.eye(3))
        self.client.load_from_repository(SCENE, replace=True)  # the stored scene back for the other tests

    def test_a_token_is_sent(self):
        token_file = os.path.join(self.scratch, "token")
        with open(token_file, "w") as f:
            f.write("s3cret-token-for-python\r\n")
        server = Server(["--auth-token-file", token_file])
        try:
            with visq.Client(server.address) as anonymous:
                self.assertEqual(anonymous.health(), "SERVING", "health needs no token")
                with self.assertRaises(visq.VisqError) as caught:
                    anonymous.list_scenes()
                self.assertEqual(caught.exception.code, grpc.StatusCode.UNAUTHENTICATED)
            with visq.Client(server.address, token_file=token_file) as client:
                self.assertIn(SCENE, [s.name for s in client.list_scenes()])
        finally:
            server.stop()
            shutil.rmtree(server.dir, ignore_errors=True)

    def test_a_long_map_cancelled_stops_its_work_on_the_server(self):
        # Half a billion segments by either sampled method; the Cancellation
        # fires a second in, and the server's log must show the call's end
        # within a second of it: the cancel reached the work.
        import re
        ended = re.compile(r"HiddenSampleMap\] CANCELLED in ([0-9.]+) ms")
        for method in ("raycast", "raster"):
            with self.subTest(method=method):
                before = len(ended.findall(SERVER.log_text()))
                cancel = visq.Cancellation()
                threading.Timer(1.0, cancel.cancel).start()
                with self.assertRaises(visq.Cancelled):
                    self.client.hidden_sample_map(SCENE, LIGHT_SOURCE, FLOOR, width=1024, height=512, samples=4096,
                                                  method=method, cancel=cancel)
                deadline = time.monotonic() + 5
                while len(ended.findall(SERVER.log_text())) == before and time.monotonic() < deadline:
                    time.sleep(0.05)
                found = ended.findall(SERVER.log_text())
                self.assertGreater(len(found), before, SERVER.log_text()[-2000:])
                self.assertLess(float(found[-1]), 2000.0, "the work ran on after the cancel")

    def test_a_bake_is_cancelled(self):
        cancel = visq.Cancellation()
        started = time.monotonic()

        def progress(p):
            cancel.cancel()  # from the first progress message on

        with self.assertRaises(visq.Cancelled) as caught:
            self.client.compute_obscurances(SCENE, 0.5, resolution=64, directions=4096, progress=progress,
                                            cancel=cancel, method="depth-peeling")
        self.assertEqual(caught.exception.code, grpc.StatusCode.CANCELLED)
        self.assertLess(time.monotonic() - started, 30)
        # Cancelled from another thread, before any message.
        other = visq.Cancellation()
        threading.Timer(0.2, other.cancel).start()
        with self.assertRaises(visq.Cancelled):
            self.client.compute_obscurances(SCENE, 0.5, resolution=64, directions=4096, cancel=other)
        # The server is still serving.
        self.assertEqual(self.client.health(), "SERVING")


if __name__ == "__main__":
    unittest.main()
