"""TileMask: which square blocks of texels of the display maps, the currency between the scene's look and a view (the
blocks the next compose would change, those a view wants brought up to date, those that changed)."""
from typing import NamedTuple

import numpy as np


class TileMask(NamedTuple):
    """tile: texels a block's side; flags: (rows, cols) bool over the blocks, row-major from row 0 (v = 1), the blocks
    of the last row and column cut by the maps' edge."""

    tile: int
    flags: np.ndarray

    @classmethod
    def of(cls, value) -> "TileMask":
        """value as a TileMask: a TileMask, or a (tile, flags) pair (flags as a bool array)."""
        tile, flags = value
        return cls(int(tile), np.asarray(flags, bool))
