"""Scene: a validated scene config -> only the models it names (sims.scene.models), stepped and coupled; its outputs
and state files. What it offers to change is in sims.scene.parameters, what a hand does in sims.scene.hands (the
Scene's two mixins)."""
import contextlib
import io
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sims.core import backend
from sims.look.tile_mask import TileMask
from sims.scene.config import ConfigError, load_scene_config
from sims.scene.hands import HandInteraction
from sims.scene.models import MODELS, SceneLinks
from sims.scene.parameters import SceneParameters

NEAR_CACHE = 64  # positions texel_near remembers


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


class Scene(SceneParameters, HandInteraction):
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


    def script_end_s(self) -> float:
        """Time of the last keyframe of any tool or bleed point (0 when nothing is scripted)."""
        ends = [tool.script_end_s() for tool in self.instruments]
        ends += [frame["t_s"] for point in self.bleed_points for frame in point.item["path"]]
        return max(ends, default=0.0)

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

    def reset(self) -> None:
        """Back to t = 0 with the current parameters; every tool back to its script."""
        self.release()
        self.time_s, self.steps = 0.0, 0
        self._time_base = (0.0, 0, self.time_step_s)
        self._unchecked = set(self.models)
        for model in self._models.values():
            model.reset()

    # --- outputs ------------------------------------------------------------------------------
    def composite(self, wanted: TileMask | None = None) -> np.ndarray:
        """The display texture's base colour (H, W, 3) uint8, image orientation (row 0 = v 1); material_maps() then
        gives its normal and roughness maps. It shows the state after the last step, whenever it is called.
        wanted: the blocks (sims.look.tile_mask.TileMask, or a (tile, flags) pair, on pending_display_changes' grid)
        of a front end that reads only some of the maps now: only those are brought up to date, the rest keep what
        they showed and their work waits (sims.look.display_tiles). None: every texel is up to date."""
        with self._timed("compose"):
            self._collect_display_changes()
            tiles = self.display_tiles
            wanted = None if wanted is None else TileMask.of(wanted)
            if wanted is not None and (wanted.tile != tiles.tile or wanted.flags.shape != tiles.grid):
                raise ValueError(f"wanted: {wanted.flags.shape} blocks of {wanted.tile} texels; the display has "
                                 f"{tiles.grid} tiles of {tiles.tile}")
            tiles.plan(None if wanted is None else wanted.flags)
            return self.composer.compose(tiles, **{model.look_input: model.look_layer() for model in self._shown})

    def pending_display_changes(self) -> TileMask:
        """The tile x tile texel blocks of the maps that the next composite() would change (flags
        (rows, cols) bool, row-major from row 0), so a front end can ask for only some of them."""
        with self._timed("compose"):
            self._collect_display_changes()
            return TileMask(self.display_tiles.tile, self.display_tiles.pending_outputs())

    def _collect_display_changes(self) -> None:
        """Hand the tiles the burn and the film changed since the last call to the display's pending work."""
        changed = {model.look_input: model.take_changed_tiles(self.composer.shows_temperature) for model in self._shown}
        self.display_tiles.select(**changed)

    def material_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(normal (H, W, 3) uint8, roughness (H, W) uint8) of the last composite() (sims.look.compose.Composer)."""
        return self.composer.maps()

    def take_display_changes(self) -> TileMask:
        """The display tiles (tile texels a side; flags (rows, cols) bool, row-major from row 0) whose
        maps changed in the composites since the last call; a texture stream compares and encodes only those."""
        return TileMask(self.display_tiles.tile, self.display_tiles.take_changed())

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
