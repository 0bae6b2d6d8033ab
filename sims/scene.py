"""Scene: a validated scene config -> only the models it names; step(); outputs; state files."""
import contextlib
import io
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from sims import backend
from sims.config import ConfigError, load_scene_config


class Scene:
    """Everything a browser or a script does with a scene. Time advances in fixed steps of time_step_s."""

    def __init__(self, config: dict, arch: str = "auto"):
        from sims.compose import TextureError, load_texture
        from sims.surface import MeshError, build_surface, load_mesh

        self.config = config
        self.file = config["scene_file"]
        size = config["texture_size"]
        try:  # read every input file before the device starts, so bad input fails fast
            mesh = load_mesh(config["mesh"])
        except MeshError as exc:
            raise ConfigError(self.file, "mesh", f"{config['mesh']}: {exc}") from None
        textures = []
        for index, stage in enumerate(config["look"]["stages"]):
            try:
                textures.append(load_texture(stage["texture"], size, stage["tile"]))
            except TextureError as exc:
                raise ConfigError(self.file, f"look.stages.{index}.texture", f"{stage['texture']}: {exc}") from None
        for index, item in enumerate(config["instruments"]):
            if item["shape"]["type"] == "mesh":
                key = f"instruments.{index}.shape.file"
                try:
                    tool = load_mesh(item["shape"]["file"])
                except MeshError as exc:
                    raise ConfigError(self.file, key, f"{item['shape']['file']}: {exc}") from None
                if not tool.is_watertight:
                    raise ConfigError(self.file, key, f"{item['shape']['file']}: an instrument mesh must be closed (watertight) to have an inside")
        self.arch = backend.init(arch)
        try:
            self.surface = build_surface(mesh, size)
        except MeshError as exc:
            raise ConfigError(self.file, "mesh", f"{config['mesh']}: {exc}") from None
        self.models = list(config["models"])
        self.time_s, self.steps = 0.0, 0
        self._time_base = (0.0, 0, config["time_step_s"])  # time_s = t0 + (steps - n0) * dt while dt stays dt
        self._displayed_at = 0.0
        self.profile = False      # True: sync the device around each model and add its wall seconds to model_seconds
        self.model_seconds: dict[str, float] = {}
        from sims.compose import Composer
        from sims.instruments import Instrument

        self.instruments = [Instrument.from_config(item) for item in config["instruments"]]
        self.cautery = self.bleeding = None
        if "cautery" in self.models:
            from sims.cautery import Cautery
            from sims.instruments import InstrumentFields

            self.instrument_fields = InstrumentFields([tool for tool in self.instruments if tool.suction is None])
            self.cautery = Cautery(self.surface, config["tissue"], config["cautery"], self.instrument_fields, scheme=config["cautery"]["scheme"])
        if "bleeding" in self.models:
            from scipy.spatial import cKDTree

            from sims.sph import Bleeding, BleedPoint, auto_capacity

            capacity = auto_capacity(config["bleed_points"], config["bleeding"], config["duration_s"])
            self.bleeding = Bleeding(self.surface, config["bleeding"], config["gravity_mm_s2"], capacity)
            self.bleed_points = [BleedPoint(item) for item in config["bleed_points"]]
            rows, cols = np.nonzero(self.surface.mask)
            self._texels = np.stack([rows, cols], axis=1)
            self._texel_tree = cKDTree(self.surface.position_mm[rows, cols])
        texel_mm = float(np.sqrt(np.median(self.surface.texel_area_mm2[self.surface.mask])))
        self.composer = Composer(config["look"]["stages"], textures, self.surface.fill_index, texel_mm)

    @classmethod
    def from_file(cls, path, overrides=(), arch: str = "auto") -> "Scene":
        """Load, validate and build a scene file; raises ConfigError on bad input."""
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
        if self.cautery is not None:
            with self._timed("cautery"):
                self.instrument_fields.set_time(self.time_s)
                self.cautery.step(dt)
        if self.bleeding is not None:
            with self._timed("bleeding"):
                self._bleed(dt)
        self.steps += 1
        t0, n0, _ = self._time_base
        self.time_s = t0 + (self.steps - n0) * dt  # = steps * dt exactly while dt never changed

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

    def texel_near(self, position_mm) -> tuple[int, int]:
        """(row, col) of the surface texel nearest to a world position (mm)."""
        _, index = self._texel_tree.query(np.asarray(position_mm, np.float64))
        return tuple(int(v) for v in self._texels[index])

    def coagulated_fraction(self, texel_rc) -> float:
        """1 - exp(-Omega) at a texel; 0 without the cautery model."""
        if self.cautery is None:
            return 0.0
        return float(1.0 - np.exp(-float(self.cautery.omega[texel_rc])))

    def bleed_rates(self) -> dict:
        """Current rate (ml/s) of every bleed point, after coagulation of the tissue under it."""
        rates = {}
        for point in self.bleed_points:
            texel = self.texel_near(point.position_at(self.time_s))
            rates[point.name] = point.rate_at(self.time_s) * (1.0 - self.coagulated_fraction(texel))
        return rates

    def add_bleed_point(self, name: str, position_mm, rate_ml_s: float, radius_mm: float = 0.5):
        """A new bleed point from now on (bleeding model only); returns it."""
        from sims.sph import BleedPoint

        point = BleedPoint({"name": name, "position_mm": [float(v) for v in position_mm], "rate_ml_s": float(rate_ml_s),
                            "radius_mm": float(radius_mm), "start_s": 0.0, "stop_s": None, "path": []})
        self.bleed_points.append(point)
        return point

    def _bleed(self, dt: float) -> None:
        for point in self.bleed_points:
            rate = point.rate_at(self.time_s)
            if rate > 0.0:
                texel = self.texel_near(point.position_at(self.time_s))
                rate *= 1.0 - self.coagulated_fraction(texel)
                self.bleeding.spawn_rate(point.name, texel, rate, dt, point.item["radius_mm"])
        suction = []
        for instrument in self.instruments:
            if instrument.suction is not None:
                pose = instrument.pose_at(self.time_s)
                if pose.energized:
                    suction.append((pose.position_mm, instrument.suction["radius_mm"], instrument.suction["rate_ml_s"]))
        self.bleeding.step(dt, suction)

    def reset(self) -> None:
        self.time_s, self.steps = 0.0, 0
        self._time_base = (0.0, 0, self.time_step_s)
        self._displayed_at = 0.0
        if self.cautery is not None:
            self.cautery.reset()
        if self.bleeding is not None:
            self.bleeding.reset()

    # --- outputs ------------------------------------------------------------------------------
    def composite(self) -> np.ndarray:
        """The display texture (H, W, 3) uint8, image orientation (row 0 = v 1)."""
        with self._timed("compose"):
            if self.bleeding is not None:
                fade_s = self.bleeding.params["display_fade_s"]
                elapsed = self.time_s - self._displayed_at
                self.bleeding.update_display(float(np.exp(-elapsed / fade_s)) if fade_s > 0 and elapsed >= 0 else 0.0)
                self._displayed_at = self.time_s
            return self.composer.compose(self.cautery, self.bleeding)

    def state_arrays(self) -> dict:
        """Arrays of DESIGN section 4 for the models this scene runs."""
        state = {"texel_position_mm": self.surface.position_mm, "texel_mask": self.surface.mask}
        if self.cautery is not None:
            state.update(temperature_c=self.cautery.temperature_c(), damage_omega=self.cautery.damage_omega(), char=self.cautery.char_level())
        if self.bleeding is not None:
            state.update(self.bleeding.particle_arrays())
        return state

    def non_finite_field(self) -> str | None:
        """Name of the first simulated field holding NaN or inf, or None."""
        for name, values in self.state_arrays().items():
            if values.dtype.kind == "f" and not np.isfinite(values).all():
                return name
        return None

    def metrics(self) -> dict:
        result = {"scene": self.name, "duration_s": self.time_s, "steps": self.steps, "models": self.models, "arch": self.arch}
        if self.cautery is not None:
            result["cautery"] = {**self.cautery.metrics(), "heat_scheme": self.cautery.scheme,
                                 "heat_substeps_per_step": self.cautery.substeps(self.time_step_s),
                                 "heat_solver_iterations_last_step": self.cautery.last_iterations}
        if self.bleeding is not None:
            result["bleeding"] = {
                **self.bleeding.accounting(),
                "blood_area_mm2": self.bleeding.blood_area_mm2(),
                "capacity": self.bleeding.capacity,
                "particle_volume_ml": self.bleeding.particle_volume_ml,
                "bleed_rates_ml_s": self.bleed_rates(),
            }
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
