"""The surface texel nearest a point in space (mm): one k-d tree over a TissueSurface's texels, built once."""
import numpy as np
from scipy.spatial import cKDTree


class NearestTexel:
    def __init__(self, surface):
        rows, cols = np.nonzero(surface.mask)
        self.texels = np.stack([rows, cols], axis=1)
        self.tree = cKDTree(surface.position_mm[rows, cols])

    def query(self, points_mm) -> np.ndarray:
        """(N, 2) row, column of the surface texel nearest each point of points_mm (N, 3)."""
        return self.texels[self.tree.query(points_mm)[1]]
