"""Tiles of texels that sleep and wake, so a model's cost follows where something happens.

The texture is cut into TILE x TILE texel tiles. A model steps only the awake tiles (`active`, `count`), each as
deep as `depth` says (layers of a layered field; 1 for a flat one). After a step the model scans its awake tiles and
writes into `hot` the deepest layer that is off rest (-1: all at rest); before the next step it writes into `wanted`
the depth a tile needs for its own reasons (a tool within reach). plan() then wakes every tile that is wanted, hot,
next to a hot tile (within `reach_tiles`: heat moves at most one texel per explicit substep) or joined to a hot tile
by a UV seam link, each with a depth of the deepest hot layer around it plus `margin` layers (so heat moving down
always finds a solved layer to go into), and lists them in tile order (the same list, so the same sums, whatever
the thread count; on a GPU the lists are built by blocks of LIST_BLOCK tiles, sims.core.scan, in the same order). A tile
that goes to sleep keeps its values, which are at rest within the model's tolerance; the
tiles that fell asleep at this plan are listed in `asleep` (a model with two buffers copies them across once).
The tiles stepped since a reader last asked are flagged in `changed`; a model flags in `damaged` the tiles where it
also changed a lasting field (the burn's damage and char). take_changed() hands either set to its one reader, the
look, which recomposes only those tiles (sims.look.display_tiles): only the damaged ones when it shows no temperature.
"""

import numpy as np
import taichi as ti

from sims.core import backend, field_io, scan

TILE = 8  # texels per tile side
LIST_BLOCK = 64  # tiles a thread lists in plan when the lists are built by blocks (a GPU)
WAKE_HALO_TEXELS = 16  # awake texels at least this far around a hot tile: the tails of a spreading bump keep moving


def tile_grid(shape: tuple[int, int], tile: int) -> tuple[int, int]:
    """(rows, columns) of tile x tile tiles covering a (H, W) texture."""
    return -(-shape[0] // tile), -(-shape[1] // tile)


def tile_spheres(position_mm: np.ndarray, mask: np.ndarray, tile: int = TILE) -> tuple[np.ndarray, np.ndarray]:
    """Per tile (row-major over the tile grid) the centre (mm, (T, 3)) and radius (mm, (T,)) of a ball holding its
    surface texels; radius -1 for a tile without any."""
    height, width = mask.shape
    rows, cols = tile_grid((height, width), tile)
    centre, radius = np.zeros((rows * cols, 3), np.float32), np.full(rows * cols, -1.0, np.float32)
    for index in range(rows * cols):
        tr, tc = divmod(index, cols)
        block = (slice(tr * tile, (tr + 1) * tile), slice(tc * tile, (tc + 1) * tile))
        points = position_mm[block][mask[block]].astype(np.float64)
        if len(points):
            middle = 0.5 * (points.min(axis=0) + points.max(axis=0))
            centre[index] = middle
            radius[index] = np.linalg.norm(points - middle, axis=1).max()
    return centre, radius


def tile_index(flat: np.ndarray, width: int, tile: int) -> np.ndarray:
    """Row-major tile of flat texel indices (row * width + column) of a texture `width` texels wide."""
    return (flat // width) // tile * tile_grid((1, width), tile)[1] + (flat % width) // tile


def tile_links(link_start: np.ndarray, link_to: np.ndarray, shape: tuple[int, int], tile: int = TILE):
    """Tiles joined by texel links (seams), CSR over tiles: (start (T + 1,) int32, partner (P,) int32), both ways."""
    width = shape[1]
    count = int(np.prod(tile_grid(shape, tile)))
    sources = np.repeat(np.arange(len(link_start) - 1), np.diff(link_start))
    targets = np.asarray(link_to[: len(sources)])
    pairs = np.unique(np.stack([tile_index(sources, width, tile), tile_index(targets, width, tile)], axis=1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    start = np.zeros(count + 1, np.int64)
    np.add.at(start, pairs[:, 0] + 1, 1)
    return np.cumsum(start).astype(np.int32), pairs[:, 1].astype(np.int32)


@ti.data_oriented
class TileSchedule:
    """Awake tiles of a (H, W) texture and how deep each is solved; see the module docstring."""

    def __init__(self, mask: np.ndarray, link_start: np.ndarray, link_to: np.ndarray, max_depth: int, tile: int = TILE):
        self.tile, self.max_depth = tile, int(max_depth)
        self.height, self.width = mask.shape
        self.rows, self.cols = tile_grid(mask.shape, tile)
        count = self.rows * self.cols
        self.tiles = count
        self.serial = backend.serial(count)  # plan's loop over the tiles on the launching thread (backend.serial)
        occupied = np.array([mask[tr * tile:(tr + 1) * tile, tc * tile:(tc + 1) * tile].any()
                             for tr in range(self.rows) for tc in range(self.cols)], np.int32)
        self.occupied = ti.field(ti.i32, count)
        self.surface_tiles = int(occupied.sum())  # tiles holding surface texels
        self.depth = ti.field(ti.i32, count)   # layers solved per tile this step, 0 asleep
        self.hot = ti.field(ti.i32, count)     # deepest layer off rest at the last scan, -1 none
        self.wanted = ti.field(ti.i32, count)  # depth the model asks for (a tool within reach), 0 none
        self.planned = ti.field(ti.i32, count)
        self.active = ti.field(ti.i32, count)  # awake tiles, in tile order
        self.asleep = ti.field(ti.i32, count)  # tiles that were awake in the last step and are not now
        self.count = ti.field(ti.i32, (2,))    # awake, fell asleep
        self.parallel_lists = not backend.on_cpu()  # plan's lists built by blocks (sims.core.scan), not on one thread
        self.list_start = ti.Vector.field(2, ti.i32, count // LIST_BLOCK + 2)  # each block's place in active, asleep
        self.changed = ti.field(ti.i32, count)  # 1: stepped (or reset) since take_changed()
        self.damaged = ti.field(ti.i32, count)  # 1: a lasting field changed (set by the model) since take_changed()
        start, partner = tile_links(link_start, link_to, mask.shape, tile)
        self.partner_start = ti.field(ti.i32, count + 1)
        self.partner = ti.field(ti.i32, max(len(partner), 1))
        self.awake = 0        # tiles awake this step (copies of count, read once per plan)
        self.fell_asleep = 0  # tiles in `asleep`
        self._flagged = True  # changed or damaged may hold a flag (a tile stepped or was set since take_changed)
        field_io.load([(self.occupied, occupied), (self.partner_start, start), (self.hot, -1)]
                      + ([(self.partner, partner)] if len(partner) else []))

    @ti.func
    def texel(self, i, j):
        """(tile, row, column, inside) of the j-th texel (0 <= j < TILE^2) of the i-th awake tile."""
        return self.texel_of(self.active[i], j)

    @ti.func
    def texel_of(self, t, j):
        """(tile, row, column, inside) of the j-th texel (0 <= j < TILE^2) of tile t."""
        r = (t // self.cols) * self.tile + j // self.tile
        c = (t % self.cols) * self.tile + j % self.tile
        return t, r, c, (r < self.height) and (c < self.width)

    def plan(self, reach_tiles: int, margin: int, wake_all: bool) -> int:
        """Decide this step's awake tiles (see the module docstring); wake_all: every tile with surface texels, at
        full depth. Returns how many are awake."""
        counts = self._plan(self.serial, int(reach_tiles), int(margin), int(wake_all))  # a returned value: no separate read back
        self.awake, self.fell_asleep = int(counts[0]), int(counts[1])
        self._flagged = self._flagged or self.awake > 0
        return self.awake

    def serial_for(self, tiles: int) -> bool:
        """backend.serial for a loop over the texels of `tiles` tiles."""
        return backend.serial(tiles * self.tile * self.tile)

    @ti.kernel
    def _plan(self, serial: ti.template(), reach: ti.i32, margin: ti.i32, wake_all: ti.i32) -> ti.types.vector(2, ti.i32):
        ti.loop_config(serialize=serial)
        for t in range(self.tiles):
            tr, tc = t // self.cols, t % self.cols
            deepest = -1
            for dr, dc in ti.ndrange((-reach, reach + 1), (-reach, reach + 1)):
                nr, nc = tr + dr, tc + dc
                if 0 <= nr < self.rows and 0 <= nc < self.cols:
                    deepest = ti.max(deepest, self.hot[nr * self.cols + nc])
            for m in range(self.partner_start[t], self.partner_start[t + 1]):
                deepest = ti.max(deepest, self.hot[self.partner[m]])
            depth = self.wanted[t]
            if deepest >= 0:
                depth = ti.max(depth, deepest + 1 + margin)
            if wake_all:
                depth = self.max_depth
            self.planned[t] = ti.min(depth, self.max_depth) * self.occupied[t]
        if ti.static(self.parallel_lists):
            blocks = (self.tiles + LIST_BLOCK - 1) // LIST_BLOCK
            for b in range(blocks):
                found = ti.Vector([0, 0])
                for t in range(b * LIST_BLOCK, ti.min((b + 1) * LIST_BLOCK, self.tiles)):
                    found += self._listed(t)
                self.list_start[b + 1] = found
            scan.add_up_blocks(self.list_start, blocks)
            for b in range(blocks):
                at = self.list_start[b]
                for t in range(b * LIST_BLOCK, ti.min((b + 1) * LIST_BLOCK, self.tiles)):
                    at += self._list(t, at)
            self.count[0], self.count[1] = self.list_start[blocks][0], self.list_start[blocks][1]
        else:
            ti.loop_config(serialize=True)
            for t in range(self.tiles):
                if t == 0:
                    self.count[0] = 0
                    self.count[1] = 0
                listed = self._list(t, ti.Vector([self.count[0], self.count[1]]))
                self.count[0] += listed[0]
                self.count[1] += listed[1]
        return ti.Vector([self.count[0], self.count[1]])

    @ti.func
    def _listed(self, t):
        """(1 if tile t is awake in this plan, 1 if it fell asleep at it) as an i32 vector."""
        awake = self.planned[t] > 0
        return ti.Vector([ti.cast(awake, ti.i32), ti.cast((not awake) and self.depth[t] > 0, ti.i32)])

    @ti.func
    def _list(self, t, at):
        """Tile t into `active` at at[0] if awake, into `asleep` at at[1] if it fell asleep; its depth becomes the
        planned one and its scan values are cleared. Returns _listed(t), read before the depth changes."""
        listed = self._listed(t)
        if listed[0]:
            self.active[at[0]] = t
            self.changed[t] = 1
        elif listed[1]:
            self.asleep[at[1]] = t
        self.depth[t] = self.planned[t]
        self.hot[t] = -1
        self.wanted[t] = 0
        return listed

    def mark_all_changed(self) -> None:
        """Every tile's values were set from outside (a reset, a new state)."""
        self.changed.fill(1)
        self.damaged.fill(1)
        self._flagged = True

    def take_changed(self, stepped: bool) -> np.ndarray:
        """(T,) bool: the tiles stepped (stepped=True) or only those damaged, since the last call or a reset (what a
        reader of the fields must refresh); both sets start again empty. No tile stepped since: no device access."""
        if not self._flagged:
            return np.zeros(self.tiles, bool)
        changed = (self.changed if stepped else self.damaged).to_numpy().astype(bool)
        self.changed.fill(0)
        self.damaged.fill(0)
        self._flagged = False
        return changed

    def awake_fraction(self) -> float:
        """Share of the tiles with surface texels that are awake this step."""
        return self.awake / max(self.surface_tiles, 1)
