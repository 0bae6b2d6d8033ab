"""The models a scene can run, built by name: the cautery (sims.heat.cautery) and the bleeding methods a scene picks with
`bleeding.method`. Their parameter tables live in sims.scene.params (the scene files are checked without Taichi).

Every bleeding method is one module with the same small interface (BleedingMethod); the scene, the lab and the
runner use only that, so the sliders, stats, metrics and outputs follow the method in use.
"""
import importlib
from typing import Protocol

import numpy as np

BLEEDING_CLASSES = {"particles": ("sims.blood.particles", "Bleeding"), "height_field": ("sims.blood.height_field", "HeightFieldBleeding")}
REBUILD_KEYS = {"particles": {"capacity"}, "height_field": {"grid_divisor"}}  # parameters read only when the model is built


class BleedingMethod(Protocol):
    """Blood on a TissueSurface, in texture space. Volumes in ml, lengths in mm, times in s."""

    method: str    # its name in BLEEDING_CLASSES
    params: dict   # the scene's bleeding parameters (sims.scene.params.BLEEDING_METHODS[method]), read every step
    film_shape: tuple  # the grid of its film (sims.look.film): its own grid, or the display's
    film_display: object  # sims.surface.resample.GridResampler from that grid onto the display, or None (the same grid)
    film_clot: object  # Taichi field on that grid: clot fraction 0-1, or None
    moved: bool  # whether the last step() (or a reset) changed the blood: False while it is dry or all asleep

    def reset(self) -> None: ...
    def set_gravity(self, gravity_mm_s2) -> None: ...
    def spawn_rate(self, key, texel_rc, rate_ml_s: float, dt_s: float, radius_mm: float) -> int: ...
    def step(self, dt_s: float, suction: list = ()) -> None:
        """suction: [(position_mm (3,), radius_mm, rate_ml_s)] of the suction tools switched on."""
    def fresh_film(self, out) -> None:
        """out (a Taichi field of film_shape) = the blood's thickness now, mm."""
    def blood_area_mm2(self) -> float: ...
    def metrics(self) -> dict:
        """method, blood_area_mm2, max_thickness_mm, volume_ml and spawned_ml = on_surface_ml + suctioned_ml +
        left_surface_ml + dried_ml, then the method's own keys."""
    def state_arrays(self, display_grid: bool = True) -> dict[str, np.ndarray]:
        """blood_thickness_mm (H, W), then the method's own arrays; display_grid False: on the method's own grid
        where it has one (not resampled)."""
    def take_warning(self) -> str | None:
        """Once: a reason blood was lost, else None."""


def build_bleeding(surface, config: dict) -> BleedingMethod:
    """The bleeding method a validated scene config names, on a TissueSurface."""
    bleeding = config["bleeding"]
    module, name = BLEEDING_CLASSES[bleeding["method"]]
    cls = getattr(importlib.import_module(module), name)
    if bleeding["method"] == "particles":
        from sims.blood.particles import auto_capacity

        capacity = auto_capacity(config["bleed_points"], bleeding, config["duration_s"])
        return cls(surface, bleeding, config["gravity_mm_s2"], capacity)
    from sims.surface.resample import model_grid

    grid, resampler = model_grid(surface, bleeding["grid_divisor"])
    return cls(grid, bleeding, config["gravity_mm_s2"], display=resampler)

