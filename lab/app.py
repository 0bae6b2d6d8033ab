"""The browser lab: a viser server showing the textured tissue, draggable instruments and bleed
points, sliders for every parameter, run controls and live stats.

Threads: viser runs GUI callbacks concurrently in a pool; they never touch the simulation. They put
small functions on `commands`, and the one simulation loop (`LabApp.run`, on the main thread: Taichi
compiles a rebuilt scene only on the thread that started it) runs them between steps.

Parameters the models read every step change live. The others (texture size, particle pool,
instrument shapes, quality preset) are kept as scene overrides (the `--set` syntax of sims.config)
that every rebuild applies; a burst of changes (a slider being dragged) waits for REBUILD_DELAY_S of
quiet and then rebuilds once. Live changes are kept as overrides too, so a rebuild keeps them.
"""
import json
import math
import queue
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from lab.stream import TextureStream
from sims import backend, params
from sims.config import REPO_ROOT, ConfigError, load_scene_config, parse_override
from sims.instruments import Instrument, Pose, local_frame
from sims.scene import Scene

FRAME_INTERVAL_S = 1.0 / 30.0       # texture updates at most this often
STATS_INTERVAL_S = 0.5
PLOT_SECONDS = 60.0
REBUILD_DELAY_S = 0.5               # a rebuild waits until its sliders have been still this long (one rebuild per drag)
QUALITY = {  # name: scene overrides (texture texels, fluid substeps)
    "scene file": {},
    "fast": {"texture_size": 256, "bleeding.substeps": 1},
    "balanced": {"texture_size": 512, "bleeding.substeps": 2},
    "accurate": {"texture_size": 1024, "bleeding.substeps": 4},
}
QUALITY_KEYS = ("texture_size", "bleeding.substeps")
# Slider folders: (config group, "" for top-level keys; folder; specs; model it needs; names that need a rebuild).
# duration_s is left out: it only ends headless runs.
SLIDER_GROUPS = (
    ("", "Simulation", {name: spec for name, spec in params.SIMULATION.items() if name != "duration_s"}, None, {"texture_size"}),
    ("tissue", "Tissue", params.TISSUE, "cautery", set()),
    ("cautery", "Cautery", params.CAUTERY, "cautery", set()),
    ("bleeding", "Bleeding", params.BLEEDING, "bleeding", {"capacity"}),
)
SHAPE_SLIDERS = {"ball": ("radius_mm",), "capsule": ("radius_mm", "length_mm"), "spatula": ("width_mm", "thickness_mm", "length_mm"), "mesh": ("sdf_resolution",)}
REBUILD_HINT = "Changing it restarts the scene (rebuilt with the new value)."
SPARE_SUCTION = {"radius_mm": 4.0, "rate_ml_s": 0.2}
TOOL_COLOR, HOT_COLOR = (170, 175, 185), (255, 140, 40)
ENVIRONMENT_INTENSITY = 0.4


def bounded(handle, low: float, high: float) -> float:
    """The handle's value kept inside [low, high]; a value typed outside is put back in the browser."""
    value = min(max(float(handle.value), low), high)
    if value != handle.value:
        handle.value = value
    return value


def slider_step(spec: params.ParamSpec) -> float:
    """1 for whole numbers, else a power of ten near a thousandth of the range (typed values are kept exactly)."""
    if spec.integer:
        return 1
    return 10.0 ** math.floor(math.log10((spec.max - spec.min) / 1000.0))


def slider_label(name: str, spec: params.ParamSpec) -> str:
    return f"{name} ({spec.unit})" if spec.unit else name


def yaml_value(value) -> str:
    """`value` as YAML flow text that reads back as the same value (YAML 1.1 reads 1e-05 as text: 1.0e-05)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(key))}: {yaml_value(item)}" for key, item in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(item) for item in value) + "]"
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a finite number: {value}")
        mantissa, mark, exponent = repr(value).partition("e")
        if "." not in mantissa:
            mantissa += ".0"
        return mantissa + mark + (exponent if not exponent or exponent[0] in "+-" else "+" + exponent)
    if isinstance(value, Path):
        value = str(value)
    return json.dumps(value)


def override_texts(overrides: dict) -> list[str]:
    """{dotted.key: value} -> ["dotted.key=value", ...] for sims.config.load_scene_config."""
    return [f"{key}={yaml_value(value)}" for key, value in overrides.items()]


def scene_files() -> list[str]:
    return sorted(str(path.relative_to(REPO_ROOT)) for path in (REPO_ROOT / "scenes").glob("*.yaml"))


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


def pose_wxyz(pose: Pose) -> np.ndarray:
    return vtf.SO3.from_matrix(local_frame(pose.direction, pose.roll_deg).T).wxyz


def pose_from_transform(wxyz, position, old: Pose) -> Pose:
    """Direction and roll from a gizmo rotation (local z points back along the shaft)."""
    world_from_local = vtf.SO3(np.asarray(wxyz)).as_matrix()
    direction = -world_from_local[:, 2]
    zero = local_frame(direction, 0.0)
    roll = math.degrees(math.atan2(world_from_local[:, 0] @ zero[1], world_from_local[:, 0] @ zero[0]))
    return Pose(np.asarray(position, np.float64), direction, roll, old.energized, old.tip_temperature_c)


class UntilFailed(Exception):
    """The condition given to LabApp.run raised (its exception is the cause)."""


class LabApp:
    """One scene served to every connected browser. Build it and call `run` on the thread that started Taichi."""

    def __init__(self, scene_path, host: str = "127.0.0.1", port: int = 8080, arch: str = "auto", overrides=()):
        """overrides: `dotted.key=value` texts (as `--set`), applied on every rebuild of this scene."""
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.simple_lighting = False
        self.set_simple_lighting(False)
        self.arch = arch
        self.commands: queue.Queue = queue.Queue()
        self.running, self.speed, self.single_steps = True, 1.0, 0
        self.quality = "scene file"
        self.overrides: dict = {}            # dotted scene key -> value, applied on every (re)build
        for text in overrides:
            parts, value = parse_override(text)
            self.overrides[".".join(parts)] = value
        self.added_points: list[dict] = []   # items of bleed points added in the browser (re-added after a rebuild)
        self.removed_points: set[str] = set()  # scene bleed points removed in the browser
        self.spare_suction = dict(SPARE_SUCTION)
        self.builds = 0                      # scene builds so far (1 after start-up)
        self.notice = ""
        self._rebuild_at: float | None = None
        self.stop_event = threading.Event()
        self.stats = {"steps_per_s": 0.0, "updates_per_s": 0.0, "bytes_per_s": 0.0}
        self.history: list[tuple] = []
        self.scene = None
        self.server.on_client_connect(self._frame_camera)
        self._load(Path(scene_path))

    # --- scene lifetime ---------------------------------------------------------------------
    def _load(self, path: Path) -> None:
        """Build the scene with the overrides, the texture stream and the GUI (simulation thread or start-up only).
        A rebuild the overrides make invalid keeps the scene it had and says why; a scene file that fails to build
        (a mesh that does not load) brings the previous scene back, restarted, and says why.

        Every build after the first starts a fresh Taichi runtime: Taichi frees no field of a dropped scene and
        allows 512 field trees per runtime (a hemostasis build makes 14), and a fresh runtime builds faster too."""
        first_build = self.scene is None
        try:
            config = load_scene_config(path, override_texts(self.overrides))
        except ConfigError as exc:
            if first_build:
                raise
            self.overrides = dict(self._built_with)
            self.notice = f"**not rebuilt: {exc}**"
            return
        notice = ""
        if not first_build:
            self.stream.close()
            self.scene = None
            backend.shutdown()
        try:
            scene = Scene(config, self.arch)
        except ConfigError as exc:
            if first_build:
                raise
            path, self.overrides = self.scene_path, dict(self._built_with)
            scene = Scene(load_scene_config(path, override_texts(self.overrides)), self.arch)
            notice = f"**not switched: {exc}**"
        self._built_with = dict(self.overrides)
        self.scene_path, self.scene, self.notice = path, scene, notice
        self.builds += 1
        if scene.bleeding is not None:
            scene.bleed_points = [point for point in scene.bleed_points if point.name not in self.removed_points]
            self.added_points = [scene.add_bleed_point(item["name"], item["position_mm"], item["rate_ml_s"], item["radius_mm"]).item
                                 for item in self.added_points]
            if not any(tool.suction for tool in scene.instruments):
                scene.instruments.append(self._spare_sucker())
        self.server.gui.reset()
        self.server.scene.reset()
        self.server.scene.set_up_direction("+z")
        self.stream = TextureStream(self.server, scene.surface)
        self.stream.update(scene.composite())
        self.history.clear()
        self._build_gui()

    def _schedule_rebuild(self) -> None:
        """Rebuild once REBUILD_DELAY_S passed without another change (simulation thread)."""
        self._rebuild_at = time.monotonic() + REBUILD_DELAY_S

    def _switch_scene(self, path: Path) -> None:
        """Another scene: keeps the quality preset, forgets the changes made to this one."""
        self.overrides = dict(QUALITY[self.quality])
        self.added_points, self.removed_points = [], set()
        self.spare_suction = dict(SPARE_SUCTION)
        self._rebuild_at = None
        self._load(path)

    def _set_quality(self, name: str) -> None:
        self.quality = name
        for key in QUALITY_KEYS:
            self.overrides.pop(key, None)
        self.overrides.update(QUALITY[name])
        self._schedule_rebuild()

    def _spare_sucker(self) -> Instrument:
        """A suction cannula parked above the tissue, for scenes that bleed without one."""
        top = self.scene.surface.vertices_mm.max(axis=0)
        shape = {"type": "capsule", "radius_mm": 1.5, "length_mm": 20.0, "width_mm": 1.0, "thickness_mm": 1.0, "file": None, "sdf_resolution": 8}
        parked = Pose(np.array([top[0] - 5.0, top[1] - 5.0, top[2] + 10.0]), np.array([0.0, 0.0, -1.0]), 0.0, False, 20.0)
        return Instrument("sucker", shape, parked, suction=self.spare_suction)

    def _frame_camera(self, client) -> None:
        lo, hi = self.scene.surface.vertices_mm.min(axis=0), self.scene.surface.vertices_mm.max(axis=0)
        centre, size = (lo + hi) / 2, float(np.max(hi - lo))
        client.camera.position = tuple(centre + np.array([0.0, -0.45, 1.0]) * 0.95 * size)
        client.camera.look_at = tuple(centre)

    # --- GUI --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, scene = self.server.gui, self.scene
        self.sliders = {}  # every parameter slider by its scene key (its label when it has none)
        with gui.add_folder("Run"):
            pause = gui.add_button("Resume" if not self.running else "Pause")
            step = gui.add_button("Single step")
            reset = gui.add_button("Reset", hint="back to t = 0, with the current settings")
            reload = gui.add_button("Back to the scene file", hint="forgets every change but the quality preset; " + REBUILD_HINT)
            speed = gui.add_slider("Speed (x real time)", 0.1, 4.0, 0.1, self.speed)
            files = scene_files()
            current = str(self.scene_path.resolve().relative_to(REPO_ROOT)) if self.scene_path.resolve().is_relative_to(REPO_ROOT) else str(self.scene_path)
            chooser = gui.add_dropdown("Scene", files if current in files else [current, *files], initial_value=current,
                                       hint="keeps the quality preset, forgets the other changes")
            lighting = gui.add_checkbox("Simple lighting", self.simple_lighting,
                                        hint="no environment light, no shadows: draws several times faster in a browser without a GPU")
            quality = gui.add_dropdown("Quality", tuple(QUALITY), initial_value=self.quality,
                                       hint="fast: 256² texels, 1 fluid substep; balanced: 512², 2; accurate: 1024², 4; "
                                            "scene file: as the scene says. " + REBUILD_HINT)

        self.pause_button = pause
        self.lighting_checkbox = lighting
        lighting.on_update(lambda _: self.set_simple_lighting(bool(lighting.value)))
        pause.on_click(lambda _: self.set_running(not self.running))
        step.on_click(lambda _: self.commands.put(lambda: setattr(self, "single_steps", self.single_steps + 1)))
        reset.on_click(lambda _: self.commands.put(self.scene.reset))
        reload.on_click(lambda _: self.commands.put(lambda: self._switch_scene(self.scene_path)))
        speed.on_update(lambda _: setattr(self, "speed", bounded(speed, 0.1, 4.0)))
        chooser.on_update(lambda _: self.commands.put(lambda path=REPO_ROOT / chooser.value: self._switch_scene(path)))
        quality.on_update(lambda _: self.commands.put(lambda name=quality.value: self._set_quality(name)))
        self.scene_dropdown, self.quality_dropdown = chooser, quality

        self._build_sliders()
        self._build_instruments()
        if scene.bleeding is not None:
            self._build_bleeding_tools()
        with gui.add_folder("Stats"):
            self.stats_text = gui.add_markdown("starting...")
            series = {0: viser.uplot.Series(label="t (s)"), 1: viser.uplot.Series(label="max T (C)", stroke="orange"),
                      2: viser.uplot.Series(label="blood (mm2)", stroke="red")}
            self.plot_columns = [0] + ([1] if scene.cautery is not None else []) + ([2] if scene.bleeding is not None else [])
            self.plot = gui.add_uplot(
                data=tuple(np.zeros(1) for _ in self.plot_columns), series=tuple(series[column] for column in self.plot_columns),
                title="over time", aspect=2.0, scales={"x": {"time": False}},
            )

    def set_simple_lighting(self, simple: bool) -> None:
        """Environment light and shadows (the default), or the default lights alone (any thread: viser calls only)."""
        self.simple_lighting = simple
        if simple:
            self.server.scene.configure_environment_map(None)
        else:  # viser's environment light at full strength washes the liver out to pale pink
            self.server.scene.configure_environment_map("warehouse", environment_intensity=ENVIRONMENT_INTENSITY)
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=not simple)
        if getattr(self, "lighting_checkbox", None) is not None:
            self.lighting_checkbox.value = simple  # (no callback when it shows that already)

    def set_running(self, running: bool) -> None:
        """Pause or resume (any thread: the loop reads the flag)."""
        self.running = running
        self.pause_button.label = "Pause" if running else "Resume"
        if running and self.notice.startswith("**simulation stopped"):
            self.notice = ""

    def _slider(self, label: str, spec: params.ParamSpec, value, key: str | None, apply=None):
        """A slider over the spec's range. A change is bounded (and rounded for whole numbers) here, then on the
        simulation thread kept as override `key` (None: not a scene key) and handed to apply(value), or, without
        apply, it rebuilds the scene."""
        hint = spec.help + (f". {REBUILD_HINT}" if apply is None else "")
        handle = self.server.gui.add_slider(label, spec.min, spec.max, slider_step(spec), value, hint=hint)
        handle.on_update(lambda _: self._slider_changed(handle, spec, key, apply))
        self.sliders[key or label] = handle
        return handle

    def _slider_changed(self, handle, spec, key, apply) -> None:
        """GUI thread: queue the bounded value for the simulation thread."""
        value = bounded(handle, spec.min, spec.max)
        if spec.integer:
            value = int(round(value))
            if handle.value != value:
                handle.value = value
        scene = self.scene

        def change():
            if self.scene is not scene:  # the scene was switched or rebuilt since: the slider is gone
                return
            if key is not None:
                self.overrides[key] = value
            if apply is None:
                self._schedule_rebuild()
            else:
                apply(value)

        self.commands.put(change)

    def _build_sliders(self) -> None:
        gui, config = self.server.gui, self.scene.config
        for group, label, table, model, rebuild in SLIDER_GROUPS:
            if model is not None and model not in self.scene.models:
                continue
            values = config[group] if group else config  # the dict the models read each step
            with gui.add_folder(label, expand_by_default=False):
                handles = {}
                for name, spec in table.items():
                    key = f"{group}.{name}" if group else name
                    apply = None if name in rebuild else (lambda value, d=values, n=name: d.__setitem__(n, value))
                    handles[name] = self._slider(slider_label(name, spec), spec, values[name], key, apply)
                defaults = gui.add_button(f"Reset {label.lower()} to defaults")
                defaults.on_click(lambda _, t=table, h=handles, g=group: self._reset_sliders(t, h, g))

    def _reset_sliders(self, table, handles, group) -> None:
        base = params.TISSUE_PRESETS[self.scene.config["tissue"]["preset"]] if group == "tissue" else {n: s.default for n, s in table.items()}
        for name, handle in handles.items():
            handle.value = base[name]  # fires on_update, which queues the change (rebuilds coalesce into one)

    def _build_instruments(self) -> None:
        gui, scene = self.server.gui, self.scene
        self.tool_meshes, self.tool_gizmos, self.tool_hot, self.tool_placed = {}, {}, {}, {}
        self.tool_switches, self.tool_switch_shown = {}, {}  # energize checkboxes, and the value each last had
        with gui.add_folder("Instruments"):
            demo = gui.add_checkbox("Demo mode (scripted paths)", any(tool.path for tool in scene.instruments))
            demo.on_update(lambda _: self.commands.put(lambda: self._set_demo(demo.value)))
            for index, tool in enumerate(scene.instruments):
                pose = tool.pose_at(scene.time_s)
                gizmo = self.server.scene.add_transform_controls(f"/tools/{tool.name}", scale=8.0, position=tuple(pose.position_mm), wxyz=tuple(pose_wxyz(pose)))
                body = instrument_mesh(tool.shape)
                self.tool_meshes[tool.name] = self.server.scene.add_mesh_simple(
                    f"/tools/{tool.name}/body", body.vertices.astype(np.float32), body.faces.astype(np.uint32), color=TOOL_COLOR)
                on = gui.add_checkbox(f"{tool.name}: {'suction on' if tool.suction else 'energized'}", pose.energized)
                tip = params.INSTRUMENT["tip_temperature_c"]
                temperature = None if tool.suction else gui.add_slider(f"{tool.name}: tip temperature (C)", tip.min, tip.max, 1.0, pose.tip_temperature_c, hint=tip.help)
                self.tool_gizmos[tool.name] = gizmo
                gizmo.on_update(lambda _, t=tool, g=gizmo: self.commands.put(lambda: self._move_tool(t, g.wxyz, g.position)))
                self.tool_switches[tool.name], self.tool_switch_shown[tool.name] = on, pose.energized
                on.on_update(lambda _, t=tool, h=on: self._switch_changed(t, h))
                if temperature is not None:
                    temperature.on_update(lambda _, t=tool, h=temperature: self.commands.put(lambda: self._tool_setting(t, tip_temperature_c=bounded(h, tip.min, tip.max))))
                in_file = index < len(scene.config["instruments"])  # not the spare sucker
                if in_file:  # the shape's sizes: the scene is rebuilt with them
                    for name in SHAPE_SLIDERS[tool.shape["type"]]:
                        spec = params.SHAPE[name]
                        self._slider(f"{tool.name}: {slider_label(name, spec)}", spec, tool.shape[name], f"instruments.{index}.shape.{name}")
                if tool.suction is not None:  # read every step
                    for name, spec in params.SUCTION.items():
                        self._slider(f"{tool.name}: suction {slider_label(name, spec)}", spec, tool.suction[name],
                                     f"instruments.{index}.suction.{name}" if in_file else None,
                                     lambda value, d=tool.suction, n=name: d.__setitem__(n, value))
        if not demo.value:
            self._set_demo(False)

    def _switch_changed(self, tool, handle) -> None:
        """GUI thread: a click on an energize checkbox takes the tool over; the echo of _show_tools showing a scripted
        change does not (it stores the value first)."""
        value = bool(handle.value)
        if value != self.tool_switch_shown.get(tool.name):
            self.tool_switch_shown[tool.name] = value
            self.commands.put(lambda: self._tool_setting(tool, energized=value))

    def _set_demo(self, on: bool) -> None:
        for tool in self.scene.instruments:
            tool.override = None if on else tool.pose_at(self.scene.time_s)

    def _move_tool(self, tool, wxyz, position) -> None:
        tool.override = pose_from_transform(wxyz, position, tool.pose_at(self.scene.time_s))

    def _tool_setting(self, tool, **changes) -> None:
        pose = tool.pose_at(self.scene.time_s)
        tool.override = Pose(pose.position_mm, pose.direction, pose.roll_deg, changes.get("energized", pose.energized), changes.get("tip_temperature_c", pose.tip_temperature_c))

    def _build_bleeding_tools(self) -> None:
        gui = self.server.gui
        self.bleed_markers, self.point_folders = {}, {}
        with gui.add_folder("Bleed points") as folder:
            add = gui.add_button("Add bleed point (then click the tissue)")
            remove = gui.add_button("Remove last bleed point")
        self.bleed_folder = folder
        for point in self.scene.bleed_points:
            self._add_marker(point)

        scene = self.scene

        @add.on_click
        def _(_):
            def clicked(event):  # the next click in the scene, only
                self.server.scene.remove_click_callback(clicked)
                hit = self._hit_surface(np.asarray(event.ray_origin), np.asarray(event.ray_direction))
                if hit is not None:
                    self.commands.put(lambda: self._add_point(hit) if self.scene is scene else None)

            self.server.scene.remove_click_callback("all")  # pressing the button twice still adds one point
            self.server.scene.on_click()(clicked)

        remove.on_click(lambda _: self.commands.put(lambda: self._remove_last_point() if self.scene is scene else None))

    def _hit_surface(self, origin: np.ndarray, direction: np.ndarray):
        """The surface texel position (mm) nearest to a ray, if the ray passes within 1 mm of one."""
        surface = self.scene.surface
        points = surface.position_mm[surface.mask]
        direction = direction / np.linalg.norm(direction)
        along = (points - origin) @ direction
        miss = np.linalg.norm(points - origin - along[:, None] * direction, axis=1)
        miss[along <= 0] = np.inf
        best = int(np.argmin(miss))
        return points[best] if miss[best] < 1.0 else None

    def _add_point(self, position) -> None:
        """A new bleed point at a surface position, with the default rate and radius (simulation thread)."""
        taken = {point.name for point in self.scene.bleed_points} | self.removed_points
        number = len(self.scene.bleed_points) + 1
        while f"point{number}" in taken:
            number += 1
        defaults = params.BLEED_POINT
        point = self.scene.add_bleed_point(f"point{number}", position, defaults["rate_ml_s"].default, defaults["radius_mm"].default)
        self.added_points.append(point.item)
        self._add_marker(point)

    def _add_marker(self, point) -> None:
        """The point's red marker with a gizmo, and its folder of sliders."""
        gizmo = self.server.scene.add_transform_controls(f"/bleed/{point.name}", scale=5.0, position=tuple(point.position_at(self.scene.time_s)), disable_rotations=True)
        self.server.scene.add_icosphere(f"/bleed/{point.name}/dot", radius=0.8, color=(150, 0, 0))
        gizmo.on_update(lambda _, p=point, g=gizmo: self.commands.put(lambda: self._move_point(p, g.position)))
        self.bleed_markers[point.name] = gizmo
        with self.bleed_folder, self.server.gui.add_folder(point.name) as folder:
            for name, spec in params.BLEED_POINT.items():
                self._slider(f"{point.name}: {slider_label(name, spec)}", spec, point.item[name], None,
                             lambda value, p=point, n=name: self._set_point(p, n, value))
        self.point_folders[point.name] = folder

    def _point_index(self, point) -> int | None:
        """The point's index in the scene file's bleed_points, or None for a point added in the browser."""
        return next((index for index, item in enumerate(self.scene.config["bleed_points"]) if item is point.item), None)

    def _remember_point(self, point, *names) -> None:
        index = self._point_index(point)
        if index is not None:  # added points keep their item, which the rebuild re-adds
            for name in names:
                self.overrides[f"bleed_points.{index}.{name}"] = json.loads(json.dumps(point.item[name]))

    def _set_point(self, point, name: str, value: float) -> None:
        point.item[name] = value
        changed = [name]
        if name == "rate_ml_s" and any(frame.get("rate_ml_s") is not None for frame in point.item["path"]):
            for frame in point.item["path"]:  # the slider's rate holds from now on
                frame["rate_ml_s"] = None
            changed.append("path")
        self._remember_point(point, *changed)

    def _move_point(self, point, position) -> None:
        point.item["position_mm"] = [float(v) for v in self.scene.surface.position_mm[self.scene.texel_near(position)]]
        point.item["path"] = []
        self._remember_point(point, "position_mm", "path")

    def _remove_last_point(self) -> None:
        if not self.scene.bleed_points:
            return
        point = self.scene.bleed_points.pop()
        self.bleed_markers.pop(point.name).remove()
        self.point_folders.pop(point.name).remove()
        if any(item is point.item for item in self.added_points):
            self.added_points = [item for item in self.added_points if item is not point.item]
        else:
            self.removed_points.add(point.name)

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
                self.set_running(False)
                self.notice = f"**simulation stopped: {type(exc).__name__}: {exc}** (press Resume or Reset)"
                self.stats_text.content = self.notice
                time.sleep(0.5)
        return False

    def _run(self, until, deadline) -> bool:
        last_frame = last_stats = last_check = time.perf_counter()
        steps = updates = sent = 0
        wall_anchor, sim_anchor = time.perf_counter(), self.scene.time_s
        while not self.stop_event.is_set():
            now = time.perf_counter()
            if until is not None and now - last_check >= 0.05:
                last_check = now
                try:
                    if until():
                        return True
                except Exception as exc:
                    raise UntilFailed() from exc
                if deadline is not None and time.monotonic() > deadline:
                    return False
            while not self.commands.empty():
                self.commands.get_nowait()()
                wall_anchor, sim_anchor = time.perf_counter(), self.scene.time_s
            if self._rebuild_at is not None and time.monotonic() >= self._rebuild_at:
                self._rebuild_at = None
                self._load(self.scene_path)
                wall_anchor, sim_anchor = time.perf_counter(), self.scene.time_s
            now = time.perf_counter()
            behind = (now - wall_anchor) * self.speed - (self.scene.time_s - sim_anchor)
            if (self.running and behind > 0) or self.single_steps:
                self.single_steps = max(0, self.single_steps - 1)
                self.scene.step()
                steps += 1
                if behind > 0.5:  # cannot keep up: drop the backlog rather than spiral
                    wall_anchor, sim_anchor = now, self.scene.time_s
            else:
                time.sleep(0.002)
                if not self.running:
                    wall_anchor, sim_anchor = now, self.scene.time_s
            if now - last_frame >= FRAME_INTERVAL_S:
                self._show_tools()
                result = self.stream.update(self.scene.composite())
                updates += result["tiles_sent"] > 0  # updates that sent something
                sent += result["bytes"]
                last_frame = now
            if now - last_stats >= STATS_INTERVAL_S:
                span = now - last_stats
                self.stats = {"steps_per_s": steps / span, "updates_per_s": updates / span, "bytes_per_s": sent / span}
                steps = updates = sent = 0
                last_stats = now
                self._show_stats()
        return False

    def _show_tools(self) -> None:
        """Move scripted tools' gizmos and colour energized ones (only what changed is sent)."""
        for tool in self.scene.instruments:
            pose = tool.pose_at(self.scene.time_s)
            placed = (tuple(pose.position_mm), tuple(pose_wxyz(pose)))
            if tool.override is None and self.tool_placed.get(tool.name) != placed:
                gizmo = self.tool_gizmos[tool.name]
                gizmo.position, gizmo.wxyz = placed
                self.tool_placed[tool.name] = placed
            switch = self.tool_switches[tool.name]
            if switch.value != pose.energized:  # a scripted switch shows in the checkbox
                self.tool_switch_shown[tool.name] = pose.energized
                switch.value = pose.energized
            hot = pose.energized and tool.suction is None
            if self.tool_hot.get(tool.name) != hot:
                self.tool_meshes[tool.name].color = HOT_COLOR if hot else TOOL_COLOR
                self.tool_hot[tool.name] = hot

    def _show_stats(self) -> None:
        metrics = self.scene.metrics()
        lines = [
            f"t = {self.scene.time_s:.2f} s, {'running' if self.running else 'paused'}, arch {self.scene.arch}",
            f"simulation: {self.stats['steps_per_s']:.0f} steps/s",
            f"texture: {self.stats['updates_per_s']:.1f} updates/s, {self.stats['bytes_per_s'] / 1024:.0f} kB/s",
        ]
        max_t, blood = 0.0, 0.0
        if "cautery" in metrics:
            c = metrics["cautery"]
            max_t = c["max_temperature_c"]
            lines.append(f"max temperature: {max_t:.0f} C, coagulated: {c['coagulated_area_mm2']:.1f} mm2, charred: {c['charred_area_mm2']:.1f} mm2")
        if "bleeding" in metrics:
            b = metrics["bleeding"]
            blood = b["blood_area_mm2"]
            lines.append(f"particles alive: {b['alive']} / {b['capacity']}, blood: {blood:.0f} mm2, suctioned: {b['suctioned']}")
            if b["dropped_pool_full"]:
                lines.append(f"**pool full: {b['dropped_pool_full']} particles not spawned**")
        if self._rebuild_at is not None:
            lines.append("**restarting the scene with the new value...**")
        if self.notice:
            lines.append(self.notice)
        self.stats_text.content = "  \n".join(lines)
        self.history.append((self.scene.time_s, max_t, blood))
        self.history = [row for row in self.history if self.scene.time_s - PLOT_SECONDS <= row[0] <= self.scene.time_s]  # (after a reset too)
        self.plot.data = tuple(np.array([row[column] for row in self.history], np.float64) for column in self.plot_columns)

    def close(self) -> None:
        self.stop_event.set()
        self.stream.close()
        self.server.stop()


def serve(scene_path, host: str, port: int, arch: str) -> None:
    """Start the lab and block until Ctrl-C."""
    app = LabApp(scene_path, host, port, arch)
    print(f"tissue lab: http://{host}:{port}  ({Path(scene_path).name}, {app.scene.arch}); Ctrl-C stops", flush=True)
    try:
        app.run()  # Taichi stays on the main thread, where the scene was built
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
