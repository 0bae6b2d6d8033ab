"""Blood as a height field: blood depth h (mm, along the normal) per texel, exchanged through virtual pipes
(O'Brien and Hodgins 1995; Mei, Decaudin and Hu 2007; Borgeat et al. 2011), in millimetres whatever the UV stretch.

Pipes: every texel pair of the 8-neighbour stencil with a conductance w_ij > 0 (sims.surface.stencil.direction_coefficients
and edge_weights: w = face width / distance in the surface metric), every UV seam link (sims.surface.seams.seam_links), and
an outfall pipe from a texel toward each stencil direction that leaves the surface at an open mesh border (off the
mask and not seam-linked): a pipe to an always empty ghost texel one tangent step away. Pipe length L_ij = |p_i - p_j|
(3D), width W_ij = w_ij L_ij. A texel owns the pipes toward +x, +y, (+x,+y), (+x,-y) (NEIGHBOURS 0, 2, 4, 6), its
outfalls and the seam links to higher texel indices; the other side reads them.

State: the volume per texel as an integer count of UNIT (fixed point: every transfer leaves one texel and enters the
other exactly, so the accounting is exact at every step), and one velocity u_ij (mm/s) per pipe; the volume flux of
the brief's Q form is Q_ij = u_ij W_ij h_donor (the same model written per unit cross-section: dQ/dt = A dphi / L with
A = W h_face is du/dt = dphi / L; the velocity is kept because the donor depth changes under a stored Q).

Driving: the free-surface potential phi_i = -g.(p_i + h_i n_i). The bed part of phi_i - phi_j is precomputed per pipe
in float64 (set_gravity), so a level pool is at rest to rounding (well balanced); the donor (upwind) depth is 0 at a
dry shore, so no flux starts there. Where the normal faces down (g.n > 0) the hydrostatic term g_n h uses
g_n = max(-g.n, 0) = 0: blood hanging under an overhang is moved by the bed slope only (a negative g_n would make depth
attract depth: anti-diffusion, unstable).

One substep, per pipe (kernel _momentum): u_new = advect(u) + dt dphi / L, then drag, pinning and the bound:
  advection: momentum-conservative first-order upwind advection of the pipe velocity along its own line (Stelling
       and Duinmeijer 2003): du/dt = -(qbar_donor / hbar) (u - u_up) / L, with u_up the collinear pipe entering the
       donor (0 at a wall, upstream flow only), qbar_donor the donor's mean discharge along the line and hbar the mean
       depth of the pipe's two texels; taken implicitly (u relaxes toward u_up, bounded for any rate), then the pressure
       increment dt dphi / L is added in full. Without it (or with the non-conservative u du/ds) the dam-break front
       stalls. Neglected: cross-stream advection (v du/dn), advection on seam links and outfalls' upstream; in a 1D
       flow (the dam break) only the first order remains: the front runs 21-28 % behind Ritter's 2 sqrt(g h0) t (by
       the substeps: see Substeps), independently of the resolution (measured at 1 and 0.5 mm texels), the depth
       profile within 2-3 % of h0.
  laminar film drag, implicit: u = u* / (1 + dt 3 nu / h_donor^2), stable for any dt.
  pinning (Borgeat): the donor deeper than pinning_depth_mm or u = 0; a front stops and leaves a film and rivulets.
  |u| <= L / dt (one pipe length per substep) bounds the explicit parts at any step.
Then per texel (kernel _limit) the outflow in the substep, sum of u W h (1 - clot) dt over the pipes leaving it, is
scaled down to at most its volume (depth stays >= 0; the pipe keeps the scaled velocity, as in Mei et al.), and
each pipe moves |u| W h (1 - clot) scale dt / UNIT units, stochastically rounded (unbiased), from donor to receiver
(kernel _transfer, integers gathered per texel: exact and order independent). A texel keeps back one unit per leaving pipe
(the rounding up), so its volume never goes below zero.
Substeps (automatic, CFL): n = ceil(dt S / (cfl L_min)) with S the largest over the wet texels at the step's start
of max(|u| + g_t min(dt, h^2/3nu), sqrt(g_n h)) (g_t the tangential gravity: the speed gravity can add in the step),
and at least sqrt(g_n (h + h_s / n)) at a source adding h_s in the step; at most max_substeps (the velocity bound
keeps a capped step bounded; 0.05 s steps are fine). The gravity waves are explicit: their Courant number must stay
below about 0.73 (measured: grid-scale noise on a deep pool grows above it; the cfl slider stops at 0.65). The
advection is implicit, so flow and waves need not add up as in a fully explicit scheme (|u| + c): the flow's own
Courant number only keeps blood within a texel per substep. Taking the larger instead of the sum costs the dam
break's front 24 -> 28 % (behind Ritter's) and saves a third of the substeps of a 1 ml/s bleed (9 -> 6.5).

Sinks and sources (per step): spawn_rate puts rate dt (1 ml = 1000 mm^3) as a uniform depth over the texels within
radius_mm (3D) of the centre texel (at least the centre), added in equal parts over the step's substeps (a bleed is
a steady source: 1 ml/s into one 1 mm texel would otherwise drop a 10 mm column every 0.01 s, whose collapse
needed twice the substeps); suction removes from the texels within a tool's radius, in
proportion to their volume, at most rate dt; drying removes V (1 - exp(-dt / lifetime_s)) units per texel per
step, stochastically rounded (exponential drying at rate h / lifetime_s; unbiased, and a thin film does vanish);
clotting: a clot fraction c per texel grows as dc/dt = clotting_rate (1 - c) where the blood is at rest (pipe
speeds times 1 - c below rest_speed_mm_s), clotted blood does not flow (the donor's flux times 1 - c), inflowing
fresh blood dilutes c by volume. The stain field keeps the
largest depth ever seen (it stays after the blood is gone).

Accounting (integers of UNIT, host Python ints): spawned = on_surface + suctioned + left_surface + dried, exactly, at
every step; dropped_too_deep counts blood refused where a texel holds its capacity (CAPACITY_MM deep).

Cost follows the wetted area (sims.surface.sleep_tiles): only tiles holding blood plus a halo of ceil(substeps / TILE) tiles (blood
moves at most one texel per substep) and their seam partners are stepped; a dry surface launches no kernel at all.
UNIT = largest texel area x CAPACITY_MM / VOLUME_LEVELS: about 4e-6 mm of depth on a 64^2 texture of 40 mm.
"""

import math

import numpy as np
import taichi as ti

from sims.blood.suction import MAX_SUCTION_TOOLS, active_suction
from sims.core import backend, field_io
from sims.core.hashing import hash01
from sims.surface.seams import TOLERANCE as SEAM_TOLERANCE
from sims.surface.seams import seam_links
from sims.surface.sleep_tiles import TileSchedule
from sims.surface.stencil import NEIGHBOURS, direction_coefficients, edge_weights

KEYS = ("spawned", "suctioned", "left_surface", "dried", "dropped_too_deep")
TILE = 4  # texels per side of the tiles that sleep and wake: the halo of dry texels stepped around the blood is
          # narrower than with the cautery's 8 (hemostasis.yaml: 7-11 % less time in the step, identical blood)
SUCTIONED, LEFT, DRIED = range(3)  # columns of the per-tile counters of a step (added to the totals by _sinks)
NONE, OWNED, BACKWARD, OUTFALL = range(4)   # pipe kinds per texel and direction
CAPACITY_MM = 64.0              # depth a texel of the largest area holds at VOLUME_LEVELS units
VOLUME_LEVELS = 1 << 24         # units per texel at most from sources (per-tile i32 counters stay below 2^30 per step)
LIMIT_MARGIN = 1e-5             # the outflow limiter leaves this fraction (float rounding between kernels)
AREA_DEPTH_FRACTION = 0.1       # blood_area_mm2 counts texels at least this fraction of film_thickness_mm deep


def kinematic_viscosity_mm2_s(params: dict) -> float:
    return params["blood_viscosity_mpa_s"] * 1e-3 / params["blood_density_kg_m3"] * 1e6


@ti.data_oriented
class HeightFieldBleeding:
    """Blood depth on a TissueSurface (sims.blood.methods.BleedingMethod).

    walls: open mesh borders hold the blood (no outfall pipes; benchmarks such as the dam break).
    display: a sims.surface.resample.GridResampler from this surface's grid onto a finer display grid (bleeding.grid_divisor),
    or None when blood runs on the display grid itself. With one, the state arrays and the texels
    spawn_rate takes are on the display grid; depth_mm(), the metrics and the stepping are on this one."""

    method = "height_field"

    def __init__(self, surface, params: dict, gravity_mm_s2, walls: bool = False, display=None):
        self.surface, self.params, self.walls, self.display = surface, params, bool(walls), display
        mask = surface.mask
        height, width = mask.shape
        self.height, self.width = height, width
        shape = (height, width)
        area = np.where(mask, surface.texel_area_mm2, 0.0).astype(np.float64)
        self.unit_mm3 = float(area.max() * CAPACITY_MM / VOLUME_LEVELS) if mask.any() else 1.0
        self._area = area
        position = surface.position_mm.astype(np.float64)
        self._position = position
        coefficients = direction_coefficients(surface.metric, mask)
        weights = edge_weights(coefficients, mask).astype(np.float64)
        link_start, link_to, link_weight = seam_links(surface, coefficients, NEIGHBOURS)
        self.seam_links = len(link_to) // 2
        # --- pipes on the stencil ---
        kind = np.zeros(shape + (8,), np.int32)
        length = np.ones(shape + (8,), np.float64)
        pipe_width = np.zeros(shape + (8,), np.float64)
        delta = np.zeros(shape + (8, 3), np.float64)  # p_i - p_j (or p_i - p_ghost)
        padded = np.pad(mask, 1)
        ex, ey = surface.tangent_u.astype(np.float64), -surface.tangent_v.astype(np.float64)
        flat = np.arange(height * width).reshape(shape)
        has_links = np.diff(link_start).reshape(shape) > 0
        for k, (dr, dc) in enumerate(NEIGHBOURS):
            inside = padded[1 + dr: 1 + dr + height, 1 + dc: 1 + dc + width]
            shifted = np.zeros_like(position)
            r0, r1 = max(0, -dr), height - max(0, dr)
            c0, c1 = max(0, -dc), width - max(0, dc)
            shifted[r0:r1, c0:c1] = position[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
            pair = mask & inside & (weights[..., k] > 0)
            d = position - shifted
            dist = np.linalg.norm(d, axis=-1)
            kind[..., k] = np.where(pair, OWNED if k % 2 == 0 else BACKWARD, NONE)
            delta[..., k, :] = np.where(pair[..., None], d, 0.0)
            length[..., k] = np.where(pair, dist, 1.0)
            pipe_width[..., k] = np.where(pair, weights[..., k] * dist, 0.0)
            if not self.walls:
                step = dc * ex + dr * ey
                step_length = np.linalg.norm(step, axis=-1)
                open_border = mask & ~inside & (coefficients[..., k] > 0) & (step_length > 0)
                rows, cols = np.nonzero(open_border & has_links)
                for r, c in zip(rows, cols):  # seam-linked this way: a link partner near the point stepped to
                    f = flat[r, c]
                    partners = link_to[link_start[f]:link_start[f + 1]]
                    target = position[r, c] + step[r, c]
                    near = np.linalg.norm(position.reshape(-1, 3)[partners] - target, axis=1) < SEAM_TOLERANCE * step_length[r, c]
                    if near.any():
                        open_border[r, c] = False
                kind[..., k] = np.where(open_border, OUTFALL, kind[..., k])
                delta[..., k, :] = np.where(open_border[..., None], -step, delta[..., k, :])
                length[..., k] = np.where(open_border, step_length, length[..., k])
                pipe_width[..., k] = np.where(open_border, coefficients[..., k] * step_length, pipe_width[..., k])
        self._delta = delta
        # --- seam links ---
        count = len(link_to)
        sources = np.repeat(np.arange(height * width), np.diff(link_start))
        link_delta = position.reshape(-1, 3)[sources] - position.reshape(-1, 3)[link_to] if count else np.zeros((0, 3))
        link_length = np.maximum(np.linalg.norm(link_delta, axis=1), 1e-6)
        order = {(int(a), int(b)): index for index, (a, b) in enumerate(zip(sources, link_to))}
        link_rev = np.array([order[(int(b), int(a))] for a, b in zip(sources, link_to)], np.int32)
        self._link_delta = link_delta
        pipe_lengths = np.concatenate([length[kind == OWNED], length[kind == OUTFALL], link_length])
        self.min_pipe_mm = float(max(pipe_lengths.min(), 1e-3)) if len(pipe_lengths) else 1.0
        # --- fields ---
        self.mask = ti.field(ti.i32, shape)
        self.volume = ti.field(ti.i32, shape)           # units of unit_mm3
        self.inflow = ti.field(ti.i32, shape)           # units received since the clot was last diluted
        self.source = ti.field(ti.i32, shape)           # units spawned for the coming step, added over its substeps
        self.clot = ti.field(ti.f32, shape)
        self.stain = ti.field(ti.f32, shape)            # largest depth seen, mm
        self.film_shape, self.film_display, self.film_clot = shape, display, self.clot  # the look's film (sims.look.film)
        self.give = ti.field(ti.f32, shape)             # units a pipe of 1 mm width carries per mm/s this substep
        self.scale = ti.field(ti.f32, shape)            # outflow limiter of this substep (1: not limited)
        self.unit_per_area = ti.field(ti.f32, shape)    # mm of depth per unit
        self.area = ti.field(ti.f32, shape)
        self.gn = ti.field(ti.f32, shape)               # max(-g.n, 0), mm/s^2
        self.gt = ti.field(ti.f32, shape)               # |tangential g|, mm/s^2
        self.position = ti.Vector.field(3, ti.f32, shape)
        self.kind = ti.Vector.field(8, ti.i32, shape)
        self.length = ti.Vector.field(8, ti.f32, shape)
        self.pipe_width = ti.Vector.field(8, ti.f32, shape)
        self.bed = ti.Vector.field(8, ti.f32, shape)    # bed part of phi_i - phi_j, mm^2/s^2
        self.u = ti.Vector.field(8, ti.f32, (2,) + shape)  # two buffers (read, write)
        links = max(count, 1)
        self.link_start = ti.field(ti.i32, height * width + 1)
        self.link_to = ti.field(ti.i32, links)
        self.link_rev = ti.field(ti.i32, links)
        self.link_length = ti.field(ti.f32, links)
        self.link_width = ti.field(ti.f32, links)
        self.link_bed = ti.field(ti.f32, links)
        self.link_u = ti.field(ti.f32, (2, links))
        field_io.load([(self.mask, mask), (self.link_start, link_start),
                       (self.unit_per_area, np.where(mask, self.unit_mm3 / np.where(mask, area, 1.0), 0.0)),
                       (self.area, area), (self.position, surface.position_mm), (self.kind, kind), (self.length, length),
                       (self.pipe_width, pipe_width)]
                      + ([(self.link_to, link_to), (self.link_rev, link_rev), (self.link_length, link_length),
                          (self.link_width, link_weight.astype(np.float64) * link_length)] if count else []))
        self.tiles = TileSchedule(mask, link_start, link_to, 1, TILE)
        self.counts = ti.field(ti.i32, (self.tiles.tiles, 3))
        self.sink_totals = ti.field(ti.i64, 3)           # units suctioned, left, dried since the reset (exact)
        self.stats = ti.field(ti.f32, 3)                 # largest wave speed (mm/s); at sources: g_n h, g_n h_source (mm^2/s^2)
        self.tools = ti.Vector.field(5, ti.f32, MAX_SUCTION_TOOLS)  # x, y, z, radius (mm), mm^3 to take this step
        self.tool_units = ti.field(ti.i64, MAX_SUCTION_TOOLS)       # units within reach (integer: exact)
        self.tool_fraction = ti.field(ti.f32, MAX_SUCTION_TOOLS)
        texel_sides = np.concatenate([np.linalg.norm(ex[mask], axis=1), np.linalg.norm(ey[mask], axis=1)])
        self._min_side_mm = float(max(texel_sides.min(), 1e-6)) if len(texel_sides) else 1.0
        self.set_gravity(gravity_mm_s2)
        self.reset()
        if not self.tiles.serial_for(self.tiles.surface_tiles):
            self._compile_thread_pool_kernels()

    # --- set-up -------------------------------------------------------------------------------
    def _compile_thread_pool_kernels(self) -> None:
        """Compile the step's kernels with their loops on the thread pool now (backend.serial), launched over no tile:
        on a grid whose wetted area can outgrow the launching thread's share they were compiled on the step that
        crossed it, a stall of 0.8 s mid-bleed at 1024² (Taichi's front end 0.58 s of it, the kernel cache warm)."""
        nu = kinematic_viscosity_mm2_s(self.params)
        self._substep(False, 0, 0.01, nu, 0.0, 0.0, 1.0, 0, 0, 1)
        self._suction_sum(False, 0, 0, np.zeros((MAX_SUCTION_TOOLS, 5), np.float32))
        self._sinks(False, 0, 0, 0.0, 0, 0.01, nu)

    def set_gravity(self, gravity_mm_s2) -> None:
        """World gravity (mm/s^2): the bed differences per pipe (float64, then float32), g_n and g_t per texel."""
        g = np.asarray(gravity_mm_s2, np.float64)
        self.gravity = g
        normal = self.surface.normal.astype(np.float64)
        gn = -(normal @ g)
        tangential = g[None, None, :] - (normal @ g)[..., None] * normal
        mask = self.surface.mask
        field_io.load([(self.bed, -(self._delta @ g)),
                       (self.gn, np.where(mask, np.maximum(gn, 0.0), 0.0)),
                       (self.gt, np.where(mask, np.linalg.norm(tangential, axis=-1), 0.0))]
                      + ([(self.link_bed, -(self._link_delta @ g))] if len(self._link_delta) else []))

    def reset(self) -> None:
        """No blood, no stain, counters at zero."""
        field_io.load([(getattr(self, name), 0) for name in ("volume", "source", "inflow", "clot", "stain", "give", "u",
                                                             "link_u", "counts", "sink_totals", "stats")]
                      + [(self.tiles.hot, -1), (self.tiles.depth, 0)])
        self.tiles.plan(0, 0, False)
        self.tiles.mark_all_changed()
        self.sources = {"spawned": 0, "dropped_too_deep": 0}  # units (Python ints: exact); the sinks: sink_totals
        self._spawn_budget = {}
        self._disks = {}
        self._pending_speed = 0.0
        self._touched = False  # blood was added since the last step (wakes a sleeping surface)
        self.step_index = 0
        self.last_substeps = 0
        self._substep_count = 0
        self._warned = False  # take_warning() said it since the reset

    def set_depth(self, depth_mm: np.ndarray) -> None:
        """Replace the blood by depths (H, W) mm at rest (tests, benchmarks); counted as spawned."""
        self.reset()
        units = np.where(self.surface.mask, np.rint(np.maximum(depth_mm, 0.0) * self._area / self.unit_mm3), 0).astype(np.int64)
        self.volume.from_numpy(units.astype(np.int32))
        self.sources["spawned"] = int(units.sum())
        wet = np.pad(units > 0, ((0, -self.height % TILE), (0, -self.width % TILE)))
        hot = wet.reshape(self.tiles.rows, TILE, self.tiles.cols, TILE).any(axis=(1, 3))
        self.tiles.hot.from_numpy(np.where(hot.ravel(), 0, -1).astype(np.int32))
        gn = self.gn.to_numpy().astype(np.float64)
        self._touched = True
        self._pending_speed = float(np.sqrt(gn * self.depth_mm()).max())

    # --- sources ------------------------------------------------------------------------------
    def spawn_rate(self, key, texel_rc, rate_ml_s: float, dt_s: float, radius_mm: float) -> int:
        """Add rate_ml_s dt_s ml over the disk of radius_mm (3D) around texel (row, col) (of the display grid when
        there is one); returns units added."""
        budget = self._spawn_budget.get(key, 0.0) + rate_ml_s * dt_s * 1000.0 / self.unit_mm3
        whole = int(min(math.floor(budget), 1 << 30))
        if whole <= 0:
            self._spawn_budget[key] = budget
            return 0
        row, col = (int(v) for v in (texel_rc if self.display is None else self.display.coarse_texel(texel_rc)))
        self._touched = True
        reach = min(int(math.ceil(radius_mm / self._min_side_mm)) + 1, max(self.height, self.width))
        disk, serial = (row, col, float(radius_mm)), backend.serial((2 * reach + 1) ** 2)
        area = self._disks.get(disk)
        if area is None:
            area = float(self._disk_area(serial, row, col, float(radius_mm), reach))
            self._disks = {disk: area} if len(self._disks) > 64 else {**self._disks, disk: area}
        added, refused = (int(v) for v in self._disk_add(serial, row, col, float(radius_mm), reach, whole / max(area, 1e-30)))
        self.sources["spawned"] += added
        self.sources["dropped_too_deep"] += refused
        self._spawn_budget[key] = budget - added - refused  # the rounding short of `whole` carries over
        return added

    @ti.func
    def _in_disk(self, row, col, dr, dc, radius):
        """Texel (row + dr, col + dc) is a surface texel within radius (mm, 3D) of (row, col), or that texel itself."""
        r, c = row + dr, col + dc
        inside = False
        if 0 <= r < self.height and 0 <= c < self.width:
            if self.mask[r, c]:
                inside = (dr == 0 and dc == 0) or (self.position[r, c] - self.position[row, col]).norm() <= radius
        return inside

    @ti.kernel
    def _disk_area(self, serial: ti.template(), row: ti.i32, col: ti.i32, radius: ti.f32, reach: ti.i32) -> ti.f32:
        """The area (mm^2) of the disk's texels."""
        total = 0.0
        ti.loop_config(serialize=serial)
        for dr, dc in ti.ndrange((-reach, reach + 1), (-reach, reach + 1)):
            if self._in_disk(row, col, dr, dc, radius):
                total += self.area[row + dr, col + dc]
        return total

    @ti.kernel
    def _disk_add(self, serial: ti.template(), row: ti.i32, col: ti.i32, radius: ti.f32, reach: ti.i32, units_per_mm2: ti.f32) -> ti.types.vector(2, ti.i32):
        """Put units_per_mm2 * area into each texel of the disk as the coming step's source, up to its capacity:
        (units added, units refused), returned (no separate read back)."""
        added, refused = 0, 0
        ti.loop_config(serialize=serial)
        for dr, dc in ti.ndrange((-reach, reach + 1), (-reach, reach + 1)):
            if self._in_disk(row, col, dr, dc, radius):
                r, c = row + dr, col + dc
                wanted = ti.cast(units_per_mm2 * self.area[r, c], ti.i32)
                put = ti.min(wanted, ti.max(VOLUME_LEVELS - self.volume[r, c] - self.source[r, c], 0))
                self.source[r, c] += put
                t = (r // TILE) * self.tiles.cols + c // TILE
                added += put
                refused += wanted - put
                self.tiles.hot[t] = 0
                ti.atomic_max(self.stats[1], self.gn[r, c] * self._depth(r, c))
                ti.atomic_max(self.stats[2], self.gn[r, c] * self.source[r, c] * self.unit_per_area[r, c])
        return ti.Vector([added, refused])

    # --- the step -----------------------------------------------------------------------------
    def substeps(self, dt_s: float, speed_mm_s: float) -> int:
        """Substeps for a step of dt_s when waves and flow reach speed_mm_s (CFL, at most max_substeps)."""
        p = self.params
        wanted = math.ceil(dt_s * speed_mm_s / (p["cfl"] * self.min_pipe_mm)) if speed_mm_s > 0 else 1
        return int(min(max(wanted, 1), p["max_substeps"]))

    def step(self, dt_s: float, suction: list = ()) -> None:
        """Advance dt_s. suction: [(position_mm (3,), radius_mm, rate_ml_s)] of the tools switched on."""
        p = self.params
        previous = self.tiles.awake
        if not previous and not self._touched:  # a dry surface: nothing to do, no kernel, no read back
            self.last_substeps = 0
            self.step_index += 1
            return
        self._touched = False
        nu = kinematic_viscosity_mm2_s(p)
        speed, at_source, source = (float(v) for v in self._take_stats())
        n = self.substeps(dt_s, max(speed, self._pending_speed))
        self._pending_speed = 0.0
        if source > 0.0:  # the sources add 1/n of their step's depth per substep: waves as fast as sqrt(g_n (h + h_source / n))
            n = max(n, self.substeps(dt_s, math.sqrt(at_source + source / n)))
        awake = self.tiles.plan(-(-n // TILE), 0, False)
        self.last_substeps = n if awake else 0
        if awake:
            serial = self.tiles.serial_for(awake)
            sub = dt_s / n
            clot_keep = math.exp(-p["clotting_rate_1_s"] * sub)
            for k in range(n):
                self._substep(serial, awake, sub, nu, p["pinning_depth_mm"], p["rest_speed_mm_s"], clot_keep, self._substep_count, k, n)
                self._substep_count += 1
            tools = active_suction(suction)
            if tools:  # one launch takes the tools and works out the fraction each takes, on the device
                data = np.zeros((MAX_SUCTION_TOOLS, 5), np.float32)
                for index, (position, radius, rate) in enumerate(tools):
                    data[index] = [*np.asarray(position, np.float64), radius, rate * dt_s * 1000.0]
                self._suction_sum(serial, awake, len(tools), data)
            self._sinks(serial, awake, len(tools), 1.0 - math.exp(-dt_s / p["lifetime_s"]), self.step_index, dt_s, nu)
        self.step_index += 1

    @property
    def moved(self) -> bool:
        """Whether the last step changed the blood (sims.blood.methods.BleedingMethod.moved)."""
        return self.last_substeps > 0

    @ti.func
    def _depth(self, r, c):
        return self.volume[r, c] * self.unit_per_area[r, c]

    @ti.func
    def _inside(self, r, c):
        return 0 <= r < self.height and 0 <= c < self.width

    @ti.kernel
    def _take_stats(self) -> ti.types.vector(3, ti.f32):
        """The stats, returned and zeroed in one launch."""
        taken = ti.Vector([self.stats[0], self.stats[1], self.stats[2]])
        self.stats[0], self.stats[1], self.stats[2] = 0.0, 0.0, 0.0
        return taken

    @ti.func
    def _finish(self, un, length, h_own, h_other, dt, nu, pin, outfall):
        """A pipe's new velocity after pressure and advection: outfall one way, pinning, implicit drag, the bound."""
        if outfall:
            un = ti.max(un, 0.0)
        donor = h_own if un >= 0.0 else h_other
        if donor <= pin or donor <= 0.0:
            un = 0.0
        elif nu > 0.0:
            un = un / (1.0 + dt * 3.0 * nu / (donor * donor))
        bound = length / dt
        return ti.min(ti.max(un, -bound), bound)

    @ti.kernel
    def _substep(self, serial: ti.template(), n: ti.i32, dt: ti.f32, nu: ti.f32, pin: ti.f32, rest_speed: ti.f32,
                 clot_keep: ti.f32, seed: ti.i32, k: ti.i32, substeps: ti.i32):
        """Substep k of `substeps` of the n awake tiles, in one launch (its loops run one after the other): the step's
        _momentum, _limit, _transfer."""
        self._momentum(serial, n, dt, nu, pin)
        self._limit(serial, n, dt, rest_speed, clot_keep)
        self._transfer(serial, n, seed, k, substeps)

    @ti.func
    def _momentum(self, serial: ti.template(), n, dt, nu, pin):
        """New velocities (buffer 1) of the pipes each texel owns, from buffer 0; then copied back (below)."""
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(n, TILE * TILE):
            t, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c]:
                h = self._depth(r, c)
                gn = self.gn[r, c]
                kind = self.kind[r, c]
                for k in ti.static(range(8)):
                    dr, dc = ti.static(NEIGHBOURS[k])
                    if kind[k] == OWNED or kind[k] == OUTFALL:
                        h_other, gn_other = 0.0, 0.0
                        if kind[k] == OWNED:
                            h_other, gn_other = self._depth(r + dr, c + dc), self.gn[r + dr, c + dc]
                        if h <= 0.0 and h_other <= 0.0:  # both ends dry: no donor, the pipe rests (as _finish gives)
                            self.u[1, r, c][k] = 0.0
                        else:
                            length = self.length[r, c][k]
                            u = self.u[0, r, c][k]
                            dphi = self.bed[r, c][k] + gn * h - gn_other * h_other
                            u_star = u + dt * dphi / length  # decides the donor (upwind) side
                            # momentum-conservative upwind advection along the pipe's line (Stelling and Duinmeijer 2003):
                            # du/dt = -(q_donor / h_donor) (u - u_up) / L, q_donor the donor's mean discharge along the line
                            rate, u_up = 0.0, 0.0
                            if u_star > 0.0:
                                rb, cb = r - dr, c - dc
                                q_up = 0.0
                                if self._inside(rb, cb):
                                    if self.kind[rb, cb][k] == OWNED:
                                        u_up = ti.max(self.u[0, rb, cb][k], 0.0)
                                        q_up = u_up * self._depth(rb, cb)
                                q = 0.5 * (q_up + ti.max(u, 0.0) * h)
                                rate = q / (ti.max(0.5 * (h + h_other), 1e-12) * length)
                            elif u_star < 0.0 and kind[k] == OWNED:
                                ra, ca = r + dr, c + dc
                                q_up = 0.0
                                if self.kind[ra, ca][k] == OWNED:
                                    u_up = ti.min(self.u[0, ra, ca][k], 0.0)
                                    q_up = -u_up * self._depth(ra + dr, ca + dc)
                                q = 0.5 * (q_up - ti.min(u, 0.0) * h_other)
                                rate = q / (ti.max(0.5 * (h + h_other), 1e-12) * length)
                            # advection implicit (bounded for any rate), then the pressure increment in full
                            u_new = (u + dt * rate * u_up) / (1.0 + dt * rate) + dt * dphi / length
                            self.u[1, r, c][k] = self._finish(u_new, length, h, h_other, dt, nu, pin, kind[k] == OUTFALL)
                f = r * self.width + c
                for m in range(self.link_start[f], self.link_start[f + 1]):
                    g = self.link_to[m]
                    if f < g:
                        rg, cg = g // self.width, g % self.width
                        h_other = self._depth(rg, cg)
                        dphi = self.link_bed[m] + gn * h - self.gn[rg, cg] * h_other
                        length = self.link_length[m]
                        self.link_u[1, m] = self._finish(self.link_u[0, m] + dt * dphi / length, length, h, h_other, dt, nu, pin, False)

    @ti.func
    def _limit(self, serial: ti.template(), n, dt, rest_speed, clot_keep):
        """Per texel from the new velocities (buffer 1): the outflow scale (give), clot dilution and growth."""
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(n, TILE * TILE):
            t, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c]:
                volume = self.volume[r, c]
                clot = self.clot[r, c]
                if volume <= 0:
                    clot = 0.0
                elif self.inflow[r, c] > 0:
                    clot *= ti.max(0.0, 1.0 - ti.cast(self.inflow[r, c], ti.f32) / ti.cast(volume, ti.f32))
                self.inflow[r, c] = 0
                kind = self.kind[r, c]
                out, speed, leaving = 0.0, 0.0, 0
                for k in ti.static(range(8)):
                    dr, dc = ti.static(NEIGHBOURS[k])
                    if kind[k] == OWNED or kind[k] == OUTFALL:
                        u = self.u[1, r, c][k]
                        speed = ti.max(speed, ti.abs(u))
                        out += self.pipe_width[r, c][k] * ti.max(u, 0.0)
                        leaving += ti.cast(u > 0.0, ti.i32)
                    elif kind[k] == BACKWARD:
                        u = self.u[1, r + dr, c + dc][k ^ 1]
                        speed = ti.max(speed, ti.abs(u))
                        out += self.pipe_width[r, c][k] * ti.max(-u, 0.0)
                        leaving += ti.cast(u < 0.0, ti.i32)
                f = r * self.width + c
                for m in range(self.link_start[f], self.link_start[f + 1]):
                    u = self.link_u[1, m]
                    if f > self.link_to[m]:
                        u = -self.link_u[1, self.link_rev[m]]
                    speed = ti.max(speed, ti.abs(u))
                    out += self.link_width[m] * ti.max(u, 0.0)
                    leaving += ti.cast(u > 0.0, ti.i32)
                h = self._depth(r, c)
                total = out * h * (1.0 - clot) * dt  # mm^3 leaving in this substep
                available = ti.cast(ti.max(volume - leaving, 0), ti.f32) * (self.unit_per_area[r, c] * self.area[r, c]) * (1.0 - LIMIT_MARGIN)
                scale = 1.0
                if total > available:  # each leaving pipe may round up by one unit: `leaving` units are kept back
                    scale = available / total
                self.scale[r, c] = scale
                self.give[r, c] = h * (1.0 - clot) * scale * dt / (self.unit_per_area[r, c] * self.area[r, c])
                if volume > 0 and speed * (1.0 - clot) < rest_speed:
                    clot = 1.0 - (1.0 - clot) * clot_keep
                self.clot[r, c] = clot

    @ti.func
    def _units(self, x, pipe, seed):
        """x >= 0 units stochastically rounded (unbiased: a flow of less than a unit per substep still moves blood and
        a residual force cannot build up a velocity that moves nothing)."""
        return ti.cast(ti.floor(x + hash01(pipe, seed)), ti.i32)

    @ti.func
    def _awake(self, r, c):
        return self.tiles.depth[(r // TILE) * self.tiles.cols + c // TILE] > 0

    @ti.func
    def _flow(self, u, w, owner_r, owner_c, other_r, other_c, pipe, seed):
        """Units through a pipe in this substep, positive from its owner to the other end: the same expression on
        both ends (each texel sums its own pipes: no atomics, exact)."""
        amount = 0
        if u > 0.0:
            amount = self._units(u * w * self.give[owner_r, owner_c], pipe, seed)
        elif u < 0.0:
            amount = -self._units(-u * w * self.give[other_r, other_c], pipe, seed)
        return amount

    @ti.func
    def _transfer(self, serial: ti.template(), n, seed, k, substeps):
        """Integer units through every pipe between awake texels, donor to receiver, each texel adding up its own
        pipes (gathered: the owner and the other end compute the same units, so exact and order independent without
        atomics); the owner keeps in buffer 0 its pipe's velocity times the donor's limiter (what really flowed, Mei
        et al.), so it cannot grow where nothing moves. Substep k of `substeps` adds its share of the step's sources
        (the same integer share each, the remainder in the first substeps: exact)."""
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(n, TILE * TILE):
            t, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c]:
                kind = self.kind[r, c]
                f = r * self.width + c
                change, received = 0, 0
                pending = self.source[r, c]
                if pending > 0:
                    change += pending // substeps + ti.cast(k < pending % substeps, ti.i32)
                    if k == substeps - 1:
                        self.source[r, c] = 0
                for k8 in ti.static(range(8)):
                    dr, dc = ti.static(NEIGHBOURS[k8])
                    rn, cn = r + dr, c + dc
                    if kind[k8] == OWNED:
                        u = self.u[1, r, c][k8]
                        flow = 0
                        if self._awake(rn, cn):
                            flow = self._flow(u, self.pipe_width[r, c][k8], r, c, rn, cn, f * 8 + k8, seed)
                        change -= flow
                        received += ti.max(-flow, 0)
                        self.u[0, r, c][k8] = u * (self.scale[r, c] if u > 0.0 else self.scale[rn, cn])
                    elif kind[k8] == BACKWARD:
                        if self._awake(rn, cn):
                            g = rn * self.width + cn
                            flow = self._flow(self.u[1, rn, cn][k8 ^ 1], self.pipe_width[rn, cn][k8 ^ 1], rn, cn, r, c,
                                              g * 8 + (k8 ^ 1), seed)
                            change += flow
                            received += ti.max(flow, 0)
                    elif kind[k8] == OUTFALL:
                        u = self.u[1, r, c][k8]
                        left = self._flow(ti.max(u, 0.0), self.pipe_width[r, c][k8], r, c, r, c, f * 8 + k8, seed)
                        self.u[0, r, c][k8] = u * self.scale[r, c]
                        if left > 0:
                            change -= left
                            self.counts[t, LEFT] += left
                for m in range(self.link_start[f], self.link_start[f + 1]):
                    g = self.link_to[m]
                    rg, cg = g // self.width, g % self.width
                    if f < g:  # owned here
                        u = self.link_u[1, m]
                        flow = 0
                        if self._awake(rg, cg):
                            flow = self._flow(u, self.link_width[m], r, c, rg, cg, -1 - m, seed)
                        change -= flow
                        received += ti.max(-flow, 0)
                        self.link_u[0, m] = u * (self.scale[r, c] if u > 0.0 else self.scale[rg, cg])
                    elif self._awake(rg, cg):
                        owned = self.link_rev[m]
                        flow = self._flow(self.link_u[1, owned], self.link_width[owned], rg, cg, r, c, -1 - owned, seed)
                        change += flow
                        received += ti.max(flow, 0)
                if change != 0:
                    self.volume[r, c] = self.volume[r, c] + change
                if received > 0:
                    self.inflow[r, c] = self.inflow[r, c] + received
                    self.tiles.hot[t] = 0

    @ti.func
    def _tool_of(self, r, c, tools):
        """The first suction tool whose reach holds texel (r, c), -1 none."""
        found = -1
        for k in range(tools):
            tool = self.tools[k]
            if found < 0 and (self.position[r, c] - ti.Vector([tool[0], tool[1], tool[2]])).norm() <= tool[3]:
                found = k
        return found

    @ti.kernel
    def _suction_sum(self, serial: ti.template(), n: ti.i32, tools: ti.i32, data: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        """The tools (data: MAX_SUCTION_TOOLS rows of x, y, z, radius (mm), mm^3 to take), then the fraction of the
        blood within each tool's reach that it takes this step (at most all of it)."""
        ti.loop_config(serialize=serial)
        for k in range(MAX_SUCTION_TOOLS):
            self.tools[k] = ti.Vector([data[k, 0], data[k, 1], data[k, 2], data[k, 3], data[k, 4]])
            self.tool_units[k] = 0
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(n, TILE * TILE):
            t, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c] and self.volume[r, c] > 0:
                k = self._tool_of(r, c, tools)
                if k >= 0:
                    self.tool_units[k] += ti.cast(self.volume[r, c], ti.i64)
        ti.loop_config(serialize=serial)
        for k in range(tools):
            within_mm3 = ti.cast(self.tool_units[k], ti.f32) * self.unit_mm3
            self.tool_fraction[k] = 0.0
            if within_mm3 > 0.0:
                self.tool_fraction[k] = ti.min(1.0, self.tools[k][4] / within_mm3)

    @ti.kernel
    def _sinks(self, serial: ti.template(), n: ti.i32, tools: ti.i32, dry_fraction: ti.f32, step: ti.i32, dt: ti.f32, nu: ti.f32):
        """Suction (fraction of the volume within a tool's reach), then drying; then for the next step: tiles holding
        blood or flow are hot, the stain, and the largest speed that sets the substeps (stats[0]): over the wet
        texels, the larger of the flow's |u| + g_t min(dt, h^2 / 3 nu) and the waves' sqrt(g_n h). Last, the step's
        counts go into sink_totals and are zeroed."""
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(n, TILE * TILE):
            t, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c]:
                volume = self.volume[r, c]
                if volume > 0:
                    if tools > 0:
                        k = self._tool_of(r, c, tools)
                        if k >= 0:
                            taken = ti.min(volume, ti.cast(ti.cast(volume, ti.f32) * self.tool_fraction[k], ti.i32))
                            volume -= taken
                            self.counts[t, SUCTIONED] += taken
                    dither = hash01(r * self.width + c, step)  # stochastic rounding: unbiased, and a film does vanish
                    dried = ti.min(volume, ti.cast(ti.floor(ti.cast(volume, ti.f32) * dry_fraction + dither), ti.i32))
                    volume -= dried
                    self.counts[t, DRIED] += dried
                    self.volume[r, c] = volume
                h = self._depth(r, c)
                umax = 0.0
                for k in ti.static(range(8)):
                    umax = ti.max(umax, ti.abs(self.u[0, r, c][k]))
                f = r * self.width + c
                for m in range(self.link_start[f], self.link_start[f + 1]):
                    umax = ti.max(umax, ti.abs(self.link_u[0, m]))
                if h > 0.0 or umax > 0.0:
                    self.tiles.hot[t] = 0
                    self.stain[r, c] = ti.max(self.stain[r, c], h)
                    reach = dt
                    if nu > 0.0:
                        reach = ti.min(dt, h * h / (3.0 * nu))
                    ti.atomic_max(self.stats[0], ti.max(umax + self.gt[r, c] * reach, ti.sqrt(self.gn[r, c] * h)))
        ti.loop_config(serialize=serial)
        for q in range(3):  # the step's per-tile counts into the totals, on the device (no read back per step)
            total = ti.cast(0, ti.i64)
            for t in range(self.counts.shape[0]):
                total += self.counts[t, q]
                self.counts[t, q] = 0
            self.sink_totals[q] += total

    # --- outputs ------------------------------------------------------------------------------
    @ti.kernel
    def fresh_film(self, out: ti.template()):
        """out (this grid) = blood depth, mm."""
        for r, c in out:
            out[r, c] = self.film_depth(r, c)

    @ti.func
    def film_depth(self, r, c):
        """Blood depth (mm) at texel (r, c) of this grid, for the look's film (sims.look.film reads it in its own kernel)."""
        return self._depth(r, c)

    def depth_mm(self) -> np.ndarray:
        """(H, W) blood depth along the normal, mm (float64 from the exact volumes)."""
        return self.volume.to_numpy().astype(np.float64) * self.unit_mm3 / np.where(self.surface.mask, self._area, np.inf)

    def pipe_speeds(self) -> np.ndarray:
        """|u| of every owned pipe and seam link (mm/s)."""
        kind = self.kind.to_numpy()
        u = self.u.to_numpy()[0]
        owned = np.abs(u[(kind == OWNED) | (kind == OUTFALL)])
        links = np.abs(self.link_u.to_numpy()[0][: 2 * self.seam_links])
        return np.concatenate([owned, links])

    def state_arrays(self, display_grid: bool = True) -> dict:
        """blood_thickness_mm (H, W) (docs/guide/headless.md, "state.npz"), the stain and the clot fraction, on
        the display grid (display_grid False: on the blood's own grid)."""
        arrays = {"blood_thickness_mm": self.depth_mm().astype(np.float32), "blood_stain_mm": self.stain.to_numpy(),
                  "blood_clot": self.clot.to_numpy()}
        if self.display is None or not display_grid:
            return arrays
        return {name: self.display.array(values) for name, values in arrays.items()}

    def accounting(self) -> dict:
        """ml: spawned = on_surface + suctioned + left_surface + dried (exact in units of unit_mm3)."""
        on_surface = int(self.volume.to_numpy().astype(np.int64).sum() + self.source.to_numpy().astype(np.int64).sum())
        sinks = self.sink_totals.to_numpy()
        found = {**self.sources, "suctioned": int(sinks[SUCTIONED]), "left_surface": int(sinks[LEFT]), "dried": int(sinks[DRIED])}
        totals = {key: found[key] for key in KEYS}
        scale = self.unit_mm3 / 1000.0
        result = {key: value * scale for key, value in totals.items()}
        result["on_surface"] = on_surface * scale
        result["volume_ml"] = result["on_surface"]
        result["units"] = {**totals, "on_surface": on_surface}
        return result

    def metrics(self) -> dict:
        """metrics.json `bleeding` (sims.blood.methods.BleedingMethod): the common keys in ml, mm^2 and mm, then what only
        this method has."""
        counts = self.accounting()
        return {"method": self.method, "blood_area_mm2": self.blood_area_mm2(),
                "max_thickness_mm": float(self.depth_mm().max(initial=0.0)), "volume_ml": counts["on_surface"],
                **{f"{key}_ml": counts[key] for key in ("spawned", "on_surface", "suctioned", "left_surface", "dried")},
                "dropped_too_deep_ml": counts["dropped_too_deep"], "substeps_last_step": self.last_substeps}

    def take_warning(self) -> str | None:
        """Once: why blood was lost (a texel full to CAPACITY_MM refused new blood), else None."""
        if self._warned or not self.sources["dropped_too_deep"]:
            return None
        self._warned = True
        return (f"blood deeper than {CAPACITY_MM:g} mm in a texel: new blood there is dropped and counted in metrics.json "
                "(bleeding.dropped_too_deep_ml)")

    def blood_area_mm2(self) -> float:
        """Surface area (mm^2) of texels at least AREA_DEPTH_FRACTION of film_thickness_mm deep."""
        covered = self.depth_mm() >= AREA_DEPTH_FRACTION * self.params["film_thickness_mm"]
        return float(self._area[covered & self.surface.mask].sum())
