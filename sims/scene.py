"""Scene: a validated scene config -> only the models it names; step(); outputs; state files."""
import io
import os
import zipfile
from pathlib import Path

import numpy as np

from sims import backend
from sims.config import ConfigError, load_scene_config


class Scene:
    """Everything a browser or a script does with a scene. Time advances in fixed steps of time_step_s."""

    def __init__(self, config: dict, arch: str = "auto"):
        from sims.compose import TextureError, fill_gutters, load_texture
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
        self.cautery = None
        self._base_rgb = fill_gutters((textures[0] * 255 + 0.5).astype(np.uint8), self.surface.fill_index)
        if "cautery" in self.models:
            from sims.cautery import Cautery
            from sims.compose import Composer
            from sims.instruments import Instrument, InstrumentFields

            self.instruments = [Instrument.from_config(item) for item in config["instruments"]]
            self.instrument_fields = InstrumentFields(self.instruments)
            self.cautery = Cautery(self.surface, config["tissue"], config["cautery"], self.instrument_fields)
            self.composer = Composer(config["look"]["stages"], textures, self.surface.fill_index)

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
        """Advance one time step of time_step_s."""
        if self.cautery is not None:
            self.instrument_fields.set_time(self.time_s)
            self.cautery.step(self.time_step_s)
        self.steps += 1
        self.time_s = self.steps * self.time_step_s

    def reset(self) -> None:
        self.time_s, self.steps = 0.0, 0
        if self.cautery is not None:
            self.cautery.reset()

    # --- outputs ------------------------------------------------------------------------------
    def composite(self) -> np.ndarray:
        """The display texture (H, W, 3) uint8, image orientation (row 0 = v 1)."""
        if self.cautery is None:
            return self._base_rgb
        c = self.cautery
        return self.composer.compose(c.temperature[c.current], c.omega, c.char)

    def state_arrays(self) -> dict:
        """Arrays of DESIGN section 4 for the models this scene runs."""
        state = {"texel_position_mm": self.surface.position_mm, "texel_mask": self.surface.mask}
        if self.cautery is not None:
            state.update(temperature_c=self.cautery.temperature_c(), damage_omega=self.cautery.damage_omega(), char=self.cautery.char_level())
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
            result["cautery"] = {**self.cautery.metrics(), "heat_substeps_per_step": self.cautery.substeps(self.time_step_s)}
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
