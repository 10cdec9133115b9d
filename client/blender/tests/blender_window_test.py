# The visq add-on's modal operators in Blender with a window (under Xvfb),
# against a real visq-server: what background mode cannot show, Blender's
# window manager delivering the operator's timer and the Esc key to modal().
#   xvfb-run blender --factory-startup --enable-event-simulate \
#     --python blender_window_test.py -- --address HOST:PORT --package DIR_WITH_visq \
#     --addon client/blender/visq_blender --scratch DIR --token-file FILE --result FILE
# (tests/blender/run_blender_test.sh --window runs it). --enable-event-simulate
# makes Blender take only simulated input: the Esc below is
# Window.event_simulate, which goes through the same event queue and modal
# handlers as a key press.
#
# The script's top level runs before Blender's event loop starts, so the
# checks are steps of a state machine driven by bpy.app.timers; the last step
# writes PASS or the failure into --result and quits Blender, and the runner
# reads the file (a timer's exception does not end Blender with an error).
#   1. Bake obscurances invoked as the panel's button does (INVOKE_DEFAULT):
#      the operator returns RUNNING_MODAL, Blender delivers TIMER events to
#      modal() until the depth-peeling bake finishes, and the bake lands (the
#      session is saved, the W image exists, the progress shown never went
#      back).
#   2. A long bake invoked the same way; once it is baking, Esc (pressed and
#      released): modal() gets the key, the call is cancelled, the modal ends,
#      and the server counts the bake's call as ended in error within 30 s.
import math
import os
import shutil
import sys
import time
import traceback

import bpy

argv = sys.argv[sys.argv.index("--") + 1:]
args = dict(zip(argv[0::2], argv[1::2]))
ADDRESS, PACKAGE, ADDON, SCRATCH = args["--address"], args["--package"], args["--addon"], args["--scratch"]
TOKEN_FILE, RESULT = args["--token-file"], args["--result"]
started = time.monotonic()


def log(message):
    print(f"blender_window_test [{time.monotonic() - started:5.1f} s]: {message}", flush=True)


def check(condition, message):
    if not condition:
        raise AssertionError(message)


def finish(outcome):
    with open(RESULT, "w") as f:
        f.write(outcome + "\n")
    log(f"result: {outcome}")
    bpy.ops.wm.quit_blender()


# -- install and enable the add-on from a zip, as Preferences > Add-ons > Install does
archive = shutil.make_archive(os.path.join(SCRATCH, "visq_blender_window"), "zip", os.path.dirname(ADDON),
                              os.path.basename(ADDON))
check(bpy.ops.preferences.addon_install(filepath=archive) == {"FINISHED"}, "addon_install failed")
bpy.ops.preferences.addon_enable(module="visq_blender")
import visq_blender  # noqa: E402  (installed just now)

prefs = bpy.context.preferences.addons["visq_blender"].preferences
prefs.address, prefs.python_path, prefs.timeout, prefs.token_file = ADDRESS, PACKAGE, 10.0, TOKEN_FILE
visq = visq_blender.import_visq(bpy.context)
with visq.Client(ADDRESS, token_file=TOKEN_FILE) as c:
    c.wait_until_serving(60)
check(not bpy.app.background and len(bpy.context.window_manager.windows) > 0, "Blender has no window")

# -- a small scene: a floor, a cube on it, a lamp plane above
scene = bpy.context.scene
for obj in list(scene.objects):
    bpy.data.objects.remove(obj)
bpy.ops.mesh.primitive_grid_add(x_subdivisions=8, y_subdivisions=8, size=4.0)
bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.55), rotation=(0, 0, math.radians(30)))
bpy.ops.mesh.primitive_plane_add(size=0.6, location=(0.0, 0.0, 3.0), rotation=(math.pi, 0, 0))
bpy.ops.object.select_all(action="SELECT")  # the meshes to bake
settings = scene.visq
settings.scene_name = "blender_window_test"
log("add-on installed and enabled; server SERVING; scene built")

# -- what Blender delivers: every event modal() turns into a name, and the
# progress each TIMER shows
delivered = []
shown = []
step = visq_blender.TaskRunner.step


esc_at = []  # when modal() got Esc


def recording_step(self, context, event):
    delivered.append(event)
    if event == "ESC":
        esc_at.append(time.monotonic())
    result = step(self, context, event)
    if self.status and (not shown or shown[-1] != (self.percent, self.status)):
        shown.append((self.percent, self.status))
    return result


visq_blender.TaskRunner.step = recording_step


def invoke_bake():
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    with bpy.context.temp_override(window=window, screen=window.screen, area=area):
        return bpy.ops.visq.bake("INVOKE_DEFAULT")


def bake_calls():
    with visq.Client(ADDRESS, token_file=TOKEN_FILE) as c:
        methods = {m.method.rsplit("/", 1)[-1]: m for m in c.stats().methods}
    m = methods.get("ComputeObscurances")
    return (m.calls, m.errors) if m else (0, 0)


state = {"phase": "first bake", "since": time.monotonic()}


def tick():
    """One step of the test; the interval to the next, or None when done."""
    try:
        return advance()
    except Exception as error:  # the failure, with where it happened, into the result
        traceback.print_exc()
        finish(f"FAIL {state['phase']}: {error}")
        return None


def advance():
    phase = state["phase"]
    elapsed = time.monotonic() - state["since"]
    if phase == "first bake":
        # Long enough for several of the operator's 0.1 s timers even when
        # Blender's first redraws on llvmpipe hold its event loop for seconds
        # (16 directions baked in 1 s and Blender delivered one TIMER).
        settings.method, settings.directions = "depth-peeling", 128
        result = invoke_bake()
        check(result == {"RUNNING_MODAL"}, f"Bake invoked from the window returned {result}, not RUNNING_MODAL")
        check(visq_blender.TaskRunner.running is not None, "the invoked bake holds no call")
        state.update(phase="first bake running", since=time.monotonic())
        return 0.1
    if phase == "first bake running":
        if visq_blender.TaskRunner.running is not None:
            check(elapsed < 120, f"the modal bake did not end in 120 s; shown {shown[-3:]}")
            return 0.1
        timers = delivered.count("TIMER")
        percents = [p for p, _ in shown]
        log(f"modal bake ended after {timers} TIMER events from Blender, {len(shown)} states shown: "
            f"{[f'{p}%' for p in percents]}")
        check(timers >= 2, f"Blender delivered {timers} TIMER events to modal()")
        check(percents == sorted(percents), f"the progress bar went back: {shown}")
        check(visq_blender.load_session(scene)["scene"] == "blender_window_test", "the modal bake saved no session")
        check(bpy.data.images.get("visq_w_blender_window_test") is not None, "the modal bake made no W image")
        delivered.clear()
        shown.clear()
        settings.method, settings.resolution, settings.rays_per_patch = "raycast", 512, 4096
        state.update(phase="long bake", since=time.monotonic(), calls=bake_calls())
        result = invoke_bake()
        check(result == {"RUNNING_MODAL"}, f"the long bake returned {result}")
        return 0.1
    if phase == "long bake":
        runner = visq_blender.TaskRunner.running
        check(runner is not None, "the long bake ended before Esc")
        if not (runner.status or "").startswith("visq: baking"):
            check(elapsed < 30, f"the long bake showed no 'baking' status in 30 s: {shown[-3:]}")
            return 0.1
        window = bpy.context.window_manager.windows[0]
        state.update(phase="cancelling", since=time.monotonic(), runner=runner)
        window.event_simulate(type="ESC", value="PRESS")
        window.event_simulate(type="ESC", value="RELEASE")
        return 0.05
    if phase == "cancelling":
        if visq_blender.TaskRunner.running is not None:
            check(elapsed < 10, f"the modal did not end 10 s after Esc; delivered {delivered[-5:]}")
            return 0.05
        runner = state["runner"]
        check("ESC" in delivered, f"Blender did not deliver Esc to modal(): {sorted(set(delivered))}")
        check(type(runner.job.error).__name__ == "Cancelled", f"the bake ended with {runner.job.error!r}, not Cancelled")
        # Blender handles its event queue between redraws, which llvmpipe
        # makes slow on a loaded machine: the time the key took to reach
        # modal(), apart from the time the call took to stop after it.
        queued_s = esc_at[0] - state["since"]
        stopped_s = time.monotonic() - esc_at[0]
        log(f"Esc reached modal() {queued_s:.2f} s after it was sent; the modal ended {stopped_s:.2f} s after that "
            f"({delivered.count('TIMER')} TIMER events before)")
        check(stopped_s < 5.0, f"the bake took {stopped_s:.2f} s to stop after modal() got Esc")
        state.update(phase="server ends the call", since=time.monotonic(), modal_s=stopped_s, esc_at=esc_at[0])
        return 0.1
    if phase == "server ends the call":
        calls_before = state["calls"]
        if bake_calls()[1] <= calls_before[1]:
            check(elapsed < 30, "the server did not end the cancelled bake within 30 s")
            return 0.1
        log(f"ComputeObscurances calls/errors {calls_before} -> {bake_calls()}: the server's count showed it "
            f"{time.monotonic() - state['esc_at']:.2f} s after modal() got Esc")
        finish(f"PASS (the modal ended {state['modal_s']:.2f} s after it got Esc)")
        return None
    raise AssertionError(f"unknown phase {phase}")


bpy.app.timers.register(tick, first_interval=0.5)
