"""Fields of a coarse texel grid read on a finer one of the same texture space (the heat grid under the display).

Simulation and display resolution are decoupled (Mosegaard et al., seeds/mosegaard_gpu_spring_mass_visualisation):
heat runs on a coarse grid, the look is composed on the display grid. Each display texel reads the bilinear taps of
the coarse grid around its own (u, v), keeping only taps on the surface whose 3D position is within one coarse texel
(side plus side) of the display texel, so values never cross from one UV chart to another that merely lies next to it
in UV space; the kept weights are renormalised. A display texel with no such tap (a chart's rim finer than the coarse
grid) reads the coarse texel nearest in 3D. Every value read is a convex combination of coarse values: bounds hold.

Values that span orders of magnitude between two coarse texels (Arrhenius Omega near a burn's edge) are read through
their log (log_floor): the convex combination is taken of log values, so a level set (Omega = 1) stays where the
coarse grid's values put it, log Omega being nearly linear across a texel there; Omega itself, interpolated, reaches 1
up to half a coarse texel outside it (a ball held 2 s, heat on 192² under 384²: the burn 8 % larger on square texels,
35 % on 3:1 stretched ones). A value below exp(log_floor) reads as exp(log_floor) (0 has a log), and a texel whose
taps all lie there reads 0.
"""
import math

import numpy as np
import taichi as ti

from sims.core import field_io
from sims.core.backend import cache_key, cached_arrays, source_digest

TAPS = 4
TAPS_CACHE_BYTES = 256 << 20  # bilinear taps on disk (a 256² grid under 512²: 6 MB)
_CODE_VERSION = source_digest(__file__)  # a change here computes the taps anew
SMALLEST = float(np.finfo(np.float32).tiny)  # log_floor must lie above its log (-87.3): 0 then reads at the floor


def coarse_grid_size(texture_size: int, divisor: int) -> int:
    """Texels per side of a model's grid under a display of texture_size (cautery.heat_grid_divisor,
    bleeding.grid_divisor): texture_size / divisor, at least 16."""
    return max(16, int(math.ceil(texture_size / divisor)))


def model_grid(display, divisor: int):
    """(grid, resampler) of a model that runs texture_size / divisor texels per side under the display TissueSurface:
    the display itself and None when that is its own size, else the coarser surface and a GridResampler onto the
    display."""
    from sims.surface.texels import surface_at

    size = coarse_grid_size(display.size, divisor)
    if size == display.size:
        return display, None
    grid = surface_at(display, size)
    return grid, GridResampler(grid, display)


def axis_taps(coarse: int, fine: int) -> tuple[np.ndarray, np.ndarray]:
    """(fine,) lower coarse index (-1 to coarse - 1, unclipped) and weight fraction of the upper one, per fine index
    along an axis of coarse texels (texel centres aligned as in texture space)."""
    position = (np.arange(fine) + 0.5) * (coarse / fine) - 0.5
    lower = np.floor(position).astype(np.int64)
    return lower, position - lower


def bilinear_taps(coarse, fine) -> tuple[np.ndarray, np.ndarray]:
    """(H * W, TAPS) flat coarse indices and float32 weights (rows sum to 1 on fine surface texels, 0 elsewhere) of
    the fine TissueSurface's texels on the coarse one (see the module docstring)."""
    h, w = coarse.mask.shape
    height, width = fine.mask.shape
    (y0, fy), (x0, fx) = axis_taps(h, height), axis_taps(w, width)
    rows, cols, weights = [], [], []
    for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        rows.append(np.broadcast_to(np.clip(y0 + dr, 0, h - 1)[:, None], (height, width)))
        cols.append(np.broadcast_to(np.clip(x0 + dc, 0, w - 1)[None, :], (height, width)))
        weights.append(np.outer(fy if dr else 1.0 - fy, fx if dc else 1.0 - fx))
    rows, cols, weights = np.stack(rows, -1), np.stack(cols, -1), np.stack(weights, -1)
    side = np.linalg.norm(coarse.tangent_u, axis=-1) + np.linalg.norm(coarse.tangent_v, axis=-1)
    gap = np.linalg.norm(coarse.position_mm[rows, cols] - fine.position_mm[..., None, :], axis=-1)
    usable = coarse.mask[rows, cols] & (gap <= side[rows, cols]) & fine.mask[..., None]
    weights = np.where(usable, weights, 0.0)
    total = weights.sum(axis=-1, keepdims=True)
    weights = np.divide(weights, total, out=np.zeros_like(weights), where=total > 0)
    taps = rows * w + cols
    lonely = fine.mask & (total[..., 0] <= 0)
    if lonely.any():
        from scipy.spatial import cKDTree

        coarse_rows, coarse_cols = np.nonzero(coarse.mask)
        _, nearest = cKDTree(coarse.position_mm[coarse_rows, coarse_cols]).query(fine.position_mm[lonely])
        taps[lonely] = (coarse_rows[nearest] * w + coarse_cols[nearest])[:, None]
        weights[lonely] = np.array([1.0, 0.0, 0.0, 0.0])
    return taps.reshape(-1, TAPS).astype(np.int32), weights.reshape(-1, TAPS).astype(np.float32)


def cached_taps(coarse, fine) -> tuple[np.ndarray, np.ndarray]:
    """bilinear_taps(coarse, fine), kept on disk by the maps they read (0.14 s for a 256² grid under 512², a few ms
    read back)."""
    key = cache_key(_CODE_VERSION, *(getattr(surface, name) for surface in (coarse, fine)
                                     for name in ("mask", "position_mm", "tangent_u", "tangent_v")))
    stored = cached_arrays("taps", key, ("taps", "weights"), lambda: dict(zip(("taps", "weights"), bilinear_taps(coarse, fine))),
                           TAPS_CACHE_BYTES)
    return stored["taps"], stored["weights"]


def _read(flat: np.ndarray, taps: np.ndarray, weights: np.ndarray, log_floor: float | None) -> np.ndarray:
    """(..., N) float32 values of N fine texels from their (N, TAPS) taps and weights into flat (..., h * w) coarse
    values; with log_floor, through their log (module docstring)."""
    if log_floor is not None:
        flat = np.maximum(np.log(np.maximum(flat, np.float32(SMALLEST))) - np.float32(log_floor), np.float32(0.0))
    # tap by tap, in the order a sum over the taps adds them (the same bits), without its (..., N, TAPS) temporary:
    # 2.5 times faster for eight layers
    fine = flat[..., taps[:, 0]] * weights[:, 0]
    for tap in range(1, TAPS):
        fine += flat[..., taps[:, tap]] * weights[:, tap]
    if log_floor is not None:
        fine = np.where(fine > 0.0, np.exp(fine + np.float32(log_floor)), np.float32(0.0))
    return fine


@ti.data_oriented
class GridResampler:
    """Reads fields of the coarse TissueSurface's grid at the fine one's texels (module docstring)."""

    def __init__(self, coarse, fine):
        self.coarse_shape, self.fine_shape = coarse.mask.shape, fine.mask.shape
        self.fine_area_mm2 = fine.texel_area_mm2  # (H, W) mm^2, 0 off the surface: areas of what is read here
        taps, weights = cached_taps(coarse, fine)
        self.taps_np, self.weights_np = taps, weights
        self.dominant = taps[np.arange(len(taps)), weights.argmax(axis=1)]  # (H * W,) the heaviest tap
        # (H, 2) and (W, 2) coarse rows and columns a fine row or column taps, and the texels that read their nearest
        # coarse texel instead: where a coarse texel can be read from (area_mm2)
        (h, w), (height, width) = self.coarse_shape, self.fine_shape
        self.tap_rows = np.clip(axis_taps(h, height)[0][:, None] + [0, 1], 0, h - 1)
        self.tap_cols = np.clip(axis_taps(w, width)[0][:, None] + [0, 1], 0, w - 1)
        self.elsewhere = np.flatnonzero(taps[:, 0] != (self.tap_rows[:, :1] * w + self.tap_cols[:, 0]).reshape(-1))
        self.taps = ti.Vector.field(TAPS, ti.i32, self.fine_shape)
        self.weights = ti.Vector.field(TAPS, ti.f32, self.fine_shape)
        field_io.load([(self.taps, taps.reshape(self.fine_shape + (TAPS,))),
                       (self.weights, weights.reshape(self.fine_shape + (TAPS,)))])

    def coarse_texel(self, texel_rc) -> tuple[int, int]:
        """(row, col) on the coarse grid that weighs most in a fine texel."""
        index = int(self.dominant[texel_rc[0] * self.fine_shape[1] + texel_rc[1]])
        return divmod(index, self.coarse_shape[1])

    def array(self, values: np.ndarray, log_floor: float | None = None) -> np.ndarray:
        """Coarse (h, w) or (L, h, w) values -> fine (H, W) or (L, H, W) float32 (0 off the fine surface); with
        log_floor, non-negative values read through their log (module docstring)."""
        flat = np.asarray(values, np.float32).reshape(values.shape[:-2] + (-1,))
        return _read(flat, self.taps_np, self.weights_np, log_floor).reshape(values.shape[:-2] + self.fine_shape)

    def area_mm2(self, values: np.ndarray, level: float, log_floor: float | None = None) -> float:
        """mm^2 of the fine texels where coarse (h, w) values read at least level (as array() reads them). Only the
        fine rows and columns that tap a coarse row and column holding such a value are read (and the texels reading
        their nearest coarse texel): a convex combination reaches level nowhere else. A burn's box, not the grid."""
        flat = np.asarray(values, np.float32).reshape(-1)
        hot = (flat >= level).reshape(self.coarse_shape)
        near = hot.any(axis=1)[self.tap_rows].any(axis=1)[:, None] & hot.any(axis=0)[self.tap_cols].any(axis=1)
        near.reshape(-1)[self.elsewhere] = True
        near = np.flatnonzero(near) if near.mean() < 0.5 else slice(None)  # most of the grid: read it whole
        read = _read(flat, self.taps_np[near], self.weights_np[near], log_floor)
        return float(self.fine_area_mm2.reshape(-1)[near][read >= level].sum(dtype=np.float64))

    @ti.func
    def sample(self, src: ti.template(), r, c):
        """src (a coarse (h, w) field, scalar or vector) at fine texel (r, c)."""
        width = src.shape[1]
        index = self.taps[r, c][0]
        value = self.weights[r, c][0] * src[index // width, index % width]
        for k in ti.static(range(1, TAPS)):
            index = self.taps[r, c][k]
            value += self.weights[r, c][k] * src[index // width, index % width]
        return value

    @ti.func
    def sample_log(self, src: ti.template(), r, c, log_floor: ti.template()):
        """src (a coarse (h, w) scalar field of non-negative values) at fine texel (r, c), read through its log
        (module docstring; as array() with log_floor)."""
        width = src.shape[1]
        excess = 0.0  # the interpolated log above log_floor
        for k in ti.static(range(TAPS)):
            index = self.taps[r, c][k]
            value = src[index // width, index % width]
            excess += self.weights[r, c][k] * ti.max(ti.log(ti.max(value, SMALLEST)) - log_floor, 0.0)
        return ti.select(excess > 0.0, ti.exp(excess + log_floor), 0.0)


@ti.data_oriented
class GridReader:
    """Reads fields of a model's grid at display texels: directly when the model runs on the display grid (resampler
    None), else through the GridResampler. The base of what shows a model's fields in the look."""

    def __init__(self, resampler: "GridResampler | None"):
        self.resampler = resampler
        self.same_grid = resampler is None

    def taps(self) -> np.ndarray | None:
        """(H * W, K) flat texels of the model's grid each display texel reads; None when it runs on the display grid."""
        return None if self.resampler is None else self.resampler.taps_np

    @ti.func
    def sample(self, field: ti.template(), r, c):
        """A field of the model's grid (scalar or vector) at display texel (r, c)."""
        if ti.static(self.same_grid):
            return field[r, c]
        else:
            return self.resampler.sample(field, r, c)

    @ti.func
    def sample_log(self, field: ti.template(), r, c, log_floor: ti.template()):
        """A scalar field of the model's grid at display texel (r, c), read through its log (GridResampler)."""
        if ti.static(self.same_grid):
            return field[r, c]
        else:
            return self.resampler.sample_log(field, r, c, log_floor)
