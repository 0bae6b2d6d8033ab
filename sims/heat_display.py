"""The cautery model's fields at the display texture's resolution, when heat runs on a coarser grid (sims.resample).

What reads the burn at display resolution (the look, state.npz) goes through here; what reads numbers (metrics, the
cross-section, the bleed throttle) reads the heat grid itself.
"""
import numpy as np
import taichi as ti

from sims.resample import GridReader, GridResampler

@ti.data_oriented
class HeatDisplay(GridReader):
    """A Cautery's surface fields read at display texels (sample(), in the look's kernels) and its arrays at display
    resolution. With the same grid (resampler None) a display texel is a heat texel."""

    def __init__(self, cautery, resampler: GridResampler | None):
        super().__init__(resampler)
        self.cautery = cautery

    def coarse_texel(self, texel_rc) -> tuple[int, int]:
        """The heat-grid texel under a display texel."""
        return tuple(texel_rc) if self.resampler is None else self.resampler.coarse_texel(texel_rc)

    def arrays(self, display_grid: bool = True) -> dict[str, np.ndarray]:
        """state.npz arrays at display resolution (display_grid False: on the heat grid): (H, W) surface maps,
        (L, H, W) layers, (L,) layer depths."""
        cautery = self.cautery
        arrays = {"temperature_c": cautery.temperature_c(), "damage_omega": cautery.damage_omega(), "char": cautery.char_level(),
                  "coagulation_depth_mm": cautery.coagulation_depth_mm(), "temperature_depth_c": cautery.temperature_depth_c(),
                  "damage_omega_depth": cautery.damage_omega_depth()}
        if self.resampler is not None and display_grid:
            arrays = {name: self.resampler.array(values) for name, values in arrays.items()}
        arrays["layer_depth_mm"] = cautery.layer_depth_mm.astype(np.float32)
        return arrays
