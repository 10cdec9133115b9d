# Times a HiddenSampleMap stream: first message, first texel chunk, last
# message; and the server's peak and final RSS (VmHWM, VmRSS).
import os, sys, time, grpc
sys.path.insert(0, os.environ.get("VISQ_PY_STUBS", "/tmp/visq-stubs"))
from visq.v1 import visq_pb2 as pb, visq_pb2_grpc as rpc

address, pid, size, samples = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
def status(field):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(field): return int(line.split()[1]) // 1024
stub = rpc.VisibilityServiceStub(grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", 64 << 20)]))
r = pb.HiddenSampleMapRequest()
r.scene.name = "cornell_box_visq"
def patch(p, o, u, v):
    p.origin.x, p.origin.y, p.origin.z = o; p.edge_u.x, p.edge_u.y, p.edge_u.z = u; p.edge_v.x, p.edge_v.y, p.edge_v.z = v
patch(r.source, (-0.25, 1.99, -0.25), (0.5, 0, 0), (0, 0, 0.5))
patch(r.receiver, (-0.999, 0.001, -0.999), (1.998, 0, 0), (0, 0, 1.998))
r.samples.count = samples; r.width = r.height = size; r.want_bitmasks = True
start = time.time(); first = first_data = None; n = 0; words = 0
for m in stub.HiddenSampleMap(r, timeout=600):
    now = time.time() - start
    if first is None: first = now
    if first_data is None and (len(m.visible_fraction) or len(m.blocked_bits)): first_data = now
    n += 1; words += len(m.blocked_bits)
total = time.time() - start
print(f"{size}x{size} x {samples}: first message {first:.2f} s, first texels {first_data:.2f} s, last {total:.2f} s, "
      f"{n} messages, {words} words; server VmHWM {status('VmHWM')} MiB, VmRSS after {status('VmRSS')} MiB")
