"""The cautery model's fields at the display texture's resolution, when heat runs on a coarser grid (sims.resample).

What reads the burn at display resolution (the look, state.npz) goes through here; what reads numbers (metrics, the
cross-section, the bleed throttle) reads the heat grid itself.
"""
import numpy as np
import taichi as ti

from sims.resample import GridResampler

SURFACE_FIELDS = ("surface_temperature", "omega", "char", "coagulation_depth")  # what the look reads


@ti.data_oriented
class HeatDisplay:
    """Display-grid copies of a Cautery's surface fields (refreshed() fills them) and its arrays at display resolution.
    With the same grid (resampler None) everything is the cautery's own."""

    def __init__(self, cautery, resampler: GridResampler | None):
        self.cautery, self.resampler = cautery, resampler
        if resampler is not None:
            for name in SURFACE_FIELDS:
                setattr(self, name, ti.field(ti.f32, resampler.fine_shape))

    def refreshed(self):
        """An object with SURFACE_FIELDS (Taichi fields, display grid) holding the current burn."""
        if self.resampler is None:
            return self.cautery
        for name in SURFACE_FIELDS:
            self.resampler.field(getattr(self.cautery, name), getattr(self, name))
        return self

    def coarse_texel(self, texel_rc) -> tuple[int, int]:
        """The heat-grid texel under a display texel."""
        return tuple(texel_rc) if self.resampler is None else self.resampler.coarse_texel(texel_rc)

    def arrays(self) -> dict[str, np.ndarray]:
        """state.npz arrays at display resolution: (H, W) surface maps, (L, H, W) layers, (L,) layer depths."""
        cautery = self.cautery
        arrays = {"temperature_c": cautery.temperature_c(), "damage_omega": cautery.damage_omega(), "char": cautery.char_level(),
                  "coagulation_depth_mm": cautery.coagulation_depth_mm(), "temperature_depth_c": cautery.temperature_depth_c(),
                  "damage_omega_depth": cautery.damage_omega_depth()}
        if self.resampler is not None:
            arrays = {name: self.resampler.array(values) for name, values in arrays.items()}
        arrays["layer_depth_mm"] = cautery.layer_depth_mm.astype(np.float32)
        return arrays
