"""A lab session without any GUI: one scene at a time, changed from any thread, stepped by one.

Every front end drives the lab through a LabSession: the viser app (lab.web.app) is a view of one, and a script or a test
can do all a browser does with the same calls. Command methods (`set_parameter`, `take_over`, `switch_scene`, ...)
may be called from any thread: each checks its values at once against what the session offers (the scene list,
the quality presets, the scene's parameters and their ranges; finite numbers only) and raises `Refused` with the
reason, then queues the change as a named command (lab.commands). The simulation thread calls `tick()`, which applies queued changes between steps,
rebuilds the scene when asked, and steps it at the speed asked (real time by default).

Rebuilds: parameters the models do not read every step (texture size, particle pool, tool shapes, the quality
preset) are kept as scene overrides (the `--set` syntax) that every rebuild applies; a burst of them (a slider being
dragged) waits REBUILD_DELAY_S of quiet and rebuilds once. Changes made live are kept as overrides too, so a rebuild
keeps them. There is always a valid scene: a rebuild whose scene file or overrides are bad keeps the running scene
as it is; one whose build fails after the old scene was dropped builds the last good scene again from memory.
"""
from __future__ import annotations

import queue
import threading
import time
from pathlib import Path

import numpy as np

from lab import commands
from sims.core import backend
from sims.scene import checks, params
from sims.scene.assembly import Scene, load_inputs
from sims.scene.checked import Refused, checked_flag, checked_number, finite_vector, unit_direction
from sims.scene.config import REPO_ROOT, ConfigError, load_scene_config, parse_override
from sims.scene.instruments import Instrument, Pose

SCENES_DIR = REPO_ROOT / "scenes"
REBUILD_DELAY_S = 0.5     # a rebuild waits until its sliders have been still this long (one rebuild per drag)
MAX_PENDING = 256         # commands waiting for the simulation thread at most; more are refused
MAX_BLEED_POINTS = 16     # bleed points in a scene at most (the scene's and the added ones)
FINITE_CHECK_EVERY = 25   # steps between checks of the fields for NaN and inf
MAX_BACKLOG_S = 0.5       # the simulation drops a backlog larger than this rather than spiral
SPEED_RANGE = (0.1, 4.0)  # x real time
TEXTURE_INTERVAL_S = 0.1  # a front end composes and streams the look at most this often: the stream publishes about
                          # 21 tiles a second at most (its rate limit), so composing more often would repeat the work
REST_DEPTH_MM = 0.2       # a tool rested on the tissue presses its tip this far in
QUALITY = {  # name: scene overrides (texture texels; fluid substeps of either bleeding method, the one in use applies)
    "scene file": {},
    "fast": {"texture_size": 256, "bleeding.substeps": 1, "bleeding.cfl": 0.65},
    "balanced": {"texture_size": 512, "bleeding.substeps": 2, "bleeding.cfl": 0.6},
    "accurate": {"texture_size": 1024, "bleeding.substeps": 4, "bleeding.cfl": 0.3},
}
_NO_SWITCH = object()     # no switch is waiting (None asks for the current scene's file)
SPARE_SUCTION = {"radius_mm": 4.0, "rate_ml_s": 0.2}
SPARE_SUCKER_SHAPE = {"type": "capsule", "radius_mm": 1.5, "length_mm": 20.0, "width_mm": 1.0, "thickness_mm": 1.0, "file": None, "sdf_resolution": 8}


def override_key_values(texts) -> dict:
    """["dotted.key=value", ...] (the --set syntax) -> {dotted.key: value}; a mapping is taken as it is."""
    if isinstance(texts, dict):
        return dict(texts)
    values = {}
    for text in texts:
        parts, value = parse_override(text)
        values[".".join(parts)] = value
    return values


def fitting_overrides(path: Path, overrides: dict) -> dict:
    """The overrides without the `bleeding.` keys that the scene's bleeding method does not have (a quality preset
    names the keys of both methods). Raises ConfigError as load_scene_config does."""
    def general(key: str) -> bool:
        return not key.startswith("bleeding.") or key == "bleeding.method"

    plain = {key: value for key, value in overrides.items() if general(key)}
    table = params.BLEEDING_METHODS[load_scene_config(path, plain)["bleeding"]["method"]]
    return {key: value for key, value in overrides.items() if general(key) or key.split(".")[1] in table}


class LabSession:
    """One scene served to every front end; see the module docstring. Build it on the thread that will call tick()
    (Taichi compiles a scene only on the thread that started it)."""

    def __init__(self, scene_path, arch: str = "auto", overrides=(), scenes_dir=SCENES_DIR, wait_for_viewer: bool = False,
                 on_build=None):
        """scene_path: the scene to start with (any file the operator names; a switch later takes only files in
        scenes_dir). overrides: {dotted key: value} or `dotted.key=value` texts (as `--set`), applied on every rebuild of
        this scene.
        wait_for_viewer: hold the scene at t = 0 until viewer_joined() is called. on_build: called as
        on_build(stage, scene_name, seconds, notes) with stage "start" (seconds 0) and "done" around every build (notes:
        the built scene's notes, texts)."""
        self.arch = arch
        self.scenes_dir = Path(scenes_dir).resolve()
        self.on_build = on_build or (lambda stage, name, seconds, notes=(): None)
        self.running, self.speed, self.single_steps = True, 1.0, 0
        self.waiting_for_viewer = wait_for_viewer
        self.quality = "scene file"
        self.overrides: dict = override_key_values(overrides)  # dotted scene key -> value, applied on every (re)build
        self.added_points: list[dict] = []    # items of bleed points added at run time (re-added after a rebuild)
        self.removed_points: set[str] = set()  # scene-file bleed points removed at run time
        self.spare_suction = dict(SPARE_SUCTION)
        self.builds = 0                       # scene builds so far (1 after start-up)
        self.build_seconds: list[tuple[str, float]] = []  # (scene name, wall seconds) per build
        self.notice = ""                      # what the last refused or failed action was, for the front end
        self.broken: str | None = None        # the field that became non-finite; the scene stops until reset
        self._commands: queue.Queue = queue.Queue(maxsize=MAX_PENDING)
        self._lock = threading.Lock()
        self._pending_parameters: dict[str, float] = {}   # latest value per live parameter, applied by tick
        self._pending_placements: dict[str, tuple] = {}   # latest hand placement per tool, applied by tick
        self._pending_switch = _NO_SWITCH                 # the scene the latest switch asked for, applied by tick
        self.resting: set[str] = set()        # tools that rest on the tissue while placed by hand
        self._rebuild_at: float | None = None
        self._anchor = None                   # (wall s, scene s) that real-time pacing counts from
        self.scene: Scene | None = None
        self._good = None                     # (path, overrides, config, inputs) of the last scene that built
        self.scene_path = Path(scene_path)
        self._build(self.scene_path, first=True)

    # --- what the session offers ------------------------------------------------------------
    def scene_choices(self) -> list[str]:
        """The scenes a switch may pick: the YAML files in scenes_dir (as "scenes/<file>"), and the current one."""
        names = sorted(f"scenes/{path.name}" for path in self.scenes_dir.glob("*.yaml") if path.is_file())
        current = self.scene_name_of(self.scene_path)
        return names if current in names else [current, *names]

    def scene_name_of(self, path: Path) -> str:
        path = Path(path).resolve()
        if path.parent == self.scenes_dir:
            return f"scenes/{path.name}"
        return str(path)

    def parameters(self) -> dict:
        """The running scene's parameters (sims.scene.parameters.SceneParameter by key)."""
        return self.scene.parameters()

    def parameter_value(self, key: str):
        """The value a parameter will have once queued changes are applied."""
        with self._lock:
            if key in self._pending_parameters:
                return self._pending_parameters[key]
        parameter = self.parameters().get(key)
        if parameter is not None and not parameter.live and parameter.config_key in self.overrides:
            return self.overrides[parameter.config_key]
        return self.scene.parameter_value(key)

    @property
    def rebuild_pending(self) -> bool:
        return self._rebuild_at is not None

    @property
    def script_ended(self) -> bool:
        """The scene's script (tool paths, bleed keyframes) has played to its end."""
        end = self.scene.script_end_s()
        return end > 0 and self.scene.time_s > end

    # --- commands (any thread) --------------------------------------------------------------
    def _queue(self, command: commands.Command) -> None:
        try:
            self._commands.put_nowait(command)
        except queue.Full:
            raise Refused(f"{MAX_PENDING} changes are waiting already; try again in a moment") from None

    def set_parameter(self, key: str, value, clamp: bool = True):
        """Change a parameter of parameters(): live ones from the next step, the others by a rebuild (REBUILD_DELAY_S
        after the last such change). With clamp, a value outside the range is put inside; a value that is not a
        finite number is Refused. Returns the value used."""
        parameter = self.parameters().get(key)
        if parameter is None:
            raise Refused(f"{key}: not a parameter of this scene")
        value = checked_number(parameter.spec, value, clamp=clamp)
        if parameter.live:
            with self._lock:
                fresh = key not in self._pending_parameters
                self._pending_parameters[key] = value
            if fresh:
                self._queue(commands.SetParameters())
        else:
            self._queue(commands.RebuildWith(parameter.config_key, value))
        return value

    def reset_parameters(self, group: str) -> None:
        """Every parameter whose key starts with `group.` back to its default (tissue: the scene's preset)."""
        preset = params.TISSUE_PRESETS[self.scene.config["tissue"]["preset"]]
        for key, parameter in self.parameters().items():
            if key.startswith(group + ".") or (group == "" and "." not in key):
                name = key.rsplit(".", 1)[1]
                self.set_parameter(key, preset[name] if group == "tissue" else parameter.spec.default)

    def set_quality(self, name: str) -> None:
        if name not in QUALITY:
            raise Refused(f"quality {params.quote(name)}: expected one of {', '.join(QUALITY)}")
        self._queue(commands.SetQuality(name))

    def switch_scene(self, name: str) -> None:
        """Another scene of scene_choices() (keeps the quality preset, forgets the changes made to this one)."""
        if not isinstance(name, str) or name not in self.scene_choices():
            raise Refused(f"scene {params.quote(name)}: not one of the scenes offered")
        path = self.scenes_dir / Path(name).name if name.startswith("scenes/") else self.scene_path
        if path.resolve().parent != self.scenes_dir and path.resolve() != self.scene_path.resolve():  # a link out of scenes/
            raise Refused(f"scene {params.quote(name)}: not in {self.scenes_dir}")
        self._request_switch(path)

    def back_to_scene_file(self) -> None:
        """The scene as its file says: forgets every change but the quality preset (a rebuild)."""
        self._request_switch(None)

    def _request_switch(self, path: Path | None) -> None:
        """Queue a switch to path (None: the current scene's file); a burst of switches builds once, the last one
        asked for (each build takes seconds: queued one by one, 10 switches froze the lab for 21 s)."""
        with self._lock:
            fresh = self._pending_switch is _NO_SWITCH
            self._pending_switch = path
        if fresh:
            self._queue(commands.SwitchScene())

    def reset(self) -> None:
        """Back to t = 0 with every value as it is now; every tool back to its script (also "Replay")."""
        self._queue(commands.Reset())

    def set_running(self, running: bool) -> None:
        self.running = bool(running)
        if self.running and self.broken is None and self.notice.startswith("simulation stopped"):
            self.notice = ""

    def set_speed(self, speed) -> float:
        """Simulation speed, x real time (clamped to SPEED_RANGE). Returns the speed used."""
        spec = params.ParamSpec("speed", "x real time", 1.0, *SPEED_RANGE, "")
        self.speed = checked_number(spec, speed, clamp=True)
        return self.speed

    def single_step(self) -> None:
        self._queue(commands.SingleStep())

    def viewer_joined(self) -> None:
        """A viewer is there: a session that waited for one starts."""
        self.waiting_for_viewer = False

    def take_over(self, tool: str, position_mm, direction=None, roll_deg=None) -> None:
        """A hand places a tool (it leaves its script until release). Only the latest placement per tool waits."""
        self._check_tool(tool)
        placement = (self.scene.checked_position(position_mm, "position_mm"), None if direction is None else unit_direction(direction),
                     None if roll_deg is None else float(finite_vector([roll_deg], 1, "roll_deg")[0]))
        with self._lock:
            fresh = tool not in self._pending_placements
            self._pending_placements[tool] = placement
        if fresh:
            self._queue(commands.PlaceTools())

    def set_resting(self, tool: str, on: bool) -> None:
        """Touch-the-tissue mode: the tool is taken by hand and lowered at once until it is REST_DEPTH_MM in the tissue
        below (along its axis to its tip; a flat tool straight down to its blade), and kept there while it is dragged."""
        self._check_tool(tool)
        if not checked_flag(on, f"{tool}: touch the tissue"):
            self.resting.discard(tool)
            return
        self.resting.add(tool)
        with self._lock:
            self._pending_placements.setdefault(tool, None)  # None: where the tool is when applied (_apply_placements)
        self._queue(commands.PlaceTools())

    def set_energized(self, tool: str, on: bool) -> None:
        self._check_tool(tool)
        on = checked_flag(on, f"{tool}: energized")
        self._queue(commands.SetEnergized(tool, on))

    def release(self, tool: str | None = None) -> None:
        """Back to the script: one tool, or every tool with None."""
        if tool is not None:
            self._check_tool(tool)
        self._queue(commands.Release(tool))

    def add_bleed_point(self, position_mm) -> None:
        """A bleed point with the default rate and radius at the surface texel nearest position_mm (MAX_BLEED_POINTS
        in a scene at most)."""
        if self.scene.bleeding is None:
            raise Refused("this scene has no bleeding model")
        position = self.scene.checked_position(position_mm, "position_mm")
        if len(self.scene.bleed_points) >= MAX_BLEED_POINTS:
            raise Refused(f"at most {MAX_BLEED_POINTS} bleed points in a scene")
        self._queue(commands.AddBleedPoint(position))

    def add_bleed_point_at_click(self, ray_origin, ray_direction) -> bool:
        """A bleed point where a click's ray meets the tissue; False when it misses the tissue."""
        hit = self.scene.surface_hit(ray_origin, ray_direction)
        if hit is None:
            return False
        self.add_bleed_point(hit)
        return True

    def remove_bleed_point(self, name: str | None = None) -> None:
        """Remove a bleed point (the last one with None)."""
        self._queue(commands.RemoveBleedPoint(name))

    def move_bleed_point(self, name: str, position_mm) -> None:
        position = self.scene.checked_position(position_mm, "position_mm")
        self.scene.bleed_point(name)
        self._queue(commands.MoveBleedPoint(name, position))

    # --- the simulation thread --------------------------------------------------------------
    def tick(self) -> int:
        """Apply queued changes, a due rebuild, and step the scene as far as real time x speed asks (at most
        MAX_BACKLOG_S behind). Returns the number of steps taken (0 while paused, waiting or broken)."""
        while True:
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                break
            self._anchor = None  # a change (a reset, a new time step) counts real time from now
            try:
                command.apply(self)
            except Refused as exc:  # checked when queued, but the scene may have changed since
                self.notice = str(exc)
        if self._rebuild_at is not None and time.monotonic() >= self._rebuild_at:
            self._rebuild_at = None
            self._build(self.scene_path)
        now = time.perf_counter()
        scene = self.scene
        if self._anchor is None or not self.running or self.waiting_for_viewer or self.broken:
            self._anchor = (now, scene.time_s)
        steps = 0
        if self.broken is None and not self.waiting_for_viewer:
            while self.single_steps or (self.running and (now - self._anchor[0]) * self.speed > scene.time_s - self._anchor[1]):
                self.single_steps = max(0, self.single_steps - 1)
                scene.step()
                steps += 1
                if scene.steps % FINITE_CHECK_EVERY == 0 and self._check_finite():
                    break
                if (now - self._anchor[0]) * self.speed - (scene.time_s - self._anchor[1]) > MAX_BACKLOG_S:
                    self._anchor = (now, scene.time_s)
                if time.perf_counter() - now > 0.05:  # give the front end its frame
                    break
        return steps

    def seconds_to_next_step(self) -> float:
        """Wall seconds until tick() has a step to take (0: one is due now), as far as the clock decides; a queued
        command can change that at any time, so a front end waits at most about a frame."""
        if self._anchor is None or self.single_steps or not self._commands.empty():
            return 0.0
        if not self.running or self.waiting_for_viewer or self.broken:
            return float("inf")
        due = self._anchor[0] + (self.scene.time_s - self._anchor[1]) / self.speed
        return max(0.0, due - time.perf_counter())

    def _check_finite(self) -> bool:
        bad = self.scene.non_finite_field()
        if bad is not None:
            self.broken = bad
            self.running = False
            self.notice = f"simulation stopped: {bad} became non-finite at step {self.scene.steps} (t = {self.scene.time_s:.2f} s); press Reset"
        return bad is not None

    # --- internals (simulation thread) --------------------------------------------------------
    def _check_tool(self, tool: str) -> None:
        if not isinstance(tool, str) or tool not in {item.name for item in self.scene.instruments}:
            raise Refused(f"no instrument {params.quote(tool)} in this scene")

    def _apply_parameters(self) -> None:
        """Apply the latest value of each live parameter; one that would take the explicit heat scheme past its
        substep cap (sims.heat.cautery.MAX_SUBSTEPS) is put back and refused."""
        with self._lock:
            pending, self._pending_parameters = self._pending_parameters, {}
        for key, value in pending.items():
            if key not in self.scene.parameters():  # a rebuild may have dropped it
                continue
            old = self.scene.parameter_value(key)
            changed = self.scene.set_parameter(key, value)
            try:
                checks.check_runnable(self.scene)
            except ConfigError as exc:
                self.scene.set_parameter(key, old)
                self.notice = f"refused: {key} = {value:g}: {exc.message}"
                continue
            self.overrides.update(changed)

    def _apply_placements(self) -> None:
        with self._lock:
            pending, self._pending_placements = self._pending_placements, {}
        for tool, placement in pending.items():
            if tool not in {item.name for item in self.scene.instruments}:
                continue
            if placement is None:  # set_resting: lowered where it is now, unless switched off since
                if tool not in self.resting:
                    continue
                pose = self.scene.instrument(tool).pose_at(self.scene.time_s)
                placement = (pose.position_mm, pose.direction, pose.roll_deg)
            position, direction, roll = placement
            try:
                if tool in self.resting:
                    self.scene.rest_on_tissue(tool, position, REST_DEPTH_MM, direction, roll)
                else:
                    self.scene.take_over(tool, position, direction, roll)
            except Refused as exc:  # (checked when queued; a rebuild may have moved the tissue) the others still move
                self.notice = f"refused: {exc}"

    def _rebuild_with(self, config_key: str, value) -> None:
        self.overrides[config_key] = value
        self._rebuild_at = time.monotonic() + REBUILD_DELAY_S

    def _apply_quality(self, name: str) -> None:
        self.quality = name
        for key in {key for preset in QUALITY.values() for key in preset}:
            self.overrides.pop(key, None)
        self.overrides.update(QUALITY[name])
        self._rebuild_at = time.monotonic() + REBUILD_DELAY_S

    def _apply_switch(self) -> None:
        with self._lock:
            path, self._pending_switch = self._pending_switch, _NO_SWITCH
        if path is not _NO_SWITCH:
            self._switch(self.scene_path if path is None else path)

    def _switch(self, path: Path) -> None:
        """Another scene: keeps the quality preset, forgets the changes made to this one."""
        self.overrides = dict(QUALITY[self.quality])
        self.added_points, self.removed_points = [], set()
        self.spare_suction = dict(SPARE_SUCTION)
        self.resting.clear()
        self._rebuild_at = None
        self._build(path)

    def _reset(self) -> None:
        self.scene.reset()
        if self.broken is not None:
            self.broken, self.running = None, True
        if self.notice.startswith("simulation stopped"):
            self.notice = ""

    def _add_point(self, position) -> None:
        if len(self.scene.bleed_points) >= MAX_BLEED_POINTS:
            raise Refused(f"at most {MAX_BLEED_POINTS} bleed points in a scene")
        taken = {point.name for point in self.scene.bleed_points} | self.removed_points
        number = len(self.scene.bleed_points) + 1
        while f"point{number}" in taken:
            number += 1
        defaults = params.BLEED_POINT
        texel = self.scene.texel_near(position)
        point = self.scene.add_bleed_point(f"point{number}", self.scene.surface.position_mm[texel], defaults["rate_ml_s"].default,
                                           defaults["radius_mm"].default)
        self.added_points.append(point.item)

    def _remove_point(self, name: str | None) -> None:
        if not self.scene.bleed_points:
            return
        point = self.scene.bleed_points[-1] if name is None else self.scene.bleed_point(name)
        self.scene.remove_bleed_point(point.name)
        if any(item is point.item for item in self.added_points):
            self.added_points = [item for item in self.added_points if item is not point.item]
        else:
            self.removed_points.add(point.name)

    def _spare_sucker(self, scene: Scene) -> Instrument:
        """A suction cannula for scenes that bleed without one, parked above the front left of the tissue, in view, its
        shaft leaning back away from the viewer (as a hand across the table holds it)."""
        lo, hi = scene.surface.vertices_mm.min(axis=0), scene.surface.vertices_mm.max(axis=0)
        spot = np.array([lo[0] + 0.2 * (hi[0] - lo[0]), lo[1] + 0.35 * (hi[1] - lo[1]), hi[2] + 6.0])
        parked = Pose(spot, np.array([0.0, -0.6, -1.0]), 0.0, False, 20.0)
        name = "sucker" if all(tool.name != "sucker" for tool in scene.instruments) else "spare_sucker"
        return Instrument(name, dict(SPARE_SUCKER_SHAPE), parked, suction=self.spare_suction)

    def _build(self, path: Path, first: bool = False) -> None:
        """Build the scene at path with the overrides; see the module docstring for what happens when that fails.
        Every build after the first starts a fresh Taichi runtime: Taichi frees no field of a dropped scene and allows
        512 field trees per runtime (a hemostasis build makes 14), and a fresh runtime builds faster too."""
        name = self.scene_name_of(path)
        self.on_build("start", name, 0.0, ())
        started = time.perf_counter()
        try:
            config = load_scene_config(path, fitting_overrides(path, self.overrides))
            inputs = load_inputs(config)
        except ConfigError as exc:
            if first:
                raise
            good_path, good_overrides, _, _ = self._good
            self.overrides = dict(good_overrides)
            self.notice = f"not {'rebuilt' if path == good_path else 'switched'}: {exc}"
            self.on_build("done", self.scene.name, time.perf_counter() - started, ())
            return
        notice = ""
        if not first:  # the old scene stays readable (config, surface: NumPy) for callers on other threads, but
            backend.shutdown()  # its fields are gone: only the simulation thread touches fields, after this build
        try:
            scene = Scene(config, self.arch, inputs)
            checks.check_runnable(scene)
        except Exception as exc:  # whatever failed, the old scene is gone: the last good one comes back from memory
            if first:
                raise
            path, overrides, config, inputs = self._good
            self.overrides = dict(overrides)
            backend.shutdown()
            scene = Scene(config, self.arch, inputs)
            notice = f"not switched: {exc if isinstance(exc, ConfigError) else f'{type(exc).__name__}: {exc}'}"
        self._good = (path, dict(self.overrides), config, inputs)
        self.scene_path, self.scene, self.notice, self.broken = path, scene, notice, None
        self.builds += 1
        if scene.bleeding is not None:
            for point in [point for point in scene.bleed_points if point.name in self.removed_points]:
                scene.remove_bleed_point(point.name)
            self.added_points = [scene.add_bleed_point(item["name"], item["position_mm"], item["rate_ml_s"], item["radius_mm"]).item
                                 for item in self.added_points]
            if not any(tool.suction for tool in scene.instruments):
                scene.add_instrument(self._spare_sucker(scene))
        self.resting &= {tool.name for tool in scene.instruments}
        self._anchor = None
        seconds = time.perf_counter() - started
        self.build_seconds.append((scene.name, seconds))
        self.on_build("done", scene.name, seconds, tuple(text for _, text in checks.notes(scene)))
