"""Which tiles of the display texture the look recomposes: those a change of the burn or of the blood can reach.

A display texel shows the look composed at its fill source (itself on the surface, the nearest surface texel in the
gutters). The tissue there reads the heat grid at the source's taps (sims.surface.resample; the texel itself when both grids
are one), the blood reads the film's grid the same way, and then smooths the film over `blood_reach` texels in two
separable passes (sims.look.compose). The normal map reads the surface height one texel around the fill source. So per
compose, from the heat tiles and the film tiles that changed:
- TISSUE: display tiles reached by a changed heat tile (the tissue's colour and surface are recomposed there);
- BLOOD_SAMPLE: reached by a changed film tile; BLOOD_ROWS: those grown left and right by the smoothing's reach (its
  pass along rows); BLOOD_COLUMNS: those grown up and down (its pass along columns);
- WRITE: TISSUE or BLOOD_COLUMNS (colour, roughness and height are written);
- NORMAL: tiles whose texels' fill sources lie within a texel of a WRITE tile (the normal map is recomputed).
Every other tile would come out byte for byte as it is. select() adds these to each tile's pending work; plan() takes
the pending work that the maps of some tiles need (all, or those a texture stream is about to read) and sets it as bits
of `flags` for the look's kernels, so work on tiles nobody reads yet waits. The kernels loop over every display texel
and skip the unflagged tiles: a loop over the texture's own layout measured 2.4
times cheaper per texel than one over a list of tiles (35 against 100 ns per texel on one core), and skipping a texel
costs next to nothing. The tiles written (WRITE or NORMAL) since a front end last asked are kept for take_changed(),
so a texture stream compares and encodes only those.
"""
import numpy as np
import scipy.sparse
import taichi as ti

from sims.surface.sleep_tiles import tile_grid, tile_index

DISPLAY_TILE = 16  # display texels per tile side
TISSUE, BLOOD_SAMPLE, BLOOD_ROWS, BLOOD_COLUMNS, WRITE, NORMAL = (1 << bit for bit in range(6))
EVERYTHING = TISSUE | BLOOD_SAMPLE | BLOOD_ROWS | BLOOD_COLUMNS | WRITE | NORMAL


def _reads(taps: np.ndarray | None, fill_index: np.ndarray, source_shape, source_tile: int, tile: int):
    """CSR (source tiles, display tiles): which display tiles read a source grid's tile, through each display texel's
    taps (H * W, K) on that grid (None: the display grid itself) and those of its fill source."""
    height, width = fill_index.shape
    texels = np.arange(height * width)
    taps = texels[:, None] if taps is None else np.asarray(taps, np.int64)
    source = tile_index(taps, source_shape[1], source_tile)  # (H * W, K) source tiles each texel reads
    own = np.repeat(tile_index(texels, width, tile), source.shape[1])
    shown = np.concatenate([source.ravel(), source[fill_index.ravel()].ravel()])  # its own, then its fill's
    count = int(np.prod(tile_grid(source_shape, source_tile)))
    matrix = scipy.sparse.csr_matrix((np.ones(len(shown), np.int32), (shown, np.concatenate([own, own]))),
                                     shape=(count, int(np.prod(tile_grid((height, width), tile)))))
    matrix.data[:] = 1
    return matrix


def _grow(flags: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """(R, C) bool flags grown by `rows` tiles up and down and `cols` tiles left and right."""
    padded = np.pad(flags, ((rows, rows), (cols, cols)))
    return np.any([padded[rows + dr:rows + dr + flags.shape[0], cols + dc:cols + dc + flags.shape[1]]
                   for dr in range(-rows, rows + 1) for dc in range(-cols, cols + 1)], axis=0)


def _bits(tissue, sample, rows, columns, write, normal) -> np.ndarray:
    """(tiles,) int32 flags from one bool array per pass (any shape holding the tiles in row-major order)."""
    return (TISSUE * np.ravel(tissue) + BLOOD_SAMPLE * np.ravel(sample) + BLOOD_ROWS * np.ravel(rows)
            + BLOOD_COLUMNS * np.ravel(columns) + WRITE * np.ravel(write) + NORMAL * np.ravel(normal)).astype(np.int32)


@ti.data_oriented
class DisplayTiles:
    """The display grid's tiles and what each reads (module docstring); `flags`, `written` and `listed` after plan()."""

    def __init__(self, fill_index: np.ndarray, heat=None, film=None, blood_reach: int = 0, tile: int = DISPLAY_TILE):
        """fill_index: (H, W) flat display index of each texel's fill source. heat, film: (taps, grid shape, grid
        tile) of the burn's and the blood's grids, or None for a model the scene does not run; taps (H * W, K) are the
        flat grid indices each display texel reads (None: that grid is the display grid). blood_reach: display texels
        over which the look smooths the film in each pass."""
        self.shape = fill_index.shape
        self.grid = tile_grid(fill_index.shape, tile)
        self.rows, self.cols = self.grid
        self.tile, self.tiles = tile, self.rows * self.cols
        self.heat_reads = None if heat is None else _reads(heat[0], fill_index, heat[1], heat[2], tile)
        self.film_reads = None if film is None else _reads(film[0], fill_index, film[1], film[2], tile)
        self.blood_reach = -(-int(blood_reach) // tile)  # tiles per smoothing pass
        # display tile -> display tiles whose texels' fill sources lie in it (the normal map reads around the source)
        self.fill_reads = _reads(None, fill_index, fill_index.shape, tile, tile)
        self.flags = ti.field(ti.i32, self.tiles)
        self.written = np.zeros(0, np.int32)  # (N,) row-major indices of the tiles the last plan() flagged WRITE or NORMAL
        self.kinds = 0                  # the OR of every tile's flags at the last plan()
        self._pending = np.zeros(self.tiles, np.int32)  # per tile, the passes (bits) it still needs
        self._changed = np.zeros(self.grid, bool)
        self._fresh = True              # nothing composed yet: the first select() makes every tile pending

    def select(self, heat: np.ndarray | None = None, film: np.ndarray | None = None) -> None:
        """Add to the pending work the tiles to recompose from the changed heat tiles and film tiles (bool, row-major
        over each grid; None: none changed), every tile the first time. plan() then flags what a compose does."""
        if self._fresh:
            self._fresh = False
            self._pending[:] = EVERYTHING
            return
        heat_changed = heat is not None and self.heat_reads is not None and np.any(heat)
        film_changed = film is not None and self.film_reads is not None and np.any(film)
        if not (heat_changed or film_changed):  # an idle scene: nothing to work out
            return
        none = np.zeros(self.tiles, bool)
        tissue = (self.heat_reads.T @ np.ravel(heat).astype(np.int32)) > 0 if heat_changed else none
        blood = (self.film_reads.T @ np.ravel(film).astype(np.int32)) > 0 if film_changed else none
        rows = _grow(blood.reshape(self.grid), 0, self.blood_reach)  # the pass along rows reads left and right
        columns = _grow(rows, self.blood_reach, 0)                   # the pass along columns up and down
        write = tissue.reshape(self.grid) | columns
        normal = (self.fill_reads.T @ _grow(write, 1, 1).ravel().astype(np.int32)) > 0
        self._pending |= _bits(tissue, blood, rows, columns, write, normal)

    def select_all(self) -> int:
        """Flag every tile for everything (a full pass). Returns how many tiles are written."""
        self._fresh = False
        self._pending[:] = EVERYTHING
        return self.plan()

    def pending_outputs(self) -> np.ndarray:
        """(rows, cols) bool: the tiles whose maps the pending work would write (WRITE or NORMAL)."""
        return ((self._pending & (WRITE | NORMAL)) != 0).reshape(self.grid)

    def plan(self, wanted: np.ndarray | None = None) -> int:
        """Flag for the look's kernels the pending work that the maps of the `wanted` tiles ((rows, cols) bool; None:
        every tile) need, and take it off the pending work; the rest waits for a later plan. Walking back from the
        maps: the normal map of a tile reads the surface height one texel around its texels' fill sources (tiles
        grown by one), the colour pass reads the blood at the tile itself and the tissue at its fill sources, the
        blood's column pass reads its row pass up and down by blood_reach tiles, and that one the sampled film left
        and right. Returns how many tiles are written."""
        pending = self._pending
        outputs = None if wanted is None else np.ravel(wanted).astype(bool)
        if outputs is None:
            flags = pending.copy()
        elif not (outputs & ((pending & (WRITE | NORMAL)) != 0)).any():  # nothing the wanted tiles show is pending
            flags = np.zeros_like(pending)
        else:
            normal = outputs & ((pending & NORMAL) != 0)
            sources = (self.fill_reads @ normal.astype(np.int32)) > 0  # tiles holding their texels' fill sources
            write = (outputs | _grow(sources.reshape(self.grid), 1, 1).ravel()) & ((pending & WRITE) != 0)
            tissue = ((self.fill_reads @ write.astype(np.int32)) > 0) & ((pending & TISSUE) != 0)
            columns = write & ((pending & BLOOD_COLUMNS) != 0)
            rows = _grow(columns.reshape(self.grid), self.blood_reach, 0).ravel() & ((pending & BLOOD_ROWS) != 0)
            sample = _grow(rows.reshape(self.grid), 0, self.blood_reach).ravel() & ((pending & BLOOD_SAMPLE) != 0)
            flags = _bits(tissue, sample, rows, columns, write, normal)
        self._pending = pending & ~flags
        return self._set(flags)

    def _set(self, flags: np.ndarray) -> int:
        self.kinds = int(np.bitwise_or.reduce(flags))
        if self.kinds:
            self.flags.from_numpy(flags)
        written = (flags & (WRITE | NORMAL)) != 0
        self._changed |= written.reshape(self.grid)
        self.written = np.flatnonzero(written).astype(np.int32)
        return self.listed

    @property
    def listed(self) -> int:
        """How many tiles the last plan() flagged WRITE or NORMAL."""
        return len(self.written)

    def take_changed(self) -> np.ndarray:
        """(rows, cols) bool over the tiles: those written since the last call (DISPLAY_TILE texels a side)."""
        changed, self._changed = self._changed, np.zeros(self.grid, bool)
        return changed

    @ti.func
    def flagged(self, r, c, kind: ti.template()):
        """Whether display texel (r, c) lies in a tile flagged `kind` (one of the bits above)."""
        return self.flags[(r // self.tile) * self.cols + c // self.tile] & kind
