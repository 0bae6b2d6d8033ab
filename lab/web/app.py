"""The browser lab: a viser view of a lab session (lab.session): the textured tissue, draggable instruments and bleed
points, sliders for every parameter, run controls and live stats.

Everything a browser sends is untrusted (viser checks no dropdown value against its options and no number for NaN):
callbacks hand each value to the session, which checks it against what it offered and refuses what it did not; a
refused value is put back in the browser and the reason shown. Callbacks of values the server set itself
(event.client is None) are ignored, so the view never echoes its own updates back as user input.

Threads: viser runs GUI callbacks concurrently in a pool; they only call the session's command methods. The
simulation loop (`LabApp.run`, on the main thread: Taichi compiles a rebuilt scene only on the thread that started
it) ticks the session and redraws what changed.
"""
from __future__ import annotations

import contextlib
import functools
import io
import math
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from lab.session import MAX_BLEED_POINTS, QUALITY, SPEED_RANGE, TEXTURE_INTERVAL_S, LabSession
from lab.web.section_view import section_image
from lab.web.stream import TextureStream
from sims.core.quoting import quote
from sims.scene import params
from sims.scene.checked import Refused, checked_flag, finite_vector
from sims.scene.instruments import local_frame

TYPING_QUIET_S = 2.0                # a slider's box is written back only after this long without a change from a browser
                                    # (with 1 s the typing test failed once in a fresh-clone CI run on a busy 2-core machine)
VIEW_INTERVAL_S = 1.0 / 30.0        # tool poses and markers sent at most this often
MAX_WAIT_S = 0.02                   # the simulation thread looks at the session at least this often
STATS_INTERVAL_S = 0.5
PLOT_SECONDS = 60.0
REBUILD_HINT = "Changing it restarts the scene (rebuilt with the new value)."
SECTION_LABEL = "depth against distance (mm)"  # the burn cross-section picture
TOOL_COLOR, HOT_COLOR = (170, 175, 185), (255, 140, 40)
ENVIRONMENT_INTENSITY = 0.4
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
MODEL_FOLDERS = (("", "Simulation"), ("tissue", "Tissue"), ("cautery", "Cautery"), ("bleeding", "Bleeding"), ("look", "Look"))


def slider_step(spec: params.ParamSpec) -> float:
    """1 for whole numbers, else a power of ten near a thousandth of the range (typed values are kept exactly)."""
    if spec.integer:
        return 1
    return 10.0 ** math.floor(math.log10((spec.max - spec.min) / 1000.0))


def slider_label(name: str, spec: params.ParamSpec) -> str:
    return f"{name} ({spec.unit})" if spec.unit else name


def instrument_mesh(shape: dict) -> trimesh.Trimesh:
    """The instrument's surface in its local frame (mm), for display."""
    kind = shape["type"]
    if kind == "ball":
        return trimesh.creation.icosphere(subdivisions=3, radius=shape["radius_mm"])
    if kind == "capsule":
        body = trimesh.creation.capsule(height=shape["length_mm"], radius=shape["radius_mm"])
        return body.apply_translation([0, 0, shape["length_mm"] / 2])
    if kind == "spatula":
        blade = trimesh.creation.box(extents=[shape["width_mm"], shape["thickness_mm"], shape["length_mm"]])
        return blade.apply_translation([0, 0, shape["length_mm"] / 2])
    return trimesh.load(str(shape["file"]), force="mesh")


def pose_wxyz(direction, roll_deg: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a tool pointing along direction, rolled roll_deg about it."""
    return np.array(_wxyz(tuple(float(v) for v in direction), float(roll_deg)))


@functools.lru_cache(maxsize=64)
def _wxyz(direction: tuple, roll_deg: float) -> tuple:
    """pose_wxyz by value: the view asks for every tool's every frame, and tools seldom turn."""
    return tuple(vtf.SO3.from_matrix(local_frame(np.array(direction), roll_deg).T).wxyz)


def placement_from_transform(wxyz, position) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, direction, roll_deg) of a gizmo pose (local z points back along the shaft); Refused unless finite."""
    position = finite_vector(position, 3, "gizmo position")
    quaternion = finite_vector(wxyz, 4, "gizmo rotation")
    if np.linalg.norm(quaternion) < 1e-6:
        raise Refused("gizmo rotation: not a rotation (zero quaternion)")
    world_from_local = vtf.SO3(quaternion / np.linalg.norm(quaternion)).as_matrix()
    direction = -world_from_local[:, 2]
    zero = local_frame(direction, 0.0)
    roll = math.degrees(math.atan2(world_from_local[:, 0] @ zero[1], world_from_local[:, 0] @ zero[0]))
    return position, direction, roll


def initial_view(surface) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at point), mm: the tissue seen from the front and above, as every browser starts."""
    lo, hi = surface.vertices_mm.min(axis=0), surface.vertices_mm.max(axis=0)
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    return centre + np.array([0.0, -0.45, 1.0]) * 0.95 * size, centre


def from_browser(event) -> bool:
    """True for a change a browser made; False for the callback viser runs when the server sets a value itself, and
    for a gizmo's drag start and end (they carry no new pose: only moving a gizmo takes a tool over)."""
    return getattr(event, "client", None) is not None and getattr(event, "phase", "update") == "update"


class UntilFailed(Exception):
    """The condition given to LabApp.run raised (its exception is the cause)."""


class LabApp:
    """A LabSession served to every connected browser. Build it and call `run` on the thread that started Taichi."""

    def __init__(self, scene_path, host: str = "127.0.0.1", port: int = 8080, arch: str = "auto", overrides=(),
                 wait_for_viewer: bool = False, allowed_origins=()):
        """overrides: `dotted.key=value` texts (as `--set`), applied on every rebuild of this scene. wait_for_viewer:
        the scene waits at t = 0 until a browser has drawn the whole tissue texture. allowed_origins: web origins besides the server's
        own that may connect (e.g. a reverse proxy's, "https://lab.example.org")."""
        from lab.web.origin import refuse_foreign_origins
        from lab.web.viser_threads import make_sends_thread_safe

        make_sends_thread_safe()  # the simulation thread sends tiles and poses
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: `serve` prints the URL once the scene is there
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.guard = refuse_foreign_origins(self.server, allowed_origins)  # its .messages counts what clients sent
        # that no widget of theirs sends (dropped before viser applies it)
        self.simple_lighting = False
        self.lighting_checkbox = None
        self.set_simple_lighting(False)
        self.stats = {"steps_per_s": 0.0, "updates_per_s": 0.0, "bytes_per_s": 0.0}
        self.history: list[tuple] = []
        self._notifications: dict = {}       # client id -> the build notification it shows
        self._notification_lock = threading.Lock()
        self._building: str | None = None    # the scene being built, while a build runs
        self.stop_event = threading.Event()
        self.stream = None
        self.session: LabSession | None = None  # a browser may connect while the first scene builds
        self.server.on_client_connect(self._client_connected)
        self.session = LabSession(scene_path, arch, overrides, wait_for_viewer=wait_for_viewer, on_build=self._on_build)
        self._show_scene()

    @property
    def scene(self):
        return self.session.scene

    # --- scene lifetime ---------------------------------------------------------------------
    def _on_build(self, stage: str, name: str, seconds: float, notes=()) -> None:
        """A notification in every browser while a scene builds (it takes seconds), then how long it took and the
        scene's notes. Runs on the simulation thread, also inside LabSession's constructor (no session yet)."""
        clients = self.server.get_clients()
        with self._notification_lock:
            self._building = name if stage == "start" else None
            self._notifications = {key: handle for key, handle in self._notifications.items() if key in clients}
            for client in clients.values():
                self._notify(client, (name, seconds, notes))

    def _notify(self, client, built: tuple | None = None) -> None:
        """This client's build notification as the build stands (the notification lock held)."""
        old = self._notifications.pop(client.client_id, None)
        if old is not None:
            old.remove()
        if self._building is not None:
            self._notifications[client.client_id] = client.add_notification(
                "Building the scene", f"{self._building}: meshes, texel maps and kernels...", loading=True, with_close_button=False)
        elif built is not None:  # (scene name, build seconds, its notes)
            name, seconds, notes = built
            note = f". Note: {'; '.join(notes)}" if notes else ""
            self._notifications[client.client_id] = client.add_notification(
                "Scene ready", f"{name} built in {seconds:.1f} s{note}", auto_close_seconds=12.0 if notes else 4.0)

    def _show_scene(self) -> None:
        """Stream, tools, markers and GUI for the session's scene (after every build)."""
        if self.stream is not None:
            self.stream.close()
        self.server.gui.reset()
        self.server.scene.reset()
        self.server.scene.set_up_direction("+z")
        self.server.scene.remove_click_callback("all")
        self.server.scene.on_click()(self._scene_clicked)  # always on: a click is only used while a point is armed
        self.shown_builds = self.session.builds
        self.stream = TextureStream(self.server, self.scene.surface)
        self._stream_look()
        self.history.clear()
        self._shown: dict = {}          # what the view last showed, by key: only changes are sent
        self.tool_views: dict = {}      # tool name -> its handles
        self.point_views: dict = {}     # bleed point name -> (marker gizmo, folder)
        self.sliders: dict = {}         # parameter key (and "speed") -> (slider handle, () -> the value in use)
        self._typed_at: dict = {}       # slider key -> when a browser last changed it (time.monotonic s)
        self.armed_click = False
        for client in self.server.get_clients().values():
            self._frame_camera(client)
        self._build_gui()

    def _stream_look(self) -> dict:
        """Compose the look where the stream is about to read it and stream its base colour, normal and roughness maps
        (only the tiles that changed are compared and encoded; lab.web.stream.TextureStream.plan)."""
        return self.stream.show(self.scene)

    def _client_connected(self, client) -> None:
        """A browser joined (a viser thread): during a build it sees the build notification, and the scene once it is
        built (`_show_scene` frames every browser's camera); the session starts once a browser drew the tissue."""
        with self._notification_lock:
            if self._building is not None or self.session is None:
                self._notify(client)
                return
        self._frame_camera(client)

    def _frame_camera(self, client) -> None:
        position, look_at = initial_view(self.scene.surface)
        client.camera.position = tuple(float(v) for v in position)
        client.camera.look_at = tuple(float(v) for v in look_at)

    # --- GUI --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, session = self.server.gui, self.session
        with gui.add_folder("Run"):
            self.pause_button = gui.add_button("Pause" if session.running else "Resume")
            step = gui.add_button("Single step")
            reset = gui.add_button("Reset", hint="back to t = 0 with the current settings; every tool back to its script")
            self.replay_button = gui.add_button("Replay the script", hint="the scripted drill has ended: play it again from t = 0",
                                                visible=False)
            reload = gui.add_button("Back to the scene file", hint="forgets every change but the quality preset; " + REBUILD_HINT)
            speed = gui.add_slider("Speed (x real time)", *SPEED_RANGE, 0.1, session.speed)
            chooser = gui.add_dropdown("Scene", session.scene_choices(), initial_value=session.scene_name_of(session.scene_path),
                                       hint="keeps the quality preset, forgets the other changes")
            lighting = gui.add_checkbox("Simple lighting", self.simple_lighting,
                                        hint="no environment light, no shadows: draws several times faster in a browser without a GPU")
            quality = gui.add_dropdown("Quality", tuple(QUALITY), initial_value=session.quality,
                                       hint="fast: 256² texels, 1 fluid substep; balanced: 512², 2; accurate: 1024², 4; "
                                            "scene file: as the scene says. " + REBUILD_HINT)
        self.lighting_checkbox, self.scene_dropdown, self.quality_dropdown = lighting, chooser, quality
        self.pause_button.on_click(lambda event: self._act(event, lambda: self.set_running(not session.running)))
        step.on_click(lambda event: self._act(event, session.single_step))
        reset.on_click(lambda event: self._act(event, session.reset))
        self.replay_button.on_click(lambda event: self._act(event, session.reset))
        reload.on_click(lambda event: self._act(event, session.back_to_scene_file))
        speed.on_update(lambda event: self._typed(event, "speed", lambda: session.set_speed(speed.value)))
        self.sliders["speed"] = (speed, lambda: session.speed)
        lighting.on_update(lambda event: self._act(event, lambda: self.set_simple_lighting(checked_flag(lighting.value, "simple lighting"))))
        chooser.on_update(lambda event: self._act(event, lambda: self._choose(chooser, session.switch_scene),
                                                  put_back=(chooser, lambda: session.scene_name_of(session.scene_path))))
        quality.on_update(lambda event: self._act(event, lambda: self._choose(quality, session.set_quality),
                                                  put_back=(quality, lambda: session.quality)))

        parameters = session.parameters()
        for group, label in MODEL_FOLDERS:
            keys = [key for key in parameters if (key.partition(".")[0] == group and "." in key) or (group == "" and "." not in key)]
            if not keys:
                continue
            with gui.add_folder(label, expand_by_default=False):
                for key in keys:
                    self._slider(key, slider_label(key.rpartition(".")[2], parameters[key].spec))
                defaults = gui.add_button(f"Reset {label.lower()} to defaults")
                defaults.on_click(lambda event, g=group: self._act(event, lambda: session.reset_parameters(g)))
        self._build_instruments()
        if self.scene.bleeding is not None:
            with gui.add_folder("Bleed points") as folder:
                add = gui.add_button("Add bleed point (then click the tissue)",
                                     hint=f"the next click on the tissue adds one point; at most {MAX_BLEED_POINTS} points in a scene")
                remove = gui.add_button("Remove last bleed point")
            self.bleed_folder = folder
            add.on_click(lambda event: self._act(event, lambda: setattr(self, "armed_click", True)))
            remove.on_click(lambda event: self._act(event, session.remove_bleed_point))
        self.section_image, self.section_time = None, None
        if self.scene.cautery is not None:
            with gui.add_folder("Burn cross-section"):
                self.section_text = gui.add_markdown("energize a tool: the cut across its stroke shows how deep the burn goes")
                self.section_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), format="png", label=SECTION_LABEL)
        with gui.add_folder("Stats"):
            self.stats_text = gui.add_markdown("starting...")
            series = {0: viser.uplot.Series(label="t (s)"), 1: viser.uplot.Series(label="max T (C)", stroke="orange"),
                      2: viser.uplot.Series(label="blood (mm2)", stroke="red")}
            self.plot_columns = [0] + ([1] if self.scene.cautery is not None else []) + ([2] if self.scene.bleeding is not None else [])
            self.plot = gui.add_uplot(
                data=tuple(np.zeros(1) for _ in self.plot_columns), series=tuple(series[column] for column in self.plot_columns),
                title="over time", aspect=2.0, scales={"x": {"time": False}},
            )
        self._sync_view()

    def _act(self, event, action, put_back=None) -> None:
        """Run a browser's action (GUI thread); a Refused one is shown, and put_back=(handle, value()) shows the value
        in use again. Values the server set itself are ignored."""
        if not from_browser(event):
            return
        try:
            action()
        except Refused as exc:
            self.session.notice = f"refused: {exc}"
            if put_back is not None:
                handle, value = put_back
                handle.value = value()

    @staticmethod
    def _choose(dropdown, choose) -> None:
        """A dropdown value reaches the session only when it is one of the dropdown's options."""
        if dropdown.value not in dropdown.options:
            raise Refused(f"{dropdown.label}: {quote(dropdown.value)} is not one of the options")
        choose(dropdown.value)

    def _slider(self, key: str, label: str, hint_extra: str = ""):
        """A slider for a session parameter; a change is checked by the session (NaN refused, clamped into range) and
        the value in use is shown again when it differs."""
        parameter = self.session.parameters()[key]
        spec = parameter.spec
        hint = spec.help + ("" if parameter.live else f". {REBUILD_HINT}") + hint_extra
        handle = self.server.gui.add_slider(label, spec.min, spec.max, slider_step(spec), self.session.parameter_value(key), hint=hint)

        handle.on_update(lambda event: self._typed(event, key, lambda: self.session.set_parameter(key, handle.value)))
        self.sliders[key] = (handle, lambda: self.session.parameter_value(key))
        return handle

    def _typed(self, event, key: str, action) -> None:
        """A browser changed a slider (GUI thread; its number box sends every keystroke): the change goes to the session
        at once, the value in use goes back on the slider only once the typing stopped (_sync_sliders)."""
        if not from_browser(event):
            return
        self._typed_at[key] = time.monotonic()
        try:
            action()
        except Refused as exc:
            self.session.notice = f"refused: {exc}"

    def _build_instruments(self) -> None:
        gui, session = self.server.gui, self.session
        parameters = session.parameters()
        with gui.add_folder("Instruments"):
            self.held_text = gui.add_markdown("")
            for tool in self.scene.instruments:
                with gui.add_folder(tool.name):
                    view = {"tool": tool}
                    view["distance"] = gui.add_markdown("")
                    view["switch"] = gui.add_checkbox(f"{tool.name}: {'suction on' if tool.suction else 'energized'}",
                                                      tool.pose_at(self.scene.time_s).energized)
                    view["rest"] = gui.add_checkbox(f"{tool.name}: touch the tissue", tool.name in session.resting,
                                                    hint="a tool moved by hand is lowered along its axis onto the tissue under it and "
                                                         "stays in contact while dragged")
                    view["rotate"] = gui.add_checkbox(f"{tool.name}: allow rotation", False, hint="show the gizmo's rotation rings")
                    view["release"] = gui.add_button(f"{tool.name}: back to the script", hint="the tool follows its scripted path again",
                                                     visible=False)
                    for key in [key for key in parameters if key.startswith(f"instruments.{tool.name}.")]:
                        name = key.removeprefix(f"instruments.{tool.name}.").replace(".", " ")
                        self._slider(key, f"{tool.name}: {slider_label(name, parameters[key].spec)}")
                name = tool.name
                view["switch"].on_update(lambda event, n=name, h=view["switch"]: self._act(
                    event, lambda: session.set_energized(n, h.value)))
                view["rest"].on_update(lambda event, n=name, h=view["rest"]: self._act(event, lambda: session.set_resting(n, h.value)))
                view["rotate"].on_update(lambda event, n=name: self._act(event, lambda: self._rotation_toggled(n)))
                view["release"].on_click(lambda event, n=name: self._act(event, lambda: session.release(n)))
                self.tool_views[name] = view
                self._place_gizmo(name)
                body = instrument_mesh(tool.shape)
                view["body"] = self.server.scene.add_mesh_simple(f"/tool_bodies/{name}", body.vertices.astype(np.float32),
                                                                 body.faces.astype(np.uint32), color=TOOL_COLOR)

    def _rotation_toggled(self, name: str) -> None:
        """"allow rotation" ticked or cleared: the gizmo is placed again, with or without its rotation rings."""
        checkbox = self.tool_views[name]["rotate"]
        try:
            checked_flag(checkbox.value, f"{name}: allow rotation")
        except Refused:
            checkbox.value = False  # in every browser, with the gizmo as a cleared box has it
            raise
        finally:
            self._place_gizmo(name)

    def _place_gizmo(self, name: str) -> None:
        """The tool's gizmo (translation handles; rotation rings too when asked), at the tool's pose."""
        view = self.tool_views[name]
        if "gizmo" in view:
            view["gizmo"].remove()
        pose = view["tool"].pose_at(self.scene.time_s)
        gizmo = self.server.scene.add_transform_controls(f"/tools/{name}", scale=8.0, position=tuple(pose.position_mm),
                                                         wxyz=self._gizmo_wxyz(name, pose), disable_rotations=not view["rotate"].value)
        view["gizmo"] = gizmo
        gizmo.on_update(lambda event, n=name, g=gizmo: self._act(event, lambda: self._gizmo_moved(n, g)))

    def _gizmo_wxyz(self, name: str, pose) -> tuple:
        """The gizmo turns with the tool while rotation is allowed; otherwise its handles point along x, y and z."""
        if self.tool_views[name]["rotate"].value:
            return tuple(float(v) for v in pose_wxyz(pose.direction, pose.roll_deg))
        return (1.0, 0.0, 0.0, 0.0)

    def _gizmo_moved(self, name: str, gizmo) -> None:
        """A hand moved the tool's gizmo: the tool is the hand's from now on. A pose that is not finite (or far off) is
        refused and the gizmo goes back to the tool."""
        try:
            position, direction, roll = placement_from_transform(gizmo.wxyz, gizmo.position)
            rotating = self.tool_views[name]["rotate"].value
            self.session.take_over(name, position, direction if rotating else None, roll if rotating else None)
        except Refused:
            pose = self.tool_views[name]["tool"].pose_at(self.scene.time_s)
            gizmo.position, gizmo.wxyz = tuple(pose.position_mm), self._gizmo_wxyz(name, pose)
            raise

    def _scene_clicked(self, event) -> None:
        """A click in the scene: adds a bleed point where it meets the tissue, once after "Add bleed point"."""
        if not self.armed_click or self.scene.bleeding is None:
            return
        try:
            if self.session.add_bleed_point_at_click(event.ray_origin, event.ray_direction):
                self.armed_click = False
        except Refused as exc:
            self.session.notice = f"refused: {exc}"

    def set_simple_lighting(self, simple: bool) -> None:
        """Environment light and shadows (the default), or the default lights alone (any thread: viser calls only)."""
        self.simple_lighting = simple
        if simple:
            self.server.scene.configure_environment_map(None)
        else:  # viser's environment light at full strength washes the liver out to pale pink
            self.server.scene.configure_environment_map("warehouse", environment_intensity=ENVIRONMENT_INTENSITY)
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=not simple)
        if self.lighting_checkbox is not None:
            self.lighting_checkbox.value = simple

    def set_running(self, running: bool) -> None:
        """Pause or resume (any thread)."""
        self.session.set_running(running)
        self.pause_button.label = "Pause" if self.session.running else "Resume"

    # --- keeping the view in step with the session (simulation thread) ------------------------
    def _show(self, key, value, apply) -> None:
        """apply(value) when value differs from what the view last showed under key."""
        if self._shown.get(key, object()) != value:
            self._shown[key] = value
            apply(value)

    def _sync_view(self) -> None:
        """Tools, markers and buttons as the session has them now; only what changed is sent."""
        scene, session = self.scene, self.session
        held = scene.held_tools()
        for name, view in self.tool_views.items():
            tool = view["tool"]
            pose = tool.pose_at(scene.time_s)
            wxyz = tuple(float(v) for v in pose_wxyz(pose.direction, pose.roll_deg))
            placed = (tuple(float(v) for v in pose.position_mm), wxyz)

            def move_body(placed, body=view["body"]):
                body.position, body.wxyz = placed

            self._show(("body", name), placed, move_body)
            if tool.hand is None:  # the script moves the gizmo; a hand's gizmo stays where the hand left it

                def move_gizmo(placed, gizmo=view["gizmo"]):
                    gizmo.position, gizmo.wxyz = placed

                self._show(("gizmo", name), (placed[0], self._gizmo_wxyz(name, pose)), move_gizmo)
            else:
                self._shown.pop(("gizmo", name), None)
            self._show(("switch", name), pose.energized, lambda on, h=view["switch"]: setattr(h, "value", on))
            hot = pose.energized and tool.suction is None
            self._show(("hot", name), hot, lambda hot, b=view["body"]: setattr(b, "color", HOT_COLOR if hot else TOOL_COLOR))
            self._show(("held", name), name in held, lambda on, b=view["release"]: setattr(b, "visible", on))
        self._show("held", tuple(held), lambda names: setattr(self.held_text, "content",
                                                             f"held by hand: {', '.join(names)}" if names else "all tools follow the script"))
        self._show("replay", session.script_ended, lambda ended: setattr(self.replay_button, "visible", ended))
        self._show("running", session.running, lambda running: setattr(self.pause_button, "label", "Pause" if running else "Resume"))
        if scene.bleeding is not None:
            self._sync_points()

    def _sync_sliders(self) -> None:
        """Every slider shows the value in use (in every browser): a value clamped, refused or changed by the session
        itself (reset to defaults) is put back, once nobody has typed into that slider for TYPING_QUIET_S (a box
        rewritten between keystrokes garbles what is being typed: "60" became 20)."""
        now = time.monotonic()
        for key, (handle, in_use) in list(self.sliders.items()):
            if now - self._typed_at.get(key, -math.inf) < TYPING_QUIET_S:
                continue
            value = in_use()
            if handle.value != value:
                handle.value = value

    def _sync_points(self) -> None:
        """A red marker with a gizmo and a folder of sliders for every bleed point; gone when the point is."""
        points = {point.name: point for point in self.scene.bleed_points}
        for name in [name for name in self.point_views if name not in points]:
            marker, folder = self.point_views.pop(name)
            marker.remove()
            folder.remove()
            for key in [key for key in self.sliders if key.startswith(f"bleed_points.{name}.")]:
                del self.sliders[key]
        parameters = self.session.parameters()
        for name, point in points.items():
            position = tuple(float(v) for v in point.position_at(self.scene.time_s))
            if name not in self.point_views:
                marker = self.server.scene.add_transform_controls(f"/bleed/{name}", scale=5.0, position=position, disable_rotations=True)
                self.server.scene.add_icosphere(f"/bleed/{name}/dot", radius=0.8, color=(150, 0, 0))
                marker.on_update(lambda event, n=name, m=marker: self._act(event, lambda: self._marker_moved(n, m)))
                with self.bleed_folder, self.server.gui.add_folder(name) as folder:
                    for key in [key for key in parameters if key.startswith(f"bleed_points.{name}.")]:
                        self._slider(key, f"{name}: {slider_label(key.rpartition('.')[2], parameters[key].spec)}")
                self.point_views[name] = (marker, folder)
            self._show(("point", name), position, lambda position, m=self.point_views[name][0]: setattr(m, "position", position))

    def _marker_moved(self, name: str, marker) -> None:
        """A hand moved a bleed point's marker: the point moves there, or the marker goes back to it in every browser."""
        try:
            self.session.move_bleed_point(name, marker.position)
        except Refused:
            marker.position = tuple(float(v) for v in self.scene.bleed_point(name).position_at(self.scene.time_s))
            raise

    def _show_stats(self) -> None:
        scene, session = self.scene, self.session
        metrics = scene.metrics()
        state = "waiting for a browser to draw the tissue" if session.waiting_for_viewer else ("running" if session.running else "paused")
        lines = [
            f"t = {scene.time_s:.2f} s, {state}, arch {scene.arch}",
            f"simulation: {self.stats['steps_per_s']:.0f} steps/s",
            f"texture: {self.stats['updates_per_s']:.1f} updates/s, {self.stats['bytes_per_s'] / 1024:.0f} kB/s",
            f"scene built in {session.build_seconds[-1][1]:.1f} s",
        ]
        max_t, blood = 0.0, 0.0
        if "cautery" in metrics:
            c = metrics["cautery"]
            max_t = c["max_temperature_c"]
            lines.append(f"max temperature: {max_t:.0f} C, coagulated: {c['coagulated_area_mm2']:.1f} mm2, charred: {c['charred_area_mm2']:.1f} mm2")
            lines.append(f"burn depth: {c['coagulation_depth_mm']:.2f} mm at the deepest, coagulated volume {c['coagulated_volume_mm3']:.1f} mm3 "
                         f"({c['layers']} layers, {100 * c['awake_tiles']:.0f} % of the tiles stepped)")
            self._show_section()
        if "bleeding" in metrics:
            b = metrics["bleeding"]
            blood = b["blood_area_mm2"]
            lines.append(f"blood ({b['method'].replace('_', ' ')}): {b['volume_ml']:.3f} ml on {blood:.0f} mm2, deepest {b['max_thickness_mm']:.2f} mm; "
                         f"suctioned {b['suctioned_ml']:.3f} ml, off the edge {b['left_surface_ml']:.3f} ml")
            if b["method"] == "particles":
                lines.append(f"particles alive: {b['alive']} / {b['capacity']}")
            lines.append(f"bleed points: {len(scene.bleed_points)} of {MAX_BLEED_POINTS} at most"
                         + (" (click the tissue to add one)" if self.armed_click else ""))
            if b.get("dropped_pool_full"):
                lines.append(f"**pool full: {b['dropped_pool_full']} particles not spawned (the height-field method has no pool)**")
        if session.script_ended:
            lines.append("the scripted drill has ended: **Replay the script** plays it again")
        if session.rebuild_pending:
            lines.append("**restarting the scene with the new value...**")
        if session.notice:
            lines.append(f"**{session.notice}**")
        dropped = self.guard.messages.dropped
        if dropped:
            kinds = ", ".join(f"{kind} {count}" for kind, count in dropped.most_common(3))
            lines.append(f"client messages refused: {sum(dropped.values())} ({kinds})")
        self.stats_text.content = "  \n".join(lines)
        for name, view in self.tool_views.items():
            clearance = scene.tool_clearance_mm(name)
            missed = "no tissue below it" if scene.instrument(name).flat else "no tissue along its axis"
            text = (missed if clearance is None else
                    f"{clearance:.1f} mm above the tissue" if clearance > 0.05 else f"touching the tissue, {-clearance:.2f} mm in")
            self._show(("distance", name), text, lambda text, h=view["distance"]: setattr(h, "content", text))
        self._sync_sliders()
        self.history.append((scene.time_s, max_t, blood))
        self.history = [row for row in self.history if scene.time_s - PLOT_SECONDS <= row[0] <= scene.time_s]  # (after a reset too)
        self.plot.data = tuple(np.array([row[column] for row in self.history], np.float64) for column in self.plot_columns)

    def _show_section(self) -> None:
        """The cross-section under the most recently energized tool (sims.heat.section), drawn by lab.web.section_view."""
        if self.section_image is None or self.section_time == self.scene.time_s:
            return  # nothing new to show (a paused lab sends no pictures)
        section = self.scene.burn_section()
        if section is None:
            return
        self.section_time = self.scene.time_s
        self.section_image.image = section_image(section)
        self.section_text.content = (f"across the stroke of **{section.tool}** (depth against distance along the surface, "
                                     f"mm; white: coagulated, Omega >= 1)")

    # --- simulation thread ------------------------------------------------------------------
    def run(self, until=None, timeout_s: float | None = None) -> bool:
        """Run the simulation on this thread (the one that started Taichi) until close(); with `until`, only until
        until() is true (checked about 20 times a second on this thread, so it may read the scene) or timeout_s
        passed. Returns whether until() became true. An error in the simulation pauses it and is shown in the stats
        instead of stopping the lab; an error raised by until() is raised here."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.stop_event.is_set():
            try:
                return self._run(until, deadline)
            except UntilFailed as exc:
                raise exc.__cause__ from None
            except Exception as exc:  # keep serving the browsers; the user can reset or switch scenes
                traceback.print_exc()
                self.session.set_running(False)
                self.session.notice = f"simulation stopped: {type(exc).__name__}: {exc} (press Resume or Reset)"
                try:  # the view may be what failed (a handle removed mid-rebuild): the next _show_scene makes new ones
                    self.pause_button.label = "Resume"
                    self.stats_text.content = self.session.notice
                except Exception:
                    pass
                time.sleep(0.5)
        return False

    def _run(self, until, deadline) -> bool:
        last_view = last_texture = last_stats = last_check = time.perf_counter()
        steps = updates = sent = 0
        while not self.stop_event.is_set():
            now = time.perf_counter()
            if now - last_check >= 0.05:
                last_check = now
                try:
                    if until is not None and until():
                        return True
                except Exception as exc:
                    raise UntilFailed() from exc
                if deadline is not None and time.monotonic() > deadline:
                    return False
            taken = self.session.tick()
            steps += taken
            if self.session.builds != self.shown_builds:
                self._show_scene()
            now = time.perf_counter()
            if not taken:  # wait for the next step, view or texture update, whichever is due first (at most MAX_WAIT_S)
                wait = min(self.session.seconds_to_next_step(), last_view + VIEW_INTERVAL_S - now,
                           last_texture + TEXTURE_INTERVAL_S - now, MAX_WAIT_S)
                if wait > 0.0:
                    time.sleep(wait)
                    now = time.perf_counter()
            if now - last_view >= VIEW_INTERVAL_S:
                self._sync_view()
                last_view = now
            if now - last_texture >= TEXTURE_INTERVAL_S:
                if self.session.broken is None:  # a non-finite field is named in the stats, not drawn
                    result = self._stream_look()
                    updates += result["tiles_sent"] > 0  # updates that sent something
                    sent += result["bytes"]
                if self.session.waiting_for_viewer and self.stream.drawn_whole():  # the clock starts once the
                    self.session.viewer_joined()  # tissue is on a screen: a slow browser sees the drill from t = 0
                last_texture = now
            if now - last_stats >= STATS_INTERVAL_S:
                span = now - last_stats
                self.stats = {"steps_per_s": steps / span, "updates_per_s": updates / span, "bytes_per_s": sent / span}
                steps = updates = sent = 0
                last_stats = now
                self._show_stats()
        return False

    def close(self) -> None:
        self.stop_event.set()
        self.stream.close()
        self.server.stop()


def serve(scene_path, host: str, port: int, arch: str, overrides=(), allowed_origins=()) -> None:
    """Start the lab, say where it is (once it serves the scene), and block until Ctrl-C. The scene waits at t = 0 until
    a browser has drawn the tissue."""
    app = LabApp(scene_path, host, port, arch, overrides=overrides, wait_for_viewer=True, allowed_origins=allowed_origins)
    bound = app.server.get_port()
    if bound != port:
        print(f"warning: port {port} is busy; the lab serves on port {bound} instead", file=sys.stderr, flush=True)
    if host not in LOOPBACK_HOSTS:
        print(f"warning: --host {host} serves the lab to every machine that can reach this one, with no password; for a "
              "remote demo put a reverse proxy with authentication in front of it (see docs/guide/lab.md, 'A remote demo')", file=sys.stderr, flush=True)
    shown = f"[{host}]" if ":" in host else host
    print(f"tissue lab: http://{shown}:{bound}  ({Path(scene_path).name}, {app.scene.arch}, built in "
          f"{app.session.build_seconds[-1][1]:.1f} s); waits at t = 0 until a browser shows it; Ctrl-C stops", flush=True)
    try:
        app.run()  # Taichi stays on the main thread, where the scene was built
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
