"""The blood film the look shows, kept on simulated time.

Every step a bleeding method writes the film it has now (mm, on its own grid: the height field's depth, the particles'
splat) and the look keeps, per texel of that grid,

    trail = max(fresh, exp(-dt / blood_trail_s) * trail)      (traces of moving blood linger about blood_trail_s)
    stain = max(stain, fresh)                                  (the deepest blood ever there: a dried stain stays)

so what a picture shows depends on the simulated time only, never on how often a front end asks for one. A trail that
decays below TRAIL_FLOOR_MM is dry (0): a finished bleed stops costing anything a few blood_trail_s later. The
composer (sims.look.compose) reads trail, stain and the method's clot fraction at display texels through sample():
bilinearly (sims.surface.resample) when the method runs on a coarser grid. The clot fraction shown follows the method's in
steps of CLOT_STEP (a pool at rest darkens as it clots). Each step flags the tiles of the film's grid (about
DISPLAY_TEXELS_PER_TILE display texels a side, at least NEAR_TEXELS film texels) where a trail, a stain or the clot
shown may have changed; take_touched() hands them to the look, which recomposes only the display tiles they reach.
"""
import math

import numpy as np
import taichi as ti

from sims.core import backend, field_io
from sims.surface.resample import GridReader

NEAR_TEXELS = 2    # film texels about a wet one whose display texels the look smooths (BloodFilm.take_near)
DISPLAY_TEXELS_PER_TILE = 16  # BloodFilm's touched tiles cover about this many display texels a side
TRAIL_FLOOR_MM = 1e-4  # a decaying trail thinner than this is dry: 0.1 um of blood changes no colour level
CLOT_STEP = 0.01  # the clot fraction shown follows the method's in steps of this (about a colour level at most)


@ti.data_oriented
class BloodFilm(GridReader):
    """A bleeding method's film as the look shows it (module docstring). bleeding: a sims.blood.methods.BleedingMethod, whose
    fresh_film(out) writes its film (mm) on film_shape (or, if it has one, whose Taichi function film_depth(r, c) is
    read in the film's own kernel instead: one launch less per step) and whose film_display is the GridResampler onto
    the display (None: its grid is the display's); clot: its clot fraction field on that grid, or None."""

    def __init__(self, bleeding):
        self.bleeding = bleeding
        shape = tuple(bleeding.film_shape)
        super().__init__(bleeding.film_display)
        # display texels per texel of the film's grid (8 under the default height field): the look smooths the film
        # over about one such texel, so that it has no cell-shaped contours (sims.look.compose)
        self.display_per_texel = 1 if self.resampler is None else max(1, round(self.resampler.fine_shape[1] / self.resampler.coarse_shape[1]))
        self.clot_live = bleeding.film_clot  # the method's clot fraction, changing every substep
        self.reads_method = hasattr(bleeding, "film_depth")  # _keep reads the method's film itself: no fresh_film launch
        self.has_clot = self.clot_live is not None
        # the clot fraction the look shows (advance: within CLOT_STEP of the live one)
        self.clot = ti.field(ti.f32, shape) if self.has_clot else None
        self.fresh = None if self.reads_method else ti.field(ti.f32, shape)  # this step's film (mm)
        self.trail = ti.field(ti.f32, shape)  # mm
        self.stain = ti.field(ti.f32, shape)  # mm
        self.near = ti.field(ti.i32, shape)   # 1: the trail is not zero within NEAR_TEXELS of this texel (take_near)
        self.tile = max(NEAR_TEXELS, round(DISPLAY_TEXELS_PER_TILE / self.display_per_texel))  # film texels a side
        self.tile_shape = (-(-shape[0] // self.tile), -(-shape[1] // self.tile))
        self.touched = ti.field(ti.i32, self.tile_shape)  # 1: a trail or stain in this tile may have changed
        self.serial = backend.serial(shape[0] * shape[1])  # _keep on the launching thread (a coarse grid's film)
        self.reset()

    def reset(self) -> None:
        """Dry, and every tile touched (what was shown before goes)."""
        field_io.load([(self.trail, 0.0), (self.stain, 0.0), (self.near, 0), (self.touched, 1)]
                      + ([(self.clot, 0.0)] if self.has_clot else []))
        self._settled = False

    def advance(self, dt_s: float, trail_s: float) -> None:
        """After a step of dt_s: take the method's film and keep the trail and the stain. Nothing to do (no kernel)
        while the film is settled (take_touched) and the method's step moved no blood."""
        if self._settled and not self.bleeding.moved:
            return
        if not self.reads_method:
            self.bleeding.fresh_film(self.fresh)
        self._keep(self.serial, math.exp(-dt_s / trail_s) if trail_s > 0 else 0.0)

    @ti.kernel
    def _keep(self, serial: ti.template(), decay: ti.f32):
        ti.loop_config(serialize=serial)
        for r, c in ti.ndrange(*self.trail.shape):  # a range, not a struct for: that one cannot be serial
            fresh = 0.0
            if ti.static(self.reads_method):
                fresh = self.bleeding.film_depth(r, c)
            else:
                fresh = self.fresh[r, c]
            trail, stain = self.trail[r, c], self.stain[r, c]
            if fresh > 0.0 or trail > 0.0:
                kept = decay * trail
                new_trail = ti.max(fresh, ti.select(kept >= TRAIL_FLOOR_MM, kept, 0.0))
                new_stain = ti.max(stain, fresh)
                if new_trail != trail or new_stain != stain:
                    self.trail[r, c], self.stain[r, c] = new_trail, new_stain
                    self.touched[r // self.tile, c // self.tile] = 1
            if ti.static(self.has_clot):  # blood at rest darkens as it clots, with no change of depth
                live = self.clot_live[r, c]
                if ti.abs(live - self.clot[r, c]) >= CLOT_STEP:
                    self.clot[r, c] = live
                    self.touched[r // self.tile, c // self.tile] = 1

    def take_touched(self) -> np.ndarray:
        """(tile rows, tile columns) bool: the film tiles whose trail or stain may have changed since the last call;
        near is brought up to date on them and their neighbours. The neighbours are not returned: near only spares the
        look work where every trail it could read is 0, so a change of near alone changes no texel of the look. When
        none was touched and the method's last step moved no blood, every trail equals the film or is 0: the film is
        settled, and advance() does nothing until the method moves blood again."""
        touched = self.touched.to_numpy().astype(bool)
        self._settled = not touched.any() and not self.bleeding.moved  # nothing decays and nothing comes: steady
        if touched.any():
            self._take_near()
            self.touched.fill(0)
        return touched

    @ti.kernel
    def _take_near(self):
        """near = whether the trail is not zero within NEAR_TEXELS texels of this grid, on the touched tiles and their
        neighbours (elsewhere the trail did not change): a display texel whose heaviest tap is not near reads a zero
        trail within the look's smoothing (half a texel of this grid), so the look skips it."""
        height, width = self.near.shape
        rows, cols = self.touched.shape
        for r, c in self.near:
            tr, tc = r // self.tile, c // self.tile
            busy = 0
            for dr, dc in ti.static(ti.ndrange((-1, 2), (-1, 2))):
                if 0 <= tr + dr < rows and 0 <= tc + dc < cols and self.touched[tr + dr, tc + dc]:
                    busy = 1
            if busy:
                found = 0
                for dr, dc in ti.ndrange((-NEAR_TEXELS, NEAR_TEXELS + 1), (-NEAR_TEXELS, NEAR_TEXELS + 1)):
                    rr, cc = ti.min(ti.max(r + dr, 0), height - 1), ti.min(ti.max(c + dc, 0), width - 1)
                    if self.trail[rr, cc] > 0.0:
                        found = 1
                self.near[r, c] = found

    @ti.func
    def is_near(self, r, c):
        """Whether display texel (r, c) may read a trail that is not zero (take_near)."""
        if ti.static(self.same_grid):
            return self.near[r, c]
        else:
            index = self.resampler.taps[r, c][0]
            return self.near[index // self.near.shape[1], index % self.near.shape[1]]

    @ti.func
    def clot_at(self, r, c):
        """Clot fraction (0-1) at display texel (r, c); 0 for a method that keeps none on a grid."""
        if ti.static(self.has_clot):
            return self.sample(self.clot, r, c)
        else:
            return 0.0

    def arrays(self) -> dict:
        """(H, W) trail and stain on the film's grid, mm."""
        return {"trail": self.trail.to_numpy(), "stain": self.stain.to_numpy()}
