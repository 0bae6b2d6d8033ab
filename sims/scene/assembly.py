"""Scene: a validated scene config -> only the models it names; step(); outputs; state files."""
import contextlib
import io
import math
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sims.core import backend
from sims.core.quoting import quote
from sims.scene import params
from sims.scene.config import ConfigError, load_scene_config
from sims.scene.models import MODELS, SceneLinks

# Parameters a scene offers (see Scene.parameters): (key prefix in the config, spec table, names that need a rebuild);
# a prefix other than "" is a section of the model that reads it (sims.scene.models). duration_s is left out: it only
# ends headless runs.
_PARAMETER_GROUPS = (
    ("", {name: spec for name, spec in params.SIMULATION.items() if name != "duration_s"}, {"texture_size"}),
    ("tissue", params.TISSUE, set()),
    ("cautery", params.CAUTERY, {"layers", "depth_mm", "heat_grid_divisor"}),
    ("bleeding", None, None),  # the table and rebuild keys of the scene's bleeding method (sims.blood.methods)
    ("look", params.LOOK, set()),
)
SHAPE_PARAMETERS = {"ball": ("radius_mm",), "capsule": ("radius_mm", "length_mm"), "spatula": ("width_mm", "thickness_mm", "length_mm"),
                    "mesh": ("sdf_resolution",)}
POSITION_MARGIN_MM = 100.0  # a hand may place a tool this far outside the mesh's bounding box at most


@dataclass(frozen=True)
class SceneParameter:
    """One number a scene offers to change. live: the models read it every step (Scene.set_parameter applies it);
    otherwise the scene must be rebuilt with it (config_key as an override). config_key: the dotted key in the scene
    config (the --set syntax), None for a bleed point or tool added at run time."""

    spec: params.ParamSpec
    live: bool
    config_key: str | None


NEAR_CACHE = 64  # positions texel_near remembers


class Refused(ValueError):
    """A value from outside (a browser, a script) that the scene does not accept; the message says why."""


def finite_vector(value, length: int = 3, name: str = "value") -> np.ndarray:
    """value as a float64 vector of `length` finite numbers, or Refused."""
    try:
        vector = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise Refused(f"{name}: expected {length} numbers, got {quote(value)}") from None
    if vector.shape != (length,) or not np.isfinite(vector).all():
        raise Refused(f"{name}: expected {length} finite numbers, got {quote(value)}")
    return vector


def unit_direction(value, name: str = "direction") -> np.ndarray:
    """value as a unit vector of 3 finite numbers, or Refused (the zero vector too)."""
    vector = finite_vector(value, 3, name)
    length = float(np.linalg.norm(vector))
    if not length > 1e-9 or not math.isfinite(length):
        raise Refused(f"{name}: must be a finite, non-zero vector, got {quote(value)}")
    return vector / length


def checked_flag(value, name: str) -> bool:
    """value if it is true or false (a checkbox's value), or Refused (bool() would take any text or dict as true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise Refused(f"{name}: must be true or false, got {quote(value)}")
    return bool(value)


def checked_number(spec: params.ParamSpec, value, clamp: bool = False) -> float | int:
    """value if the spec accepts it (clamped into its range with clamp=True; rounded for whole numbers), or Refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise Refused(f"{spec.name}: expected a number ({spec.unit}), got {quote(value)}")
    try:
        value = float(value)
    except OverflowError:  # an int beyond float's range (a 5,000-digit number from a browser)
        raise Refused(f"{spec.name}: must be finite, got {quote(value)}") from None
    if not math.isfinite(value):
        raise Refused(f"{spec.name}: must be finite, got {value}")
    if clamp:
        value = min(max(value, spec.min), spec.max)
    if spec.integer:
        value = int(round(value))
    problem = spec.check(value)
    if problem:
        raise Refused(f"{spec.name}: {problem}")
    return value


@dataclass
class SceneInputs:
    """What a scene reads from disk, read before any device starts (so a bad file fails fast and a session can keep
    the inputs of its last good build in memory)."""

    mesh: object            # sims.surface.texels.MeshArrays of the tissue
    textures: list          # one (size, size, 3) float32 colour per look stage
    surfaces: list          # one (size, size, 2) float32 height (mm) and roughness per look stage (sims.look.compose)


def load_inputs(config: dict) -> SceneInputs:
    """Read and check every input file of a validated scene config; ConfigError names the file and the key."""
    from sims.look.compose import TextureError, load_texture, stage_surface
    from sims.surface.texels import MeshError, load_mesh, read_tissue_mesh

    file = config["scene_file"]
    try:
        mesh = read_tissue_mesh(config["mesh"])
    except MeshError as exc:
        raise ConfigError(file, "mesh", f"{config['mesh']}: {exc}") from None
    textures, surfaces = [], []
    for index, stage in enumerate(config["look"]["stages"]):
        try:
            textures.append(load_texture(stage["texture"], config["texture_size"], stage["tile"]))
        except TextureError as exc:
            raise ConfigError(file, f"look.stages.{index}.texture", f"{stage['texture']}: {exc}") from None
        try:
            surfaces.append(stage_surface(stage, config["texture_size"]))
        except TextureError as exc:
            raise ConfigError(file, f"look.stages.{index}.surface", f"{stage['surface']}: {exc}") from None
    for index, item in enumerate(config["instruments"]):
        if item["shape"]["type"] == "mesh":
            key = f"instruments.{index}.shape.file"
            try:
                tool = load_mesh(item["shape"]["file"])
            except MeshError as exc:
                raise ConfigError(file, key, f"{item['shape']['file']}: {exc}") from None
            if not tool.is_watertight:
                raise ConfigError(file, key, f"{item['shape']['file']}: an instrument mesh must be closed (watertight) to have an inside")
    return SceneInputs(mesh, textures, surfaces)


class Scene:
    """Everything a browser or a script does with a scene. Time advances in fixed steps of time_step_s."""

    def __init__(self, config: dict, arch: str = "auto", inputs: SceneInputs | None = None):
        """inputs: the files of load_inputs(config), read now when not given."""
        from sims.surface.texels import MeshError, build_surface

        self.config = config
        self.file = config["scene_file"]
        size = config["texture_size"]
        if "cautery" in config["models"]:  # before anything is read or built: a refused size costs nothing
            from sims.heat.cautery import LayerBudget, check_layer_budget
            from sims.surface.resample import coarse_grid_size

            try:
                check_layer_budget(coarse_grid_size(size, config["cautery"]["heat_grid_divisor"]), config["cautery"]["layers"])
            except LayerBudget as exc:
                raise ConfigError(self.file, "cautery.layers", str(exc)) from None
        inputs = inputs or load_inputs(config)
        mesh, textures, surfaces = inputs.mesh, inputs.textures, inputs.surfaces
        self.arch = backend.init(arch)
        try:
            self.surface = build_surface(mesh, size)
        except MeshError as exc:
            raise ConfigError(self.file, "mesh", f"{config['mesh']}: {exc}") from None
        self.models = list(config["models"])
        self._unchecked = set(self.models)  # models that stepped since non_finite_field() last read them
        self.time_s, self.steps = 0.0, 0
        self._time_base = (0.0, 0, config["time_step_s"])  # time_s = t0 + (steps - n0) * dt while dt stays dt
        self.profile = False      # True: sync the device around each model and add its wall seconds to model_seconds
        self.model_seconds: dict[str, float] = {}
        from sims.look.compose import Composer
        from sims.look.display_tiles import DISPLAY_TILE, DisplayTiles
        from sims.scene.instruments import Instrument

        self.instruments = [Instrument.from_config(item) for item in config["instruments"]]
        self._triangles_mm = None     # ((F, 3, 3) the mesh's triangles, their boxes' (3, F) low and high corners) mm, for rays
        self._clearances = {}         # (tool, position, direction, roll) -> tool_clearance_mm
        self._parameters = None  # (tool and point names, parameter table) made by parameters()
        self._nearest: dict = {}      # world position (mm) -> nearest surface texel (texel_near)
        self._nearest_texel = None    # sims.surface.nearest.NearestTexel, made on the first texel_near()
        links = SceneLinks(self.instruments, self.texel_near, self.coagulated_fraction)
        self._models = {name: model.from_config(self.surface, config, links)
                        for name, model in MODELS.items() if name in self.models}  # in MODELS' (stepping) order
        texel_mm = float(np.sqrt(np.median(self.surface.texel_area_mm2[self.surface.mask])))
        self.composer = Composer(config["look"]["stages"], textures, surfaces, self.surface.fill_index, texel_mm)
        self._shown = [model for model in self._models.values() if model.look_input is not None]  # what the look reads
        reads = {model.look_input: model.display_reads() for model in self._shown}
        reach = max((model.display_reach for model in self._shown), default=0)
        self.display_tiles = DisplayTiles(self.surface.fill_index, **reads, blood_reach=reach, tile=DISPLAY_TILE)

    def model(self, name: str):
        """The scene's model of that name (sims.scene.models.MODELS), or None when it does not run it."""
        return self._models.get(name)

    # The models' own objects, for what only they offer (None without the model).
    cautery = property(lambda self: self._part("cautery", "cautery"))
    heat_display = property(lambda self: self._part("cautery", "heat_display"))
    heat_surface = property(lambda self: self._part("cautery", "heat_surface"))
    instrument_fields = property(lambda self: self._part("cautery", "instrument_fields"))
    bleeding = property(lambda self: self._part("bleeding", "bleeding"))
    film = property(lambda self: self._part("bleeding", "film"))

    def _reader(self, section: str):
        """The model of this scene that reads that config section's live parameters, or None."""
        return next((model for model in self._models.values() if section in model.sections), None)

    def _part(self, model: str, part: str):
        found = self._models.get(model)
        return None if found is None else getattr(found, part)

    @property
    def bleed_points(self) -> list:
        """The bleed points (sims.scene.bleed_points.BleedPoint) now, in the order they came; none without bleeding."""
        blood = self._models.get("bleeding")
        return [] if blood is None else blood.bleed_points

    @classmethod
    def from_file(cls, path, overrides=(), arch: str = "auto") -> "Scene":
        """Load, validate and build a scene file; overrides as sims.scene.config.load_scene_config takes them ({dotted
        key: value} or `key=value` texts). Raises ConfigError on bad input."""
        return cls(load_scene_config(path, overrides), arch)

    @property
    def name(self) -> str:
        return self.config["name"]

    @property
    def time_step_s(self) -> float:
        return self.config["time_step_s"]

    def step(self) -> None:
        """Advance one time step of time_step_s (the browser may change it between steps; time goes on from
        where it is, at the new step)."""
        dt = self.time_step_s
        if dt != self._time_base[2]:
            self._time_base = (self.time_s, self.steps, dt)
        for name, model in self._models.items():
            with self._timed(name):
                changed = model.step(dt, self.time_s)
            if changed:
                self._unchecked.add(name)
        with self._timed("compose"):
            for model in self._models.values():
                model.advance_look(dt)
        self.steps += 1
        t0, n0, _ = self._time_base
        self.time_s = t0 + (self.steps - n0) * dt  # = steps * dt exactly while dt never changed

    def burn_section(self, half_length_mm: float = 4.0, samples: int = 81):
        """sims.heat.section.BurnSection across the stroke of the most recently energized heating tool (along the texture's
        u direction while it has not moved), or None before any tool was energized or without the cautery model."""
        heat = self._models.get("cautery")
        return None if heat is None else heat.burn_section(half_length_mm, samples)

    @contextlib.contextmanager
    def _timed(self, model: str):
        """Adds the wall seconds of the block to model_seconds[model] when profiling (device synced both ends)."""
        if not self.profile:
            yield
            return
        import taichi as ti

        ti.sync()
        start = time.perf_counter()
        yield
        ti.sync()
        self.model_seconds[model] = self.model_seconds.get(model, 0.0) + time.perf_counter() - start


    # --- what a hand or a script may change -------------------------------------------------
    def parameters(self) -> dict[str, SceneParameter]:
        """Every number this scene offers to change, by key: `time_step_s`, `tissue.<name>`, `cautery.<name>`,
        `bleeding.<name>`, `instruments.<tool>.tip_temperature_c`, `instruments.<tool>.shape.<name>`,
        `instruments.<tool>.suction.<name>`, `bleed_points.<point>.<name>` (tools and points by name). The table is
        made again only when a tool or a bleed point comes or goes."""
        layout = (tuple(tool.name for tool in self.instruments), tuple(point.name for point in self.bleed_points))
        if self._parameters is None or self._parameters[0] != layout:
            self._parameters = (layout, self._parameter_table())
        return self._parameters[1]

    def _parameter_table(self) -> dict[str, SceneParameter]:
        table = {}
        for group, specs, rebuild in _PARAMETER_GROUPS:
            if group and self._reader(group) is None:
                continue
            if group == "bleeding":
                from sims.blood.methods import REBUILD_KEYS

                method = self.config["bleeding"]["method"]
                specs, rebuild = params.BLEEDING_METHODS[method], REBUILD_KEYS[method]
            for name, spec in specs.items():
                key = f"{group}.{name}" if group else name
                table[key] = SceneParameter(spec, name not in rebuild, key)
        in_file = {item["name"]: index for index, item in enumerate(self.config["instruments"])}
        for tool in self.instruments:
            index = in_file.get(tool.name)
            prefix = None if index is None else f"instruments.{index}"
            if tool.suction is None:
                table[f"instruments.{tool.name}.tip_temperature_c"] = SceneParameter(
                    params.INSTRUMENT["tip_temperature_c"], True, prefix and f"{prefix}.tip_temperature_c")
            else:
                for name, spec in params.SUCTION.items():
                    table[f"instruments.{tool.name}.suction.{name}"] = SceneParameter(spec, True, prefix and f"{prefix}.suction.{name}")
            if index is not None:
                for name in SHAPE_PARAMETERS[tool.shape["type"]]:
                    table[f"instruments.{tool.name}.shape.{name}"] = SceneParameter(params.SHAPE[name], False, f"{prefix}.shape.{name}")
        for point in self.bleed_points:
            index = self._file_index(point)
            for name, spec in params.BLEED_POINT.items():
                table[f"bleed_points.{point.name}.{name}"] = SceneParameter(spec, True, None if index is None else f"bleed_points.{index}.{name}")
        return table

    def parameter_value(self, key: str):
        """The current value of a parameter of `parameters()`."""
        group, _, rest = key.partition(".")
        if group == "instruments":
            tool_name, _, name = rest.partition(".")
            tool = self.instrument(tool_name)
            if name == "tip_temperature_c":
                return tool.base.tip_temperature_c
            part, _, name = name.partition(".")
            return (tool.shape if part == "shape" else tool.suction)[name]
        if group == "bleed_points":
            point_name, _, name = rest.partition(".")
            return self.bleed_point(point_name).item[name]
        return self.config[group][rest] if rest else self.config[group]

    def set_parameter(self, key: str, value) -> dict:
        """Set a live parameter of `parameters()` from the next step on. Returns {config key: value} of what changed in
        the scene config (to keep as overrides for a rebuild). A tool's tip temperature and a bleed point's rate hold
        from now on: keyframes that set them are dropped. Raises Refused for an unknown or rebuild-only key, a value
        that is not a finite number or outside the range."""
        parameter = self.parameters().get(key)
        if parameter is None:
            raise Refused(f"{key}: not a parameter of this scene")
        if not parameter.live:
            raise Refused(f"{key}: takes a rebuild of the scene")
        value = checked_number(parameter.spec, value)
        group, _, rest = key.partition(".")
        changed = {parameter.config_key: value}
        if group == "instruments":
            tool_name, _, name = rest.partition(".")
            tool = self.instrument(tool_name)
            if name == "tip_temperature_c":
                tool.base.tip_temperature_c = value
                changed.update(self._drop_keyframes(tool.path, "tip_temperature_c", parameter.config_key))
            else:
                tool.suction[name.partition(".")[2]] = value
        elif group == "bleed_points":
            point_name, _, name = rest.partition(".")
            point = self.bleed_point(point_name)
            point.item[name] = value
            if name == "rate_ml_s":
                changed.update(self._drop_keyframes(point.item["path"], "rate_ml_s", parameter.config_key))
        elif rest:
            self._reader(group).set(key, value)
        else:
            self.config[group] = value
        return {config_key: item for config_key, item in changed.items() if config_key is not None}

    @staticmethod
    def _drop_keyframes(path: list, name: str, config_key: str | None) -> dict:
        """Unset `name` in every keyframe of path (a slider's value holds from now on); {path config key: path}."""
        if not any(frame.get(name) is not None for frame in path):
            return {}
        for frame in path:
            frame[name] = None
        return {} if config_key is None else {config_key.rsplit(".", 1)[0] + ".path": [dict(frame) for frame in path]}

    def instrument(self, name: str):
        """The tool of that name, or Refused."""
        for tool in self.instruments:
            if tool.name == name:
                return tool
        raise Refused(f"no instrument {quote(name)} in this scene")

    def add_instrument(self, tool) -> None:
        """A suction tool added at run time (heating tools are compiled into the heat model and need a rebuild)."""
        if tool.suction is None:
            raise Refused(f"{tool.name}: only suction tools can be added to a running scene")
        if any(other.name == tool.name for other in self.instruments):
            raise Refused(f"{tool.name}: there is a tool of that name already")
        self.instruments.append(tool)

    def checked_position(self, position_mm, name: str) -> np.ndarray:
        """position_mm as 3 finite numbers (mm) within POSITION_MARGIN_MM of the tissue's bounding box, or Refused."""
        position = finite_vector(position_mm, 3, name)
        lo, hi = self.surface.vertices_mm.min(axis=0), self.surface.vertices_mm.max(axis=0)
        if (position < lo - POSITION_MARGIN_MM).any() or (position > hi + POSITION_MARGIN_MM).any():
            raise Refused(f"{name}: {position.round(1).tolist()} mm is more than {POSITION_MARGIN_MM:g} mm outside the tissue's bounding box")
        return position

    def take_over(self, name: str, position_mm, direction=None, roll_deg: float | None = None) -> None:
        """A hand places the tool (mm; direction handle -> tip, any length; roll in degrees): it leaves its script's path
        until release(). Omitted direction and roll keep the tool's current ones."""
        from sims.scene.instruments import HandPlacement

        tool = self.instrument(name)
        pose = tool.pose_at(self.time_s)
        position = self.checked_position(position_mm, f"{name}: position_mm")
        direction = unit_direction(pose.direction if direction is None else direction, f"{name}: direction")
        roll = pose.roll_deg if roll_deg is None else float(finite_vector([roll_deg], 1, f"{name}: roll_deg")[0])
        tool.hand = HandPlacement(position, direction, roll)

    def set_energized(self, name: str, on: bool) -> None:
        """A hand switches the tool on or off (until release())."""
        on = checked_flag(on, f"{name}: energized")
        self.instrument(name).energized_by_hand = bool(on)

    def release(self, name: str | None = None) -> None:
        """Give one tool (every tool with None) back to its script."""
        for tool in self.instruments if name is None else [self.instrument(name)]:
            tool.release()

    def held_tools(self) -> list[str]:
        """Names of the tools a hand holds (placed or switched), in scene order."""
        return [tool.name for tool in self.instruments if tool.held]

    def tissue_distance_mm(self, position_mm, direction) -> float | None:
        """How far the tissue is from a point along a direction (mm), or None when the ray misses it."""
        from sims.surface.raycast import first_hit

        direction = np.asarray(direction, np.float64) / np.linalg.norm(direction)
        origin = np.asarray(position_mm, np.float64)
        return first_hit(origin, direction, self._triangles_along(origin[None], direction))

    def _triangles_along(self, starts: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """The tissue's triangles (K, 3, 3) mm that rays from starts (N, 3) mm along the unit direction (3,) may cross:
        those whose bounding box meets the box holding the rays through the tissue. Few for rays close together along
        an axis (a flat tool's, straight down): each ray then costs a fraction of one through the whole mesh."""
        if self._triangles_mm is None:
            triangles = self.surface.vertices_mm[self.surface.faces]
            self._triangles_mm = triangles, np.ascontiguousarray(triangles.min(axis=1).T), np.ascontiguousarray(triangles.max(axis=1).T)
        triangles, low, high = self._triangles_mm
        tissue_low, tissue_high = low.min(axis=1), high.max(axis=1)
        through = np.linalg.norm(starts - (tissue_low + tissue_high) / 2, axis=1).max() + np.linalg.norm(tissue_high - tissue_low) / 2
        ends = starts + direction * through  # past the tissue's far side
        slack = 1e-3  # mm: a ray along a triangle's edge keeps it
        box_low, box_high = np.minimum(starts, ends).min(axis=0) - slack, np.maximum(starts, ends).max(axis=0) + slack
        keep = np.ones(len(triangles), bool)
        for axis in range(3):  # one axis at a time: rows of (3, F) compare faster than a (F, 3) array
            keep &= (low[axis] <= box_high[axis]) & (high[axis] >= box_low[axis])
        return triangles[keep]

    def _tissue_gap_mm(self, name: str, pose, behind_mm: float) -> float | None:
        """Smallest gap (mm, negative: pressed in) between the tool at this pose and the tissue, along the direction
        it is lowered (sims.scene.instruments.Instrument.contact_points_mm, lowered_along); each ray starts behind_mm back, so
        a tool pressed in still finds the surface. None when every ray misses the tissue."""
        from sims.surface.raycast import first_hit

        tool = self.instrument(name)
        direction = tool.lowered_along(pose)
        starts = tool.contact_points_mm(pose) - direction * behind_mm
        triangles = self._triangles_along(starts, direction)
        hits = [hit for hit in (first_hit(start, direction, triangles) for start in starts) if hit is not None]
        return min(hits) - behind_mm if hits else None

    def tool_clearance_mm(self, name: str) -> float | None:
        """Gap between the tool and the tissue, mm (negative: pressed in), or None when there is no tissue to meet:
        measured along the tool's axis from its tip, or for a flat tool straight down from its blade (the way
        rest_on_tissue lowers it)."""
        pose = self.instrument(name).pose_at(self.time_s)
        key = (name, tuple(pose.position_mm), tuple(pose.direction), pose.roll_deg)
        if key not in self._clearances:  # the stats ask twice a second; a tool at rest needs no new ray
            if len(self._clearances) > 64:
                self._clearances.clear()
            self._clearances[key] = self._tissue_gap_mm(name, pose, behind_mm=5.0)
        return self._clearances[key]

    def rest_on_tissue(self, name: str, position_mm, depth_mm: float, direction=None, roll_deg=None) -> float | None:
        """Place the tool by hand so that it is depth_mm into the tissue below position_mm, as a hand rests it: lowered
        along its axis until its tip is in, or a flat tool straight down until its blade's lowest point is in. Returns
        the distance moved (mm), or None when there is no tissue under it (then it is placed at position_mm)."""
        self.take_over(name, position_mm, direction, roll_deg)
        tool = self.instrument(name)
        pose = tool.pose_at(self.time_s)
        reach = float(np.ptp(self.surface.vertices_mm, axis=0).max()) + POSITION_MARGIN_MM  # starts behind any tissue
        gap = self._tissue_gap_mm(name, pose, reach)
        if gap is None:
            return None
        moved = gap + float(depth_mm)
        tool.hand.position_mm = tool.hand.position_mm + tool.lowered_along(pose) * moved
        return moved

    def script_end_s(self) -> float:
        """Time of the last keyframe of any tool or bleed point (0 when nothing is scripted)."""
        ends = [tool.script_end_s() for tool in self.instruments]
        ends += [frame["t_s"] for point in self.bleed_points for frame in point.item["path"]]
        return max(ends, default=0.0)

    def bleed_point(self, name: str):
        """The bleed point of that name, or Refused."""
        for point in self.bleed_points:
            if point.name == name:
                return point
        raise Refused(f"no bleed point {quote(name)} in this scene")

    def _file_index(self, point) -> int | None:
        """The point's index in the scene file's bleed_points, or None for a point added at run time."""
        return next((index for index, item in enumerate(self.config["bleed_points"]) if item is point.item), None)

    def remove_bleed_point(self, name: str) -> None:
        point = self.bleed_point(name)
        self.bleed_points.remove(point)

    def move_bleed_point(self, name: str, position_mm) -> dict:
        """Move a bleed point to the surface texel nearest position_mm (it leaves its path). Returns {config key: value}
        of what changed in the scene config."""
        point = self.bleed_point(name)
        texel = self.texel_near(self.checked_position(position_mm, f"{name}: position_mm"))
        point.item["position_mm"] = [float(v) for v in self.surface.position_mm[texel]]
        point.item["path"] = []
        index = self._file_index(point)
        if index is None:
            return {}
        return {f"bleed_points.{index}.position_mm": list(point.item["position_mm"]), f"bleed_points.{index}.path": []}

    def surface_hit(self, ray_origin, ray_direction) -> np.ndarray | None:
        """The surface texel position (mm) where a ray (a click) first meets the tissue, or None."""
        origin = finite_vector(ray_origin, 3, "ray_origin")
        if np.abs(origin).max() > 1.0e6:
            raise Refused(f"ray_origin: {origin.tolist()} is more than a kilometre away")
        direction = unit_direction(ray_direction, "ray_direction")
        distance = self.tissue_distance_mm(origin, direction)
        if distance is None:
            return None
        hit = origin + distance * direction
        return self.surface.position_mm[self.texel_near(hit)].astype(np.float64)

    def texel_near(self, position_mm) -> tuple[int, int]:
        """(row, col) of the surface texel nearest to a world position (mm); the last NEAR_CACHE answers are kept (a
        bleed point asks every step, mostly from where it was)."""
        key = tuple(float(v) for v in np.asarray(position_mm, np.float64).ravel())
        texel = self._nearest.get(key)
        if texel is None:
            if self._nearest_texel is None:
                from sims.surface.nearest import NearestTexel

                self._nearest_texel = NearestTexel(self.surface)
            texel = tuple(int(v) for v in self._nearest_texel.query(np.asarray([key]))[0])
            if len(self._nearest) >= NEAR_CACHE:
                self._nearest.clear()
            self._nearest[key] = texel
        return texel

    def coagulated_fraction(self, texel_rc) -> float:
        """1 - exp(-Omega) at a surface texel (sims.scene.models.HeatModel.coagulated_fraction); 0 without the
        cautery model. What couples the bleeding to the burn."""
        heat = self._models.get("cautery")
        return 0.0 if heat is None else heat.coagulated_fraction(texel_rc)

    def bleed_rates(self) -> dict:
        """Current rate (ml/s) of every bleed point, after coagulation of the tissue under it."""
        blood = self._models.get("bleeding")
        return {} if blood is None else blood.rates(self.time_s)

    def add_bleed_point(self, name: str, position_mm, rate_ml_s: float, radius_mm: float = 0.5):
        """A new bleed point from now on (bleeding model only); returns it."""
        from sims.scene.bleed_points import BleedPoint

        if "bleeding" not in self._models:
            raise Refused("this scene has no bleeding model")
        if any(point.name == name for point in self.bleed_points):
            raise Refused(f"there is a bleed point {quote(name)} already")
        position = self.checked_position(position_mm, f"{name}: position_mm")
        rate = checked_number(params.BLEED_POINT["rate_ml_s"], rate_ml_s)
        radius = checked_number(params.BLEED_POINT["radius_mm"], radius_mm)
        point = BleedPoint({"name": name, "position_mm": [float(v) for v in position], "rate_ml_s": rate,
                            "radius_mm": radius, "start_s": 0.0, "stop_s": None, "path": []})
        self.bleed_points.append(point)
        return point

    def reset(self) -> None:
        """Back to t = 0 with the current parameters; every tool back to its script."""
        self.release()
        self.time_s, self.steps = 0.0, 0
        self._time_base = (0.0, 0, self.time_step_s)
        self._unchecked = set(self.models)
        for model in self._models.values():
            model.reset()

    # --- outputs ------------------------------------------------------------------------------
    def composite(self, wanted: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """The display texture's base colour (H, W, 3) uint8, image orientation (row 0 = v 1); material_maps() then
        gives its normal and roughness maps. It shows the state after the last step, whenever it is called.
        wanted: (tile, flags) from a front end that reads only some of the maps now, flags (rows, cols) bool over
        tile x tile texel blocks (pending_display_changes' grid): only those blocks are brought up to date, the rest
        keep what they showed and their work waits (sims.look.display_tiles). None: every texel is up to date."""
        with self._timed("compose"):
            self._collect_display_changes()
            tiles = self.display_tiles
            if wanted is not None and (wanted[0] != tiles.tile or np.shape(wanted[1]) != tiles.grid):
                raise ValueError(f"wanted: {np.shape(wanted[1])} blocks of {wanted[0]} texels; the display has "
                                 f"{tiles.grid} tiles of {tiles.tile}")
            tiles.plan(None if wanted is None else wanted[1])
            return self.composer.compose(tiles, **{model.look_input: model.look_layer() for model in self._shown})

    def pending_display_changes(self) -> tuple[int, np.ndarray]:
        """(tile, flags): the tile x tile texel blocks of the maps that the next composite() would change (flags
        (rows, cols) bool, row-major from row 0), so a front end can ask for only some of them."""
        with self._timed("compose"):
            self._collect_display_changes()
            return self.display_tiles.tile, self.display_tiles.pending_outputs()

    def _collect_display_changes(self) -> None:
        """Hand the tiles the burn and the film changed since the last call to the display's pending work."""
        changed = {model.look_input: model.take_changed_tiles(self.composer.shows_temperature) for model in self._shown}
        self.display_tiles.select(**changed)

    def material_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(normal (H, W, 3) uint8, roughness (H, W) uint8) of the last composite() (sims.look.compose.Composer)."""
        return self.composer.maps()

    def take_display_changes(self) -> tuple[int, np.ndarray]:
        """(tile, flags): the display tiles (tile texels a side; flags (rows, cols) bool, row-major from row 0) whose
        maps changed in the composites since the last call; a texture stream compares and encodes only those."""
        return self.display_tiles.tile, self.display_tiles.take_changed()

    def state_arrays(self, display_grid: bool = True) -> dict:
        """Arrays of docs/guide/headless.md ("state.npz") for the models this scene runs; display_grid False: each on its model's own grid
        (not resampled: what a check for NaN needs, at a fraction of the cost)."""
        state = {"texel_position_mm": self.surface.position_mm, "texel_mask": self.surface.mask}
        for model in self._models.values():
            state.update(model.state_arrays(display_grid))
        return state

    def non_finite_field(self) -> str | None:
        """Name of the first simulated field holding NaN or inf, or None (read on the models' own grids: a resampled
        value is finite when the values it is read from are). Only the models that stepped anything since the last
        call are read: the others' fields are as they were."""
        arrays = {}
        for name, model in self._models.items():
            if name in self._unchecked:
                arrays.update(model.state_arrays(False))
        self._unchecked = set()
        for name, values in arrays.items():
            if values.dtype.kind == "f" and not np.isfinite(values).all():
                self._unchecked = set(self.models)  # still broken: the next call looks again
                return name
        return None

    def take_warnings(self) -> list[tuple[str, str]]:
        """(model name, text) of each model's warning since the last call (sims.scene.models.SceneModel.take_warning)."""
        found = [(name, model.take_warning()) for name, model in self._models.items()]
        return [(name, text) for name, text in found if text]

    def metrics(self) -> dict:
        result = {"scene": self.name, "duration_s": self.time_s, "steps": self.steps, "models": self.models, "arch": self.arch}
        for name, model in self._models.items():
            result[name] = model.metrics(self.time_s, self.time_step_s)
        return result


def save_npz_atomic(path, arrays: dict) -> None:
    """Write arrays as .npz via a temp file and a rename; fixed zip timestamps make equal states equal bytes."""
    path = Path(path)
    temp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with zipfile.ZipFile(temp, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name in sorted(arrays):
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, buffer.getvalue())
    os.replace(temp, path)
