# metadata_during_build.py SERVER_BINARY SPONZA_GLTF COPIES [LABEL] [--scaling] [--unique]
#
# How long metadata calls take while a large scene builds its structures:
# starts SERVER_BINARY on a free loopback port with an empty repository,
# uploads COPIES copies of Sponza (one glTF: each copy its own node tree
# over Sponza's meshes, as a level places repeated meshes), fires the first
# RAYCAST hidden-sample map (64x64 texels, 64 samples, at the copy at the
# origin) and, until it answers, calls GetScene, ListScenes and GetStats in
# turn. Prints the scene's CPU memory and the server's RSS after the upload,
# each call's p50 / p99 / max and the query's total and build_ms. Not a
# test: figures.
#
# --scaling then goes on to the rest of a level's scaling table: RAYCAST
# warm, RASTER first and warm, a first LightVisibility of 100 points on the
# same floor, and the memory after all three (the scene's own cpu/gpu bytes,
# its unique triangles and instances, and the server's RSS).
#
# --unique writes each copy with meshes of its own (over the same
# accessors, so the upload stays small): nothing is repeated for the
# server, which holds and indexes every triangle as unique (a level of
# COPIES x 66K unique triangles), where without it the copies share
# Sponza's meshes and stay instances.
#
# Uses the generated Python stubs (tests/bench/scripts/README.md); run with
# /usr/bin/python3 (Debian's grpcio).
import json, os, subprocess, sys, tempfile, threading, time

sys.path.insert(0, os.environ.get("VISQ_PY_STUBS", "/tmp/visq-stubs"))
import grpc
from visq.v1 import visq_pb2 as pb, visq_pb2_grpc as rpc

scaling = "--scaling" in sys.argv
unique = "--unique" in sys.argv
args = [a for a in sys.argv if a not in ("--scaling", "--unique")]
server_binary, sponza, copies = args[1], args[2], int(args[3])
label = args[4] if len(args) > 4 else os.path.basename(server_binary)

gltf = json.load(open(sponza))
bin_name = gltf["buffers"][0]["uri"]
bin_path = os.path.join(os.path.dirname(sponza), bin_name)
work = tempfile.mkdtemp(prefix="visq-metadata-")

# The level: Sponza's node tree once per copy, on a square grid 1.1 extents
# apart (copy 0 where Sponza is).
def write_level(spacing):
    nodes = gltf["nodes"]
    side = 1
    while side * side < copies:
        side += 1
    all_nodes, roots, meshes = [], [], []
    for c in range(copies):
        base = len(all_nodes)
        mesh_base = len(meshes) if unique else 0
        if unique or c == 0:
            meshes.extend(gltf.get("meshes", []))
        for n in nodes:
            m = dict(n)
            if "children" in m:
                m["children"] = [base + k for k in n["children"]]
            if "mesh" in m:
                m["mesh"] = mesh_base + n["mesh"]
            all_nodes.append(m)
        all_nodes.append({"name": f"copy{c}", "translation": [spacing * (c % side), 0.0, spacing * (c // side)],
                          "children": [base + r for r in gltf["scenes"][gltf.get("scene", 0)]["nodes"]]})
        roots.append(len(all_nodes) - 1)
    level = dict(gltf, nodes=all_nodes, meshes=meshes, scenes=[{"nodes": roots}], scene=0)
    path = os.path.join(work, "level.gltf")
    json.dump(level, open(path, "w"))
    return path

# The server, on a port it picks.
repo = os.path.join(work, "repo")
port_file = os.path.join(work, "port")
log = open(os.path.join(work, "server.log"), "w")
server = subprocess.Popen([server_binary, "--scene-repo", repo, "--address", "127.0.0.1:0", "--port-file", port_file],
                          stdout=log, stderr=subprocess.STDOUT)
try:
    for _ in range(600):
        if os.path.exists(port_file) and open(port_file).read().strip():
            break
        time.sleep(0.05)
    address = "127.0.0.1:" + open(port_file).read().strip()
    channel = grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", 64 << 20)])
    grpc.channel_ready_future(channel).result(timeout=60)
    stub = rpc.VisibilityServiceStub(channel)

    def upload(scene, main, files):
        header = pb.LoadSceneRequest()
        header.header.name = scene
        header.header.upload_main_file = main
        yield header
        for name, path in files:
            data = open(path, "rb").read()
            for i in range(0, len(data), 1 << 20):
                chunk = pb.LoadSceneRequest()
                chunk.chunk.file, chunk.chunk.data = name, data[i:i + (1 << 20)]
                yield chunk
    # Sponza alone first, for its bounds.
    one = stub.LoadScene(upload("sponza", "sponza.gltf", (("sponza.gltf", sponza), (bin_name, bin_path))), timeout=600)
    level = write_level(1.1 * max(one.bounds_max.x - one.bounds_min.x, one.bounds_max.z - one.bounds_min.z))
    start = time.time()
    info = stub.LoadScene(upload("level", "level.gltf", (("level.gltf", level), (bin_name, bin_path))), timeout=600)
    upload_s = time.time() - start
    def rss_mib():
        for line in open(f"/proc/{server.pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")
    loaded = stub.GetScene(pb.GetSceneRequest(name="level"), timeout=600)
    loaded_cpu_mib, loaded_rss_mib = loaded.memory.cpu_bytes / (1 << 20), rss_mib()

    # The query at the copy at the origin: a light patch high in the atrium,
    # the atrium floor as receiver (hidden_sample_map_bench.cpp's).
    r = pb.HiddenSampleMapRequest()
    r.scene.name = "level"
    r.method = pb.RAYCAST
    def patch(p, o, u, v):
        p.origin.x, p.origin.y, p.origin.z = o; p.edge_u.x, p.edge_u.y, p.edge_u.z = u; p.edge_v.x, p.edge_v.y, p.edge_v.z = v
    lo, hi = one.bounds_min, one.bounds_max
    ex, ey, ez = hi.x - lo.x, hi.y - lo.y, hi.z - lo.z
    mx, mz = (lo.x + hi.x) / 2, (lo.z + hi.z) / 2
    ls = 0.08 * ex
    patch(r.source, (mx - ls / 2, lo.y + 0.75 * ey, mz - ls / 2), (ls, 0, 0), (0, 0, ls))
    patch(r.receiver, (lo.x + 0.15 * ex, 0.135, mz - 0.2 * ez), (0.7 * ex, 0, 0), (0, 0, 0.4 * ez))
    r.samples.count = 64
    r.width = r.height = 64
    answer = {}
    def query():
        t0 = time.time()
        last = None
        for m in stub.HiddenSampleMap(r, timeout=600):
            last = m
        answer["s"] = time.time() - t0
        answer["timing"] = last.timing
    thread = threading.Thread(target=query)
    thread.start()
    calls = {"GetScene": lambda: stub.GetScene(pb.GetSceneRequest(name="level"), timeout=600),
             "ListScenes": lambda: stub.ListScenes(pb.ListScenesRequest(), timeout=600),
             "GetStats": lambda: stub.GetStats(pb.GetStatsRequest(), timeout=600)}
    times = {k: [] for k in calls}
    while thread.is_alive():
        for name, call in calls.items():
            t0 = time.perf_counter()
            call()
            times[name].append(1e3 * (time.perf_counter() - t0))
    thread.join()

    def pct(v, q):
        v = sorted(v)
        return v[min(len(v) - 1, int(q * len(v)))] if v else float("nan")
    t = answer["timing"]
    print(f"{label}: {copies} copies, {info.triangle_count} triangles, upload {upload_s:.1f} s; first RAYCAST "
          f"{answer['s']:.2f} s (build_ms {t.build_ms:.0f}, compute_ms {t.compute_ms:.0f})")
    print(f"  after the upload: scene cpu {loaded_cpu_mib:.1f} MiB, server RSS {loaded_rss_mib:.0f} MiB")
    for name, v in times.items():
        print(f"  {name:10s} during it: {len(v):5d} calls, p50 {pct(v, 0.5):8.2f} ms, p99 {pct(v, 0.99):8.2f} ms, "
              f"max {max(v) if v else float('nan'):8.2f} ms")
    if scaling:
        def timed_map(method):
            r.method = method
            t0 = time.time()
            for _ in stub.HiddenSampleMap(r, timeout=600):
                pass
            return time.time() - t0
        raycast_warm = min(timed_map(pb.RAYCAST) for _ in range(3))
        raster_first = timed_map(pb.RASTER)
        raster_warm = min(timed_map(pb.RASTER) for _ in range(3))
        lv = pb.LightVisibilityRequest()
        lv.scene.name = "level"
        for (x, z) in ((0, 0), (ls, 0), (ls, ls), (0, ls)):
            v = lv.light.vertices.add()
            v.x, v.y, v.z = mx - ls / 2 + x, lo.y + 0.75 * ey, mz - ls / 2 + z
        lv.radiance = 1.0
        for i in range(100):
            p = lv.points.add()
            p.position.x = lo.x + 0.15 * ex + 0.7 * ex * ((i % 10) + 0.5) / 10
            p.position.y = 0.135
            p.position.z = mz - 0.2 * ez + 0.4 * ez * ((i // 10) + 0.5) / 10
            p.normal.y = 1.0
        t0 = time.time()
        stub.LightVisibility(lv, timeout=600)
        lv_first = time.time() - t0
        scene = stub.GetScene(pb.GetSceneRequest(name="level"), timeout=600)
        rss = 0
        for line in open(f"/proc/{server.pid}/status"):
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024
        mib = 1 << 20
        print(f"  RAYCAST warm {1e3 * raycast_warm:.0f} ms; RASTER first {raster_first:.2f} s, warm "
              f"{1e3 * raster_warm:.0f} ms; LightVisibility 100 points, first {lv_first:.2f} s")
        print(f"  after all three: scene cpu {scene.memory.cpu_bytes / mib:.1f} MiB "
              f"(estimated {scene.estimated_memory.cpu_bytes / mib:.1f}), gpu {scene.memory.gpu_bytes / mib:.1f} MiB; "
              f"{scene.unique_triangle_count} unique triangles, {scene.instance_count} instances; "
              f"server RSS {rss / mib:.0f} MiB")
finally:
    server.terminate()
    server.wait(timeout=60)
