"""The particles' film: a particle pool splatted into a film thickness on its texel grid, the film the look keeps
(sims.look.film) as every bleeding method writes one."""
import numpy as np
import taichi as ti

from sims.core import field_io

SPLAT_SCALE = 1024  # fixed-point units of one particle in the splat grid (integer atomics: deterministic)
MAX_FILTER_TEXELS = 64
SPLAT_TILE = 16    # texels per side of the particles' filter tiles (ParticleSplat)


@ti.data_oriented
class ParticleSplat:
    """Film thickness (mm) of a particle pool on its texel grid: every particle's volume splatted bilinearly in fixed
    point (integer atomics: the same bits on any thread count), a separable tent filter of `reach_mm`, divided by the
    texel's area. The filter runs only on the SPLAT_TILE² tiles within its reach of a particle; the rest are 0."""

    def __init__(self, surface):
        self.height, self.width = surface.mask.shape
        shape = (self.height, self.width)
        self.splat = ti.field(ti.i32, shape)
        self.blur_tmp = ti.field(ti.f32, shape)
        tiles = (-(-self.height // SPLAT_TILE), -(-self.width // SPLAT_TILE))
        self.busy = ti.field(ti.i32, tiles)   # 1: a particle is in this tile
        self.near = ti.field(ti.i32, tiles)   # 1: the filter reaches this tile from a busy one
        self.texel_area = ti.field(ti.f32, shape)
        field_io.load([(self.texel_area, np.where(surface.mask, surface.texel_area_mm2, 1.0))])
        mask = surface.mask
        self.median_texel_mm = tuple(float(np.median(np.linalg.norm(t[mask], axis=1))) if mask.any() else 1.0
                                     for t in (surface.tangent_u, surface.tangent_v))  # along columns, rows

    def film(self, pos, count: int, particle_mm3: float, reach_mm: float, out) -> None:
        """out (H, W) = film thickness (mm) of the first `count` particles at grid positions pos (x = column + 0.5,
        y = row + 0.5), each carrying particle_mm3."""
        self.splat.fill(0)
        self.busy.fill(0)
        if count:
            self._splat(pos, count)
        radius = [max(1, min(int(round(reach_mm / texel_mm)), MAX_FILTER_TEXELS)) for texel_mm in self.median_texel_mm]
        self._dilate(-(-max(radius) // SPLAT_TILE))
        self._blur(radius[0], radius[1], particle_mm3 / SPLAT_SCALE, out)

    @ti.kernel
    def _splat(self, pos: ti.template(), n: ti.i32):
        for i in range(n):
            x = pos[i] - 0.5
            c0 = ti.cast(ti.floor(x[0]), ti.i32)
            r0 = ti.cast(ti.floor(x[1]), ti.i32)
            fx, fy = x[0] - c0, x[1] - r0
            for dr, dc in ti.static(ti.ndrange(2, 2)):
                r, c = r0 + dr, c0 + dc
                w = (fx if dc else 1.0 - fx) * (fy if dr else 1.0 - fy)
                if 0 <= r < self.height and 0 <= c < self.width:
                    ti.atomic_add(self.splat[r, c], ti.cast(w * SPLAT_SCALE + 0.5, ti.i32))
                    self.busy[r // SPLAT_TILE, c // SPLAT_TILE] = 1

    @ti.kernel
    def _dilate(self, reach: ti.i32):
        rows, cols = self.near.shape
        for tr, tc in self.near:
            found = 0
            for dr, dc in ti.ndrange((-reach, reach + 1), (-reach, reach + 1)):
                if 0 <= tr + dr < rows and 0 <= tc + dc < cols and self.busy[tr + dr, tc + dc]:
                    found = 1
            self.near[tr, tc] = found

    @ti.kernel
    def _blur(self, radius_x: ti.template(), radius_y: ti.template(), unit_mm3: ti.f32, out: ti.template()):
        for r, c in self.blur_tmp:
            total = 0
            if self.near[r // SPLAT_TILE, c // SPLAT_TILE]:
                for k in ti.static(range(-radius_x, radius_x + 1)):
                    cc = ti.min(ti.max(c + k, 0), self.width - 1)
                    total += self.splat[r, cc] * (radius_x + 1 - ti.abs(k))
            self.blur_tmp[r, c] = total * unit_mm3 / ((radius_x + 1) * (radius_x + 1))
        for r, c in out:
            total = 0.0
            if self.near[r // SPLAT_TILE, c // SPLAT_TILE]:
                for k in ti.static(range(-radius_y, radius_y + 1)):
                    rr = ti.min(ti.max(r + k, 0), self.height - 1)
                    total += self.blur_tmp[rr, c] * (radius_y + 1 - ti.abs(k))
            out[r, c] = total / ((radius_y + 1) * (radius_y + 1) * self.texel_area[r, c])
