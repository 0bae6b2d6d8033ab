"""The cautery model's fields at the display texture's resolution, when heat runs on a coarser grid (sims.surface.resample).

What reads the burn at display resolution (the look, state.npz) goes through here, and so does the coagulated area of
the metrics: Omega is read through its log (sims.surface.resample), so the burn a trainer sees and the area reported are the
same texels. The other numbers (the rest of the metrics, the cross-section, the bleed throttle) read the heat grid.
"""
import numpy as np
import taichi as ti

from sims.heat.cautery import LOG_OMEGA_FLOOR
from sims.surface.resample import GridReader, GridResampler

LOG_READ = ("damage_omega", "damage_omega_depth")  # arrays() read through their log: Omega spans orders of magnitude


@ti.data_oriented
class HeatDisplay(GridReader):
    """A Cautery's surface fields read at display texels (sample(), in the look's kernels) and its arrays at display
    resolution. With the same grid (resampler None) a display texel is a heat texel."""

    def __init__(self, cautery, resampler: GridResampler | None):
        super().__init__(resampler)
        self.cautery = cautery
        self._area = (None, 0.0)  # (the cautery's version it was counted at, coagulated area mm^2 on display texels)

    @ti.func
    def omega(self, r, c):
        """Omega at the surface at display texel (r, c), read through its log."""
        return self.sample_log(self.cautery.omega, r, c, LOG_OMEGA_FLOOR)

    def coarse_texel(self, texel_rc) -> tuple[int, int]:
        """The heat-grid texel under a display texel."""
        return tuple(texel_rc) if self.resampler is None else self.resampler.coarse_texel(texel_rc)

    def arrays(self, display_grid: bool = True) -> dict[str, np.ndarray]:
        """state.npz arrays at display resolution (display_grid False: on the heat grid): (H, W) surface maps,
        (L, H, W) layers, (L,) layer depths."""
        cautery = self.cautery
        arrays = cautery.arrays()
        if self.resampler is not None and display_grid:
            arrays = {name: self.resampler.array(values, LOG_OMEGA_FLOOR if name in LOG_READ else None)
                      for name, values in arrays.items()}
        arrays["layer_depth_mm"] = cautery.layer_depth_mm.astype(np.float32)
        return arrays

    def metrics(self) -> dict:
        """The cautery's metrics, the coagulated area (mm^2) counted on the display texels where the read Omega >= 1
        (with a coarser heat grid: its whole texels put the edge up to half a texel off the burn shown)."""
        metrics = self.cautery.metrics()
        if self.resampler is not None:
            version = self.cautery.version
            if self._area[0] != version:
                self._area = (version, self.resampler.area_mm2(self.cautery.damage_omega(), 1.0, LOG_OMEGA_FLOOR))
            metrics["coagulated_area_mm2"] = self._area[1]
        return metrics
