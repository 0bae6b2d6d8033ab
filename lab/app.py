"""The browser lab: a viser server showing the textured tissue, draggable instruments and bleed
points, sliders for every parameter, run controls and live stats.

Threads: viser runs GUI callbacks concurrently in a pool; they never touch the simulation. They put
small functions on `commands`, and the one simulation loop (the main thread under `serve`) runs them
between steps.
"""
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
from sims import params
from sims.config import REPO_ROOT
from sims.instruments import Instrument, Pose, local_frame
from sims.scene import Scene

FRAME_INTERVAL_S = 1.0 / 30.0       # texture updates at most this often
STATS_INTERVAL_S = 0.5
PLOT_SECONDS = 60.0
QUALITY = {  # name: scene overrides (texture texels, fluid substeps)
    "fast": {"texture_size": 256, "bleeding.substeps": 1},
    "balanced": {"texture_size": 512, "bleeding.substeps": 2},
    "accurate": {"texture_size": 1024, "bleeding.substeps": 4},
}
SLIDER_GROUPS = (("tissue", "Tissue", params.TISSUE, "cautery"), ("cautery", "Cautery", params.CAUTERY, "cautery"), ("bleeding", "Bleeding", params.BLEEDING, "bleeding"))
LIVE_EXCLUDED = {"capacity", "substeps"}  # need a rebuild: set by scene file or quality preset
TOOL_COLOR, HOT_COLOR = (170, 175, 185), (255, 140, 40)


def bounded(handle, low: float, high: float) -> float:
    """The handle's value kept inside [low, high]; a value typed outside is put back in the browser."""
    value = min(max(float(handle.value), low), high)
    if value != handle.value:
        handle.value = value
    return value


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


class LabApp:
    """One scene served to every connected browser."""

    def __init__(self, scene_path, host: str = "127.0.0.1", port: int = 8080, arch: str = "auto", overrides=()):
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.arch = arch
        self.commands: queue.Queue = queue.Queue()
        self.running, self.speed, self.single_steps = True, 1.0, 0
        self.quality = "balanced"
        self.stop_event = threading.Event()
        self.stats = {"steps_per_s": 0.0, "updates_per_s": 0.0, "bytes_per_s": 0.0}
        self.history: list[tuple] = []
        self.server.on_client_connect(self._frame_camera)
        self._load(Path(scene_path), overrides)
        self.thread = None

    def start(self) -> None:
        """Run the simulation in a background thread (tests). Scene switches then build Taichi fields
        on that thread; `serve` runs the loop on the main thread instead."""
        self.thread = threading.Thread(target=self.run, name="simulation", daemon=True)
        self.thread.start()

    # --- scene lifetime ---------------------------------------------------------------------
    def _load(self, path: Path, overrides=()) -> None:
        """Build the scene, the texture stream and the GUI (sim thread or start-up only)."""
        self.scene_path = path
        self.scene = Scene.from_file(path, list(overrides), arch=self.arch)
        if self.scene.bleeding is not None and not any(tool.suction for tool in self.scene.instruments):
            self.scene.instruments.append(self._spare_sucker())
        if getattr(self, "stream", None) is not None:
            self.stream.close()
        self.server.gui.reset()
        self.server.scene.reset()
        self.server.scene.set_up_direction("+z")
        self.stream = TextureStream(self.server, self.scene.surface)
        self.stream.update(self.scene.composite())
        self.history.clear()
        self._build_gui()

    def _spare_sucker(self) -> Instrument:
        """A suction cannula parked above the tissue, for scenes that bleed without one."""
        top = self.scene.surface.vertices_mm.max(axis=0)
        shape = {"type": "capsule", "radius_mm": 1.5, "length_mm": 20.0, "width_mm": 1.0, "thickness_mm": 1.0, "file": None, "sdf_resolution": 8}
        parked = Pose(np.array([top[0] - 5.0, top[1] - 5.0, top[2] + 10.0]), np.array([0.0, 0.0, -1.0]), 0.0, False, 20.0)
        return Instrument("sucker", shape, parked, suction={"radius_mm": 4.0, "rate_ml_s": 0.2})

    def _frame_camera(self, client) -> None:
        lo, hi = self.scene.surface.vertices_mm.min(axis=0), self.scene.surface.vertices_mm.max(axis=0)
        centre, size = (lo + hi) / 2, float(np.max(hi - lo))
        client.camera.position = tuple(centre + np.array([0.0, -0.45, 1.0]) * 0.95 * size)
        client.camera.look_at = tuple(centre)

    # --- GUI --------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, scene = self.server.gui, self.scene
        with gui.add_folder("Run"):
            pause = gui.add_button("Pause")
            step = gui.add_button("Single step")
            reset = gui.add_button("Reset")
            speed = gui.add_slider("Speed (x real time)", 0.1, 4.0, 0.1, self.speed)
            files = scene_files()
            current = str(self.scene_path.resolve().relative_to(REPO_ROOT)) if self.scene_path.resolve().is_relative_to(REPO_ROOT) else str(self.scene_path)
            chooser = gui.add_dropdown("Scene", files if current in files else [current, *files], initial_value=current)
            quality = gui.add_dropdown("Quality", tuple(QUALITY), initial_value=self.quality, hint="fast: 256² texels, 1 fluid substep; balanced: 512², 2; accurate: 1024², 4")

        @pause.on_click
        def _(_):
            self.running = not self.running
            pause.label = "Resume" if not self.running else "Pause"

        step.on_click(lambda _: self.commands.put(lambda: setattr(self, "single_steps", self.single_steps + 1)))
        reset.on_click(lambda _: self.commands.put(self.scene.reset))
        speed.on_update(lambda _: setattr(self, "speed", bounded(speed, 0.1, 4.0)))
        chooser.on_update(lambda _: self.commands.put(lambda: self._load(REPO_ROOT / chooser.value, self._quality_overrides())))

        @quality.on_update
        def _(_):
            self.quality = quality.value
            self.commands.put(lambda: self._load(self.scene_path, self._quality_overrides()))

        self._build_sliders()
        self._build_instruments()
        if scene.bleeding is not None:
            self._build_bleeding_tools()
        with gui.add_folder("Stats"):
            self.stats_text = gui.add_markdown("starting...")
            self.plot = gui.add_uplot(
                data=(np.zeros(1), np.zeros(1), np.zeros(1)),
                series=(viser.uplot.Series(label="t (s)"), viser.uplot.Series(label="max T (C)", stroke="orange"), viser.uplot.Series(label="blood (mm2)", stroke="red")),
                title="over time", aspect=2.0,
            )

    def _quality_overrides(self) -> list[str]:
        overrides = QUALITY[self.quality]
        return [f"{key}={value}" for key, value in overrides.items() if not key.startswith("bleeding.") or "bleeding" in self.scene.models]

    def _build_sliders(self) -> None:
        gui = self.server.gui
        self.sliders = {}
        for group, label, table, model in SLIDER_GROUPS:
            if model not in self.scene.models:
                continue
            values = self.scene.config[group]
            with gui.add_folder(label, expand_by_default=False):
                handles = {}
                for name, spec in table.items():
                    if name in LIVE_EXCLUDED:
                        continue
                    step = 1 if spec.integer else (spec.max - spec.min) / 1000.0
                    handle = gui.add_slider(f"{name} ({spec.unit})" if spec.unit else name, spec.min, spec.max, step, values[name], hint=spec.help)
                    handle.on_update(lambda _, g=group, n=name, h=handle, sp=spec: self._set_param(g, n, bounded(h, sp.min, sp.max)))
                    handles[name] = handle
                    self.sliders[f"{group}.{name}"] = handle
                defaults = gui.add_button(f"Reset {label.lower()} to defaults")
                defaults.on_click(lambda _, t=table, h=handles, g=group: self._reset_sliders(t, h, g))

    def _set_param(self, group: str, name: str, value: float) -> None:
        self.commands.put(lambda: self.scene.config[group].__setitem__(name, value))

    def _reset_sliders(self, table, handles, group) -> None:
        base = params.TISSUE_PRESETS[self.scene.config["tissue"]["preset"]] if group == "tissue" else {n: s.default for n, s in table.items()}
        for name, handle in handles.items():
            handle.value = base[name]  # fires on_update, which queues the change

    def _build_instruments(self) -> None:
        gui, scene = self.server.gui, self.scene
        self.tool_meshes, self.tool_gizmos, self.tool_hot, self.tool_placed = {}, {}, {}, {}
        with gui.add_folder("Instruments"):
            demo = gui.add_checkbox("Demo mode (scripted paths)", any(tool.path for tool in scene.instruments))
            demo.on_update(lambda _: self.commands.put(lambda: self._set_demo(demo.value)))
            for tool in scene.instruments:
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
                on.on_update(lambda _, t=tool, h=on: self.commands.put(lambda: self._tool_setting(t, energized=bool(h.value))))
                if temperature is not None:
                    temperature.on_update(lambda _, t=tool, h=temperature: self.commands.put(lambda: self._tool_setting(t, tip_temperature_c=bounded(h, tip.min, tip.max))))
        if not demo.value:
            self._set_demo(False)

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
        self.bleed_markers = {}
        with gui.add_folder("Bleed points"):
            add = gui.add_button("Add bleed point (then click the tissue)")
            rate = gui.add_slider("Rate of new points (ml/s)", 0.0, 0.2, 0.001, 0.02)
            remove = gui.add_button("Remove last bleed point")
        for point in self.scene.bleed_points:
            self._add_marker(point)

        @add.on_click
        def _(_):
            @self.server.scene.on_pointer_event("click")
            def _(event):
                self.server.scene.remove_pointer_callback()
                hit = self._hit_surface(np.asarray(event.ray_origin), np.asarray(event.ray_direction))
                if hit is not None:
                    self.commands.put(lambda: self._add_marker(self.scene.add_bleed_point(f"point{len(self.scene.bleed_points) + 1}", hit, bounded(rate, 0.0, 0.2))))

        remove.on_click(lambda _: self.commands.put(self._remove_last_point))

    def _hit_surface(self, origin: np.ndarray, direction: np.ndarray):
        """The surface texel position (mm) nearest to a ray, if the ray passes within 3 texels' reach."""
        surface = self.scene.surface
        points = surface.position_mm[surface.mask]
        direction = direction / np.linalg.norm(direction)
        along = (points - origin) @ direction
        miss = np.linalg.norm(points - origin - along[:, None] * direction, axis=1)
        miss[along <= 0] = np.inf
        best = int(np.argmin(miss))
        return points[best] if miss[best] < 1.0 else None

    def _add_marker(self, point) -> None:
        gizmo = self.server.scene.add_transform_controls(f"/bleed/{point.name}", scale=5.0, position=tuple(point.position_at(0.0)), disable_rotations=True)
        self.server.scene.add_icosphere(f"/bleed/{point.name}/dot", radius=0.8, color=(150, 0, 0))
        gizmo.on_update(lambda _, p=point, g=gizmo: self.commands.put(lambda: self._move_point(p, g.position)))
        self.bleed_markers[point.name] = gizmo

    def _move_point(self, point, position) -> None:
        point.item["position_mm"] = list(self.scene.surface.position_mm[self.scene.texel_near(position)])
        point.item["path"] = []

    def _remove_last_point(self) -> None:
        if self.scene.bleed_points:
            point = self.scene.bleed_points.pop()
            self.bleed_markers.pop(point.name).remove()

    # --- simulation thread ------------------------------------------------------------------
    def run(self) -> None:
        """Run the simulation until close(); an error pauses it and is shown in the stats instead of
        stopping the lab."""
        while not self.stop_event.is_set():
            try:
                self._run()
            except Exception as exc:  # keep serving the browsers; the user can reset or switch scenes
                traceback.print_exc()
                self.running = False
                self.stats_text.content = f"**simulation stopped: {type(exc).__name__}: {exc}** (press Resume or Reset)"
                time.sleep(0.5)

    def _run(self) -> None:
        last_frame = last_stats = time.perf_counter()
        steps = updates = sent = 0
        wall_anchor, sim_anchor = time.perf_counter(), self.scene.time_s
        while not self.stop_event.is_set():
            while not self.commands.empty():
                self.commands.get_nowait()()
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
                updates += 1
                sent += result["bytes"]
                last_frame = now
            if now - last_stats >= STATS_INTERVAL_S:
                span = now - last_stats
                self.stats = {"steps_per_s": steps / span, "updates_per_s": updates / span, "bytes_per_s": sent / span}
                steps = updates = sent = 0
                last_stats = now
                self._show_stats()

    def _show_tools(self) -> None:
        """Move scripted tools' gizmos and colour energized ones (only what changed is sent)."""
        for tool in self.scene.instruments:
            pose = tool.pose_at(self.scene.time_s)
            placed = (tuple(pose.position_mm), tuple(pose_wxyz(pose)))
            if tool.override is None and self.tool_placed.get(tool.name) != placed:
                gizmo = self.tool_gizmos[tool.name]
                gizmo.position, gizmo.wxyz = placed
                self.tool_placed[tool.name] = placed
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
        self.stats_text.content = "  \n".join(lines)
        self.history.append((self.scene.time_s, max_t, blood))
        self.history = [row for row in self.history if row[0] >= self.scene.time_s - PLOT_SECONDS]
        self.plot.data = tuple(np.array(column, np.float64) for column in zip(*self.history))

    def close(self) -> None:
        self.stop_event.set()
        if self.thread is not None:
            self.thread.join(timeout=5)
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
