"""The models a scene runs, behind one interface (SceneModel) and built from one registry (MODELS).

A model is a package that knows nothing of the others (sims.heat, sims.blood); its entry here adapts it to the scene:
it is built by `from_config(surface, config, links)`, steps, resets, hands the look its changed tiles and reads, gives
its state arrays and metrics and takes its live parameters by `set(key, value)`. What couples two models (a bleed
slowed where the tissue coagulated) goes through the SceneLinks the scene hands over, never from model to model.
A new model is one package, one class here and one line in MODELS. The scene steps its models in MODELS' order,
whatever order the scene file names them in.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class SceneLinks:
    """What a scene hands its models: its instruments (sims.scene.instruments.Instrument, the list the scene keeps), the
    surface texel (row, col) nearest a world position (mm), and 1 - exp(-Omega) at a surface texel (0 without heat)."""

    instruments: list
    texel_near: Callable[[np.ndarray], tuple[int, int]]
    coagulated_fraction: Callable[[tuple[int, int]], float]


class SceneModel:
    """One model of a scene. Subclasses set `name` (its key in MODELS and in the scene file's `models`), `sections`
    (the scene config's sections whose live parameters it reads) and `look_input` (the keyword under which the look
    takes its display reads and layer: sims.look.display_tiles.DisplayTiles, sims.look.compose.Composer.compose;
    None for a model the look does not show, which then needs no display methods)."""

    name: str
    sections: tuple[str, ...]
    look_input: str | None = None
    display_reach = 0  # display texels over which the look smooths this model's layer in each pass

    def __init__(self, config: dict):
        self.config = config

    @classmethod
    def from_config(cls, surface, config: dict, links: SceneLinks) -> "SceneModel":
        """The model on a sims.surface.texels.TissueSurface for a validated scene config."""
        return cls(surface, config, links)

    def step(self, dt: float, time_s: float) -> bool:
        """Advance one step of dt s from time_s; True when any state changed (the scene then checks it for NaN)."""
        raise NotImplementedError

    def advance_look(self, dt: float) -> None:
        """What the look keeps of this model over time (a fading trail), after every model stepped."""

    def reset(self) -> None:
        """Back to t = 0 with the current parameters."""
        raise NotImplementedError

    def set(self, key: str, value) -> None:
        """A live parameter (`section.name` of `sections`, already checked) from the next step on."""
        section, _, name = key.partition(".")
        if section not in self.sections:
            raise KeyError(f"{key}: not a parameter of the {self.name} model")
        self.config[section][name] = value  # the model reads its sections every step

    def display_reads(self):
        """(taps, grid shape, grid tile) of the grid the look reads (sims.look.display_tiles.DisplayTiles)."""
        raise NotImplementedError

    def look_layer(self):
        """What the look composes from (sims.look.compose.Composer.compose)."""
        raise NotImplementedError

    def take_changed_tiles(self, shows_temperature: bool):
        """(rows, cols) bool of the model's grid tiles changed since the last call, or None."""
        raise NotImplementedError

    def state_arrays(self, display_grid: bool = True) -> dict:
        """Its arrays of state.npz (docs/guide/headless.md); display_grid False: on its own grid (for a NaN check)."""
        raise NotImplementedError

    def metrics(self, time_s: float, dt: float) -> dict:
        """Its entry of metrics.json (under its name)."""
        raise NotImplementedError

    def take_warning(self) -> str | None:
        """Once: why the model lost something (blood past the tissue's edge), else None."""
        return None


class HeatModel(SceneModel):
    """The layered cautery (sims.heat) under the scene's heating tools, shown through its display sampling."""

    name, sections, look_input = "cautery", ("tissue", "cautery"), "heat"

    def __init__(self, surface, config: dict, links: SceneLinks):
        from sims.heat.cautery import Cautery
        from sims.heat.display import HeatDisplay
        from sims.scene.instruments import InstrumentFields
        from sims.surface.resample import model_grid

        super().__init__(config)
        self.heat_surface, resampler = model_grid(surface, config["cautery"]["heat_grid_divisor"])
        self.instrument_fields = InstrumentFields([tool for tool in links.instruments if tool.suction is None])
        self.cautery = Cautery(self.heat_surface, config["tissue"], config["cautery"], self.instrument_fields,
                               scheme=config["cautery"]["scheme"])
        self.heat_display = HeatDisplay(self.cautery, resampler)
        self.active_tool = None       # (name, position mm, last move mm) of the heating tool last seen energized
        self._section_sampler = None  # sims.heat.section.SectionSampler, made on the first burn_section()
        self._coagulated: dict = {}   # heat grid texel -> 1 - exp(-Omega) read since the burn last changed

    def step(self, dt: float, time_s: float) -> bool:
        self.instrument_fields.set_time(time_s)
        self._note_active_tool()
        self.cautery.step(dt)
        changed = self.cautery.tiles.awake or self.cautery.scheme == "implicit"
        if changed:
            self._coagulated.clear()
        return changed

    def _note_active_tool(self) -> None:
        """Remember the energized heating tool last seen (the first when several are) and which way it moved."""
        for tool, pose in zip(self.instrument_fields.instruments, self.instrument_fields.poses):
            if pose.energized:
                position = np.asarray(pose.position_mm, np.float64)
                name, last, moved = self.active_tool or (None, position, np.zeros(3))
                step = position - last
                if name == tool.name and np.linalg.norm(step) > 0.05:  # mm: a move, not jitter
                    moved = step
                elif name != tool.name:
                    moved = np.zeros(3)
                self.active_tool = (tool.name, position, moved)
                return

    def reset(self) -> None:
        self.cautery.reset()
        self.active_tool = None
        self._coagulated.clear()

    def burn_section(self, half_length_mm: float, samples: int):
        """sims.heat.section.BurnSection across the stroke of the most recently energized heating tool (along the
        texture's u direction while it has not moved), or None before any tool was energized."""
        if self.active_tool is None:
            return None
        if self._section_sampler is None:
            from sims.heat.section import SectionSampler

            self._section_sampler = SectionSampler(self.heat_surface)
        name, position, moved = self.active_tool
        r, c = self._section_sampler.nearest(position[None])[0]
        across = np.cross(self.heat_surface.normal[r, c].astype(np.float64), moved)  # zero while it has not moved
        section = self._section_sampler.section(self.cautery, position, across, half_length_mm, samples)
        section.tool = name
        return section

    def coagulated_fraction(self, texel_rc) -> float:
        """1 - exp(-Omega) under a surface texel, read from the device once per heat texel while the burn does not
        change (step forgets the values when the cautery changed)."""
        coarse = self.heat_display.coarse_texel(texel_rc)
        if coarse not in self._coagulated:
            self._coagulated[coarse] = float(1.0 - np.exp(-float(self.cautery.omega[coarse])))
        return self._coagulated[coarse]

    def display_reads(self):
        return self.heat_display.taps(), self.heat_surface.mask.shape, self.cautery.tiles.tile

    def look_layer(self):
        return self.heat_display

    def take_changed_tiles(self, shows_temperature: bool):
        return self.cautery.take_changed_tiles(shows_temperature)

    def state_arrays(self, display_grid: bool = True) -> dict:
        return self.heat_display.arrays(display_grid)

    def metrics(self, time_s: float, dt: float) -> dict:
        return {**self.heat_display.metrics(), "heat_scheme": self.cautery.scheme,
                "heat_substeps_per_step": self.cautery.substeps(dt),
                "heat_solver_iterations_last_step": self.cautery.last_iterations}


class BloodModel(SceneModel):
    """A bleeding method (sims.blood) fed by the scene's bleed points and emptied by its suction tools, shown through
    the look's film (sims.look.film)."""

    name, sections, look_input = "bleeding", ("bleeding", "look"), "film"

    def __init__(self, surface, config: dict, links: SceneLinks):
        from sims.blood.methods import build_bleeding
        from sims.look.film import BloodFilm
        from sims.scene.bleed_points import BleedPoint

        super().__init__(config)
        self.links = links
        self.bleeding = build_bleeding(surface, config)
        self.film = BloodFilm(self.bleeding)
        self.bleed_points = [BleedPoint(item) for item in config["bleed_points"]]
        self.display_reach = self.film.display_per_texel // 2

    def _throttled(self, point, time_s: float, rate: float) -> tuple[tuple[int, int], float]:
        """(the surface texel under the point, its set rate (ml/s) after coagulation of the tissue there)."""
        texel = self.links.texel_near(point.position_at(time_s))
        return texel, rate * (1.0 - self.links.coagulated_fraction(texel))

    def rates(self, time_s: float) -> dict:
        """Current rate (ml/s) of every bleed point, after coagulation of the tissue under it."""
        return {point.name: self._throttled(point, time_s, point.rate_at(time_s))[1] for point in self.bleed_points}

    def step(self, dt: float, time_s: float) -> bool:
        for point in self.bleed_points:
            rate = point.rate_at(time_s)
            if rate > 0.0:
                texel, rate = self._throttled(point, time_s, rate)
                self.bleeding.spawn_rate(point.name, texel, rate, dt, point.item["radius_mm"])
        suction = []
        for instrument in self.links.instruments:
            if instrument.suction is not None:
                pose = instrument.pose_at(time_s)
                if pose.energized:
                    suction.append((pose.position_mm, instrument.suction["radius_mm"], instrument.suction["rate_ml_s"]))
        self.bleeding.step(dt, suction)
        return self.bleeding.moved

    def advance_look(self, dt: float) -> None:
        self.film.advance(dt, self.config["look"]["blood_trail_s"])

    def reset(self) -> None:
        self.bleeding.reset()
        self.film.reset()

    def display_reads(self):
        return self.film.taps(), self.film.trail.shape, self.film.tile

    def look_layer(self):
        return self.film

    def take_changed_tiles(self, shows_temperature: bool):
        return self.film.take_touched()

    def state_arrays(self, display_grid: bool = True) -> dict:
        return self.bleeding.state_arrays(display_grid)

    def metrics(self, time_s: float, dt: float) -> dict:
        return {**self.bleeding.metrics(), "bleed_rates_ml_s": self.rates(time_s)}

    def take_warning(self) -> str | None:
        return self.bleeding.take_warning()


MODELS: dict[str, type[SceneModel]] = {"cautery": HeatModel, "bleeding": BloodModel}  # stepping order
