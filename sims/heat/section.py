"""A cross-section of the burn: temperature and damage against depth and distance along the surface, under a point.

The cut runs through the surface texel nearest `centre_mm` along `direction` (projected into the tangent plane there),
sampled every half_length_mm / (samples // 2) at the surface texel nearest each point of the straight line (on a
curved surface the line leaves the surface a little; the nearest texel follows it).
"""
from dataclasses import dataclass

import numpy as np

from sims.surface.nearest import NearestTexel


@dataclass
class BurnSection:
    """Shapes: N samples along the cut, L layers. Distances and depths in mm, temperatures in C."""

    centre_mm: np.ndarray              # (3,) the surface point at distance 0
    direction: np.ndarray              # (3,) unit, along the surface
    distance_mm: np.ndarray            # (N,)
    layer_depth_mm: np.ndarray         # (L,) layer centres
    depth_mm: float                    # the model's depth
    surface_temperature_c: np.ndarray  # (N,)
    temperature_c: np.ndarray          # (L, N)
    surface_omega: np.ndarray          # (N,)
    omega: np.ndarray                  # (L, N)
    coagulation_depth_mm: np.ndarray   # (N,)
    tool: str = ""                     # the tool it was cut under (Scene.burn_section)


class SectionSampler:
    """Burn cross-sections on one TissueSurface (the heat grid)."""

    def __init__(self, surface):
        self.surface = surface
        self.nearest = NearestTexel(surface).query  # (N, 3) points, mm -> (N, 2) row, column

    def section(self, cautery, centre_mm, direction, half_length_mm: float = 4.0, samples: int = 81) -> BurnSection:
        """The cut through the texel nearest centre_mm along direction (any vector; a zero one, or one along the normal,
        falls back to the texture's u direction there)."""
        surface = self.surface
        r, c = self.nearest(np.asarray(centre_mm, np.float64)[None])[0]
        origin, normal = surface.position_mm[r, c].astype(np.float64), surface.normal[r, c].astype(np.float64)
        along = np.asarray(direction, np.float64)
        along = along - along.dot(normal) * normal
        if not np.linalg.norm(along) > 1e-6:
            along = surface.tangent_u[r, c].astype(np.float64)
            along = along - along.dot(normal) * normal
        along /= max(np.linalg.norm(along), 1e-12)
        distance = np.linspace(-half_length_mm, half_length_mm, samples)
        rows, cols = self.nearest(origin + distance[:, None] * along).T
        return BurnSection(centre_mm=origin, direction=along, distance_mm=distance, layer_depth_mm=cautery.layer_depth_mm.copy(),
                           depth_mm=float(cautery.faces_mm[-1]), **cautery.columns_at(rows, cols))
