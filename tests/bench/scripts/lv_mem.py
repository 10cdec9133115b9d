# Identical LightVisibility batches on the bunny (0.15 m): 256 points on its
# upper surface, a 0.1 m square light 0.1 m above, no receiver_region.
import json, os, struct, sys, time, grpc
sys.path.insert(0, os.environ.get("VISQ_PY_STUBS", "/tmp/visq-stubs"))
from visq.v1 import visq_pb2 as pb, visq_pb2_grpc as rpc
address, pid, npoints = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
def rss():
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS"): return int(line.split()[1]) // 1024
g = json.load(open(os.environ.get("VISQ_SHARED_SCENES", "../shared/scenes") + "/bunny/bunny.gltf"))
acc = g["accessors"][g["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
view = g["bufferViews"][acc["bufferView"]]
data = open(os.environ.get("VISQ_SHARED_SCENES", "../shared/scenes") + "/bunny/bunny.bin", "rb").read()
off = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
verts = [struct.unpack_from("<3f", data, off + 12 * i) for i in range(acc["count"])]
top = sorted(verts, key=lambda v: -v[1])
step = max(1, len(top) // 4 // npoints)
points = top[: npoints * step : step][:npoints]
stub = rpc.VisibilityServiceStub(grpc.insecure_channel(address))
r = pb.LightVisibilityRequest(); r.scene.name = "bunny"
cx, cz, y = -0.017, -0.0015, 0.2873
for x, z in [(-0.05, -0.05), (0.05, -0.05), (0.05, 0.05), (-0.05, 0.05)]:  # the other winding
    v = r.light.vertices.add(); v.x, v.y, v.z = cx + x, y, cz + z
for p in points:
    q = r.points.add(); q.position.x, q.position.y, q.position.z = p[0], p[1] + 1e-3, p[2]
print(f"before: RSS {rss()} MiB")
for call in range(3):
    t = time.time(); resp = stub.LightVisibility(r, timeout=600); dt = time.time() - t
    s = resp.tree
    print(f"call {call+1}: {dt:.2f} s, RSS {rss()} MiB, trees' memory {s.memory_bytes/2**20:.1f} MiB, reused {s.reused}, "
          f"mean visible {sum(p.visible_fraction for p in resp.points)/len(resp.points):.4f}")
