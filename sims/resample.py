"""Fields of a coarse texel grid read on a finer one of the same texture space (the heat grid under the display).

Simulation and display resolution are decoupled (Mosegaard et al., seeds/mosegaard_gpu_spring_mass_visualisation):
heat runs on a coarse grid, the look is composed on the display grid. Each display texel reads the bilinear taps of
the coarse grid around its own (u, v), keeping only taps on the surface whose 3D position is within one coarse texel
(side plus side) of the display texel, so values never cross from one UV chart to another that merely lies next to it
in UV space; the kept weights are renormalised. A display texel with no such tap (a chart's rim finer than the coarse
grid) reads the coarse texel nearest in 3D. Every value read is a convex combination of coarse values: bounds hold.
"""
import math

import numpy as np
import taichi as ti
from scipy.spatial import cKDTree

from sims import field_io

TAPS = 4


def coarse_grid_size(texture_size: int, divisor: int) -> int:
    """Texels per side of a model's grid under a display of texture_size (cautery.heat_grid_divisor,
    bleeding.grid_divisor): texture_size / divisor, at least 16."""
    return max(16, int(math.ceil(texture_size / divisor)))


def model_grid(display, divisor: int):
    """(grid, resampler) of a model that runs texture_size / divisor texels per side under the display TissueSurface:
    the display itself and None when that is its own size, else the coarser surface and a GridResampler onto the
    display."""
    from sims.surface import surface_at

    size = coarse_grid_size(display.size, divisor)
    if size == display.size:
        return display, None
    grid = surface_at(display, size)
    return grid, GridResampler(grid, display)


def bilinear_taps(coarse, fine) -> tuple[np.ndarray, np.ndarray]:
    """(H * W, TAPS) flat coarse indices and float32 weights (rows sum to 1 on fine surface texels, 0 elsewhere) of
    the fine TissueSurface's texels on the coarse one (see the module docstring)."""
    h, w = coarse.mask.shape
    height, width = fine.mask.shape
    y = (np.arange(height) + 0.5) * (h / height) - 0.5
    x = (np.arange(width) + 0.5) * (w / width) - 0.5
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    fy, fx = y - y0, x - x0
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
        coarse_rows, coarse_cols = np.nonzero(coarse.mask)
        _, nearest = cKDTree(coarse.position_mm[coarse_rows, coarse_cols]).query(fine.position_mm[lonely])
        taps[lonely] = (coarse_rows[nearest] * w + coarse_cols[nearest])[:, None]
        weights[lonely] = np.array([1.0, 0.0, 0.0, 0.0])
    return taps.reshape(-1, TAPS).astype(np.int32), weights.reshape(-1, TAPS).astype(np.float32)


@ti.data_oriented
class GridResampler:
    """Reads fields of the coarse TissueSurface's grid at the fine one's texels (module docstring)."""

    def __init__(self, coarse, fine):
        self.coarse_shape, self.fine_shape = coarse.mask.shape, fine.mask.shape
        taps, weights = bilinear_taps(coarse, fine)
        self.taps_np, self.weights_np = taps, weights
        self.dominant = taps[np.arange(len(taps)), weights.argmax(axis=1)]  # (H * W,) the heaviest tap
        self.taps = ti.Vector.field(TAPS, ti.i32, self.fine_shape)
        self.weights = ti.Vector.field(TAPS, ti.f32, self.fine_shape)
        field_io.load([(self.taps, taps.reshape(self.fine_shape + (TAPS,))),
                       (self.weights, weights.reshape(self.fine_shape + (TAPS,)))])

    def coarse_texel(self, texel_rc) -> tuple[int, int]:
        """(row, col) on the coarse grid that weighs most in a fine texel."""
        index = int(self.dominant[texel_rc[0] * self.fine_shape[1] + texel_rc[1]])
        return divmod(index, self.coarse_shape[1])

    def array(self, values: np.ndarray) -> np.ndarray:
        """Coarse (h, w) or (L, h, w) values -> fine (H, W) or (L, H, W) float32 (0 off the fine surface)."""
        flat = np.asarray(values, np.float32).reshape(values.shape[:-2] + (-1,))
        fine = (flat[..., self.taps_np] * self.weights_np).sum(axis=-1, dtype=np.float32)
        return fine.reshape(values.shape[:-2] + self.fine_shape)

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
