"""Which tiles of the display texture to recompose: those a change of the heat grid's tiles can reach.

A display texel shows the colour composed at its fill source (itself on the surface, the nearest surface texel in
the gutters), and that colour reads the heat grid at the source's taps (sims.resample; the texel itself when both
grids are one). So a display tile must be recomposed when any heat tile under the taps of its texels or of their
fill sources changed; every other tile would come out byte for byte as it is. select() flags those tiles for the
look's kernels (sims.compose), which loop over every display texel and skip the unflagged tiles: a loop over the
texture's own layout measured 2.4 times cheaper per texel than one over a list of tiles (35 against 100 ns per texel
on one core), and skipping a texel costs next to nothing.
"""
import numpy as np
import scipy.sparse
import taichi as ti

from sims.tiles import tile_grid, tile_index

DISPLAY_TILE = 16  # display texels per tile side


@ti.data_oriented
class DisplayTiles:
    """The display grid's tiles and the heat tiles each one reads (module docstring); `dirty` and `listed` after
    select()."""

    def __init__(self, fill_index: np.ndarray, heat_taps: np.ndarray | None, heat_shape: tuple[int, int], heat_tile: int,
                 tile: int = DISPLAY_TILE):
        """fill_index: (H, W) flat display index of each texel's fill source; heat_taps: (H * W, K) flat heat-grid
        indices each display texel reads (None: the heat grid is the display grid); heat_tile: the heat tiles' side."""
        height, width = fill_index.shape
        rows, self.cols = tile_grid(fill_index.shape, tile)
        self.tile, self.tiles = tile, rows * self.cols
        texels = np.arange(height * width)
        taps = texels[:, None] if heat_taps is None else np.asarray(heat_taps, np.int64)
        heat = tile_index(taps, heat_shape[1], heat_tile)  # (H * W, K) heat tiles each texel's colour reads
        own = np.repeat(tile_index(texels, width, tile), heat.shape[1])
        shown = np.concatenate([heat.ravel(), heat[fill_index.ravel()].ravel()])  # its own colour, then its fill's
        heat_tiles = int(np.prod(tile_grid(heat_shape, heat_tile)))
        self.reads = scipy.sparse.csr_matrix((np.ones(len(shown), np.int32), (shown, np.concatenate([own, own]))),
                                             shape=(heat_tiles, self.tiles))  # heat tile -> display tiles it reaches
        self.dirty = ti.field(ti.i32, self.tiles)  # 1: recompose this tile
        self.listed = 0
        self._fresh = True  # nothing composed yet: the first select() flags every tile

    def select(self, changed_heat: np.ndarray | None) -> int:
        """Flag the display tiles to recompose and return how many: those reached by the changed heat tiles
        ((T_heat,) bool; None: none changed), every tile the first time."""
        if self._fresh:
            dirty = np.ones(self.tiles, bool)
            self._fresh = False
        elif changed_heat is None or not changed_heat.any():
            dirty = np.zeros(self.tiles, bool)
        else:
            dirty = (self.reads.T @ changed_heat.astype(np.int32)) > 0
        self.listed = int(dirty.sum())
        if self.listed:
            self.dirty.from_numpy(dirty.astype(np.int32))
        return self.listed

    def select_all(self) -> int:
        """Flag every tile (a full pass)."""
        self.dirty.fill(1)
        self.listed = self.tiles
        return self.listed

    @ti.func
    def flagged(self, r, c):
        """Whether display texel (r, c) lies in a tile to recompose."""
        return self.dirty[(r // self.tile) * self.cols + c // self.tile]
