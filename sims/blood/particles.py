"""Blood: a 2D particle fluid in the texture space of the tissue (Clavet et al. 2005, no springs).

Particles live in grid coordinates of the texel maps (x = column, y = row, one unit per texel).
Every length goes through the surface metric G = J^T J (J = [dP/dx dP/dy], mm per texel), so
spacing, interaction radius, speeds and gravity are in millimetres whatever the UV stretch:
- pair distance r = sqrt(d^T G d) with G averaged over the pair, d the grid offset;
- gravity in grid units a = G^-1 J^T g (the tangential part of g, exactly g sin(theta) on an incline);
- a physical displacement of length s along a pair becomes s / r * d in the grid.

One step (substepped): gravity with Nusselt film drag (exact exponential), advance, sort, density and near density,
double density relaxation with Clavet's viscosity impulses (sigma, beta) in the same walk (at the advanced positions
and velocities; the impulse becomes a displacement, as in Clavet's order, where it acts on the velocity before the
advance; both displacements damped by the same drag, so pressure and gravity balance alike at any substep count),
velocity from displacement (inertia factor I, speed clamp in the metric where the particle ends), clotting; after the
substeps, suction and a last sort. The sort (a stable counting sort by cell) moves the alive
particles to the front of the pool in cell order and counts and drops the others, so a particle's candidates are
three contiguous runs of the pool (the rows of its 3 x (2 CELL_COLUMNS + 1) cells). The density and relaxation
passes walk the three runs side by side without a branch (a pair out of range weighs exactly 0), in whole
multiples of LANES candidates, so that the whole walk runs in the compiler's vector loop (8 pairs per instruction
on a CPU with AVX2), and the three runs are three independent chains in one loop (1.2 times faster than one loop
per run). Every kernel gathers from neighbours and writes only its own particle; the sort's prefix sum and scatter
run serially on a CPU (2-3 % of the step) and in parallel on a GPU, where each cell's slots are then put in index
order, so results are bitwise identical across runs, thread counts and the two sorts.
A substep's passes are one launch (_passes), and a small pool's whole step is one (its loops serial in one task): on a
CPU a launch from Python costs 15-45 us, a third of a 1,000-particle step when each pass was its own. Kernels loop over
the pool's count at the start of the step and skip past the device's alive_count: the step's last launch returns the
count, the one read back. Work per particle is capped (MAX_CANDIDATES
examined, the first in cell order), so dense clumps cost bounded time. A particle carries its texel's metric and
gravity, read again (one 32-byte record) only when it enters another texel after the advance or the relaxation, or
at its first advance (a spawned or placed particle's texel is checked there); the sort moves them with the particle.

Accounting: spawned = alive + suctioned + left_surface + expired, exactly, at every step.

Walls (`Bleeding(..., walls=True)`, benchmarks such as the dam break; the product keeps the default
walls=False, where a particle that leaves the valid texels leaves the surface): after the advance and
after the relaxation a particle outside the valid texels is put back inside, on the border of its
nearest valid texel (the surface's gutter-fill map; off the texture it is first clamped to the
texture rectangle). The velocity then comes from the clamped displacement, so the part normal to the
wall is removed and the tangential part kept (a free-slip, inelastic wall). It is a compile-time switch
(ti.static): with walls off the kernels are exactly the ones without this feature.
"""
import functools
import math

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type

from sims.blood.splat import ParticleSplat
from sims.blood.suction import MAX_SUCTION_TOOLS, active_suction
from sims.core import backend, field_io, scan
from sims.core.hashing import hash01

ALIVE, SUCTIONED, LEFT_SURFACE, EXPIRED = 0, 1, 2, 3
MAX_CANDIDATES = 256        # particles one particle examines, at most (bounds the cost of dense clumps)
CELL_COLUMNS = 4            # neighbour cells are h tall and h / CELL_COLUMNS wide: a row of the 3-row block spans
                            # (2 + 1 / CELL_COLUMNS) h, not 3 h (25 % fewer candidates, runs still long)
LANES = 32                  # candidate runs are walked in whole multiples of this: LLVM vectorises the walk as 8 f32
                            # lanes x 4 interleaved, 32 candidates an iteration, and a shorter walk (24 at the default
                            # radius and spacing) ran in its scalar remainder: 8 -> 32 made both walks 2.5x faster
PARTICLE_LOOP_ITEMS = 0.8   # a particle weighs this many work items of backend.serial: the whole step runs on the
                            # launching thread below about 10,000 particles, where waking the thread pool for each of a
                            # substep's loops costs more than the second thread gains (median of 200 steps, 2 threads:
                            # 2.98 ms serial against 3.43 parallel at 5,000; 5.63 both at 10,000; 8.5 against 5.5 at 15,000)
SORT_RUN = 32              # the GPU sort ranks a cell's slots by counting in runs of this many, merges this many runs
PREFIX_BLOCK = 1024         # keys a thread of the parallel prefix sum adds up (_prefix_sum)
SQRT_HALF = math.sqrt(0.5)
COINCIDENT = 1e-6            # pairs closer than this many interaction radii are coincident (_relax)
MAX_RELAX_FRACTION = 0.5    # largest relaxation displacement per substep, in interaction radii
WALL_MARGIN = 1e-3          # walls keep particles this far (texels) inside the border of a valid texel
KEYS = ("spawned", "suctioned", "left_surface", "expired", "dropped_pool_full")
PREDICT, SORT, DENSITY, RELAX, FINISH = (1 << bit for bit in range(5))  # the passes of a substep
SUBSTEP = PREDICT | SORT | DENSITY | RELAX | FINISH
PASS_NAMES = {PREDICT: "predict", SORT: "sort", DENSITY: "density", RELAX: "relax", FINISH: "finish"}
STEP_VALUES = ("dt", "size_x", "size_y", "h", "nu", "film", "rest", "pinning", "lifetime", "push", "push_near", "inertia",
               "max_speed", "clotting", "rest_speed", "sigma", "beta", "half_dt", "inv_h2", "coincident")
# a substep's scalars (_substep), in step_values; products of parameters are taken on the host, once, so that no kernel
# multiplies two of them: LLVM may reorder such a product differently in the serial and the parallel launch


@functools.lru_cache(maxsize=64)
def lattice_density(spacing_mm: float, radius_mm: float) -> float:
    """Clavet density sum (1 - r/h)^2 over the neighbours of a particle in a hexagonal lattice (cached: the step asks
    for it every time, and a sum over about 80 lattice points costs 25 us, a twentieth of a 1,000-particle step)."""
    reach = int(math.ceil(radius_mm / spacing_mm)) + 1
    total = 0.0
    for i in range(-reach, reach + 1):
        for j in range(-reach, reach + 1):
            x, y = spacing_mm * (i + 0.5 * j), spacing_mm * j * math.sqrt(3.0) / 2.0
            r = math.hypot(x, y)
            if 0.0 < r < radius_mm:
                total += (1.0 - r / radius_mm) ** 2
    return total


def particle_volume_ml(params: dict) -> float:
    """Blood volume one particle carries: hexagonal cell area times film thickness."""
    area_mm2 = math.sqrt(3.0) / 2.0 * params["particle_spacing_mm"] ** 2
    return area_mm2 * params["film_thickness_mm"] * 1e-3


@ti.data_oriented
class Bleeding:
    """Particle pool, neighbour grid and display splat on a TissueSurface (bleeding method `particles`).

    walls: keep particles inside the valid texels (their velocity into the wall removed) instead of
    removing those that leave; off in the product. parallel_sort: the counting sort's prefix sum and scatter in
    parallel (_sort); None: on a GPU only.
    """

    method = "particles"

    def __init__(self, surface, params: dict, gravity_mm_s2, capacity: int, walls: bool = False,
                 parallel_sort: bool | None = None):
        self.surface, self.params = surface, params
        self.walls = bool(walls)
        self.parallel_sort = not backend.on_cpu() if parallel_sort is None else bool(parallel_sort)
        self.separate_passes = False  # True: one launch per pass (the bench's per-pass profile), not one per substep
        height, width = surface.mask.shape
        self.height, self.width, self.capacity = height, width, int(capacity)
        ex, ey = surface.tangent_u, -surface.tangent_v
        metric = surface.metric
        if self.walls:  # flat index of the nearest valid texel (itself when valid)
            self.wall_texel = ti.field(ti.i32, (height, width))
            self.wall_texel.from_numpy(np.asarray(surface.fill_index, np.int32).reshape(height, width))
        # what a particle needs of its texel, in one 32-byte record (one cache line; a 2048^2 texture's maps are far
        # larger than the caches, so each separate map read was a miss): gravity x, y (grid units / s^2, set_gravity),
        # metric gxx, gxy, gyy (mm^2 / texel^2), valid (1 or 0), two unused
        record = np.zeros((height, width, 8), np.float32)
        record[..., 2:5] = np.stack([metric[..., 0, 0], metric[..., 0, 1], metric[..., 1, 1]], axis=-1)
        record[..., 5] = surface.mask
        self.texel_record = ti.Vector.field(8, ti.f32, (height, width))
        self.texel_ex = ti.Vector.field(3, ti.f32, (height, width))       # dP/dx, mm per texel
        self.texel_ey = ti.Vector.field(3, ti.f32, (height, width))       # dP/dy, mm per texel
        self.texel_position = ti.Vector.field(3, ti.f32, (height, width))
        field_io.load([(self.texel_record, record), (self.texel_ex, ex), (self.texel_ey, ey),
                       (self.texel_position, surface.position_mm)])
        # extent of the metric's unit ellipse in grid units: the cell size per mm of radius
        det = np.where(surface.mask, metric[..., 0, 0] * metric[..., 1, 1] - metric[..., 0, 1] ** 2, np.nan)
        self._cell_per_mm = (
            float(np.nanpercentile(np.sqrt(metric[..., 1, 1] / det), 99.9)),
            float(np.nanpercentile(np.sqrt(metric[..., 0, 0] / det), 99.9)),
        )
        cell = self._cell_size(params["interaction_radius_mm"])
        self.cells_x, self.cells_y = max(1, math.ceil(width / cell[0])), max(1, math.ceil(height / cell[1]))
        keys = self.cells_x * self.cells_y + 3  # the cells, then one key per way of leaving (SUCTIONED ... EXPIRED)
        self.cell_count = ti.field(ti.i32, keys)
        self.cell_start = ti.field(ti.i32, keys + 1)
        self.block_start = ti.field(ti.i32, keys // PREFIX_BLOCK + 2)  # the parallel prefix sum's block offsets
        capacity = self.pool_size = max(self.capacity, 1) + MAX_CANDIDATES + LANES  # the pair walks read past the pool
        self._merge_levels = 0  # _order_cells: runs of SORT_RUN^k merged for k = 1 .. this, up to the whole pool
        while SORT_RUN ** (self._merge_levels + 1) < capacity:
            self._merge_levels += 1
        soa = ti.Layout.SOA  # the pair loops read these at LANES consecutive candidates: one load per component
        self.pos = ti.Vector.field(2, ti.f32, capacity, layout=soa)
        self.pos_prev = ti.Vector.field(2, ti.f32, capacity)
        self.pos_new = ti.Vector.field(2, ti.f32, capacity)
        self.vel = ti.Vector.field(2, ti.f32, capacity, layout=soa)
        self.vel_new = ti.Vector.field(2, ti.f32, capacity)
        self.back_v2 = ti.Vector.field(2, ti.f32, (3, capacity))  # sorting buffers (with pos_new, vel_new)
        self.back_f3 = ti.Vector.field(3, ti.f32, (2, capacity))
        self.back_i2 = ti.Vector.field(2, ti.i32, capacity)
        self.metric = ti.Vector.field(3, ti.f32, capacity, layout=soa)  # metric at the particle's texel
        self.gravity = ti.Vector.field(2, ti.f32, capacity)    # gravity at the particle's texel (grid units / s^2)
        self.density = ti.Vector.field(2, ti.f32, capacity)    # rho, rho_near
        self.pressure = ti.Vector.field(2, ti.f32, capacity, layout=soa)  # P, P_near
        self.drag = ti.field(ti.f32, capacity)                 # film drag rate (1/s) of this substep
        self.age = ti.field(ti.f32, capacity)
        self.clot = ti.field(ti.f32, capacity)
        self.uid = ti.field(ti.i32, capacity)
        self.fate = ti.field(ti.i32, capacity)                 # ALIVE or the reason it leaves
        self.cell = ti.field(ti.i32, capacity)                 # sort key: the cell, or past the cells when gone
        self.texel_moved = ti.field(ti.i32, capacity)          # 1: entered another texel, its record to be read
        self.sorted = ti.field(ti.i32, capacity)
        self.sort_scratch = ti.field(ti.i32, capacity) if self.parallel_sort else None  # _order_cells
        self.counters = ti.field(ti.i32, 8)
        self.alive_count = ti.field(ti.i32, ())                # particles in use: the first alive_count of the pool
        self.step_values = ti.field(ti.f32, len(STEP_VALUES))  # STEP_VALUES, written when they change (a kernel
        self._step_values_written = None                       # argument costs about 1 us of every launch)
        self.suction_tools = ti.Vector.field(4, ti.f32, MAX_SUCTION_TOOLS)  # x, y, z (mm), radius (mm)
        self.suction_candidates = ti.field(ti.i32, ())
        self.splatter = ParticleSplat(surface)
        self.film_shape, self.film_display, self.film_clot = (height, width), None, None  # the look's film (sims.look.film)
        self.fresh_thickness = ti.field(ti.f32, (height, width))  # this step's film (blood area, state.npz), mm
        self.reset()
        self.set_gravity(gravity_mm_s2)
        if not backend.serial(PARTICLE_LOOP_ITEMS * self.capacity):
            self._compile_thread_pool_kernels()

    def reset(self) -> None:
        """Empty the pool and zero the counters."""
        self.count, self.step_index = 0, 0
        self.moved = True  # whether the last step had particles to move (sims.blood.methods.BleedingMethod.moved)
        self.counters.fill(0)
        self.alive_count[None] = 0
        self._spawn_budget, self._suction_budget = {}, 0.0
        self.pool_full_reported = False   # the pool was full when blood should have spawned
        self.pool_full_logged = False     # a front end has told the user

    # --- set-up -------------------------------------------------------------------------------
    def _compile_thread_pool_kernels(self) -> None:
        """Compile the step's kernels with their loops on the thread pool now (backend.serial), launched over no
        particle: a pool that can outgrow the launching thread's share compiled them on the step that crossed it, a
        stall of 1.9 s at 10,000 particles (the kernel cache warm)."""
        for passes in (SUBSTEP, SORT):
            self._passes(passes, False, 1, False, 0)

    def _cell_size(self, radius_mm: float):
        """Cell (width, height) in texels: h / CELL_COLUMNS by h through the metric, at least a texel."""
        return (max(1.0, radius_mm / CELL_COLUMNS * self._cell_per_mm[0]), max(1.0, radius_mm * self._cell_per_mm[1]))

    def set_gravity(self, gravity_mm_s2) -> None:
        """Project world gravity (mm/s^2) onto the surface, per texel, in grid units: G^-1 J^T g."""
        g = np.asarray(gravity_mm_s2, np.float64)
        ex, ey = self.surface.tangent_u.astype(np.float64), -self.surface.tangent_v.astype(np.float64)
        metric = self.surface.metric.astype(np.float64)
        det = metric[..., 0, 0] * metric[..., 1, 1] - metric[..., 0, 1] ** 2
        det = np.where(self.surface.mask & (det > 0), det, np.inf)
        bx, by = ex @ g, ey @ g
        ax = (metric[..., 1, 1] * bx - metric[..., 0, 1] * by) / det
        ay = (metric[..., 0, 0] * by - metric[..., 0, 1] * bx) / det
        self._set_texel_gravity(np.stack([ax, ay], axis=-1).astype(np.float32))
        self._locate_all(self.count)

    @ti.kernel
    def _set_texel_gravity(self, gravity: ti.types.ndarray(dtype=ti.math.vec2, ndim=2)):
        for row, col in self.texel_record:
            self.texel_record[row, col][0], self.texel_record[row, col][1] = gravity[row, col][0], gravity[row, col][1]

    @ti.kernel
    def _locate_all(self, n: ti.i32):
        for i in range(n):
            self._locate(i)

    @property
    def rest_density(self) -> float:
        p = self.params
        return p["rest_density"] * lattice_density(p["particle_spacing_mm"], p["interaction_radius_mm"])

    @property
    def particle_volume_ml(self) -> float:
        return particle_volume_ml(self.params)

    # --- spawning -----------------------------------------------------------------------------
    def spawn(self, texel_rc, count: int, radius_mm: float) -> int:
        """Add `count` particles in a disk of radius_mm around texel (row, col); returns how many fit."""
        room = self.capacity - self.count
        placed = max(0, min(count, room))
        if placed < count:
            self.counters[4] += count - placed
            self.pool_full_reported = True
        if placed:
            first_uid = int(self.counters[0])
            self._spawn(self.count, placed, first_uid, int(texel_rc[0]), int(texel_rc[1]), radius_mm)
            self.counters[0] = first_uid + placed
            self.count += placed
        return placed

    def spawn_rate(self, key, texel_rc, rate_ml_s: float, dt_s: float, radius_mm: float) -> int:
        """Spawn blood at rate_ml_s for dt_s; fractional particles carry over between steps."""
        budget = self._spawn_budget.get(key, 0.0) + rate_ml_s * dt_s / self.particle_volume_ml
        whole = int(math.floor(budget))
        self._spawn_budget[key] = budget - whole
        return self.spawn(texel_rc, whole, radius_mm) if whole else 0

    def place(self, grid_xy: np.ndarray) -> None:
        """Replace the pool by particles at rest at grid positions (N, 2) (benchmarks and tests)."""
        count = len(grid_xy)
        if count > self.capacity:
            raise ValueError(f"{count} particles do not fit a pool of {self.capacity}")
        self.reset()
        full = np.zeros((self.pool_size, 2), np.float32)
        full[:count] = grid_xy
        field_io.load([(self.pos, full), (self.pos_prev, full), (self.vel, 0.0), (self.density, 0.0), (self.age, 0.0),
                       (self.clot, 0.0), (self.uid, np.arange(self.pool_size, dtype=np.int32)), (self.fate, ALIVE)])
        self.counters[0] = count
        self.count = count
        self.alive_count[None] = count
        self._locate_all(count)

    @ti.kernel
    def _spawn(self, first: ti.i32, count: ti.i32, first_uid: ti.i32, row: ti.i32, col: ti.i32, radius_mm: ti.f32):
        for k in range(count):
            i = first + k
            uid = first_uid + k
            ex, ey = self.texel_ex[row, col], self.texel_ey[row, col]
            m = self._record_metric(self.texel_record[row, col])
            e1 = ex.normalized()
            e2 = (ey - ey.dot(e1) * e1).normalized()
            angle = 2.0 * math.pi * hash01(ti.u32(uid), ti.u32(1))
            reach = radius_mm * ti.sqrt(hash01(ti.u32(uid), ti.u32(2)))
            offset = reach * (ti.cos(angle) * e1 + ti.sin(angle) * e2)
            b = ti.Vector([ex.dot(offset), ey.dot(offset)])
            det = m[0] * m[2] - m[1] * m[1]
            d = ti.Vector([m[2] * b[0] - m[1] * b[1], m[0] * b[1] - m[1] * b[0]]) / det
            self.pos[i] = ti.Vector([col + 0.5, row + 0.5]) + d
            self.pos_prev[i] = self.pos[i]
            self.vel[i] = ti.Vector([0.0, 0.0])
            self.density[i] = ti.Vector([0.0, 0.0])
            self.age[i] = 0.0
            self.clot[i] = 0.0
            self.uid[i] = uid
            self.fate[i] = ALIVE
            self._locate(i)
        self.alive_count[None] = first + count

    # --- the step -----------------------------------------------------------------------------
    def step(self, dt_s: float, suction: list = ()) -> None:
        """Advance dt_s. suction: [(position_mm (3,), radius_mm, rate_ml_s)] of the tools switched on. Kernels loop
        over the pool's count at the start of the step and skip past the device's alive_count, so the only read back
        is the count at the end (and the suction candidates while a suction tool is on)."""
        p = self.params
        size = self._cell_size_for(p["interaction_radius_mm"])
        self.moved = self.count > 0
        if self.count:
            n, h = self.count, p["interaction_radius_mm"]
            substeps = p["substeps"]
            sub = dt_s / substeps
            nu = p["blood_viscosity_mpa_s"] * 1e-3 / p["blood_density_kg_m3"] * 1e6  # mm^2/s
            rest = self.rest_density
            serial = backend.serial(PARTICLE_LOOP_ITEMS * n)
            push = sub / SQRT_HALF  # the pressures' factor in _relax's sum (its docstring)
            values = (sub, size[0], size[1], h, nu, p["film_thickness_mm"], rest, p["pinning_density"] * rest,
                      p["lifetime_s"], push * p["stiffness_mm_s2"], push * p["near_stiffness_mm_s2"], p["inertia"],
                      p["max_speed_mm_s"], p["clotting_rate_1_s"], p["rest_speed_mm_s"], sub * p["viscosity_sigma_1_s"],
                      sub * p["viscosity_beta_s_mm"] * SQRT_HALF, 0.5 * sub, SQRT_HALF / h, COINCIDENT * h / SQRT_HALF)
            if values != self._step_values_written:
                self.step_values.from_numpy(np.array(values, np.float32))
                self._step_values_written = values
            tools = active_suction(suction)
            if serial and not self.separate_passes:  # the whole step in one launch (two while a suction tool is on)
                count = self._passes(SUBSTEP, True, substeps, not tools, n)
                if tools:
                    self._apply_suction(dt_s, tools)
                    count = self._passes(SUBSTEP, True, 0, True, n)
            else:
                for _ in range(substeps):
                    for passes in PASS_NAMES if self.separate_passes else (SUBSTEP,):
                        self._passes(passes, serial, 1, False, n)
                self._apply_suction(dt_s, tools)
                count = self._passes(SORT, serial, 1, False, n)
            self.count = count  # the last sort dropped those that left in the last substep or to suction
        self.step_index += 1

    @ti.kernel
    def _passes(self, passes: ti.template(), serial: ti.template(), substeps: ti.i32, last_sort: ti.i32,
                n: ti.i32) -> ti.i32:
        """The passes in `passes` (bits PREDICT ... FINISH) in the order of a substep, in one launch, with the scalars
        in step_values; returns the alive count. Parallel: one substep, each pass's loops one after the other as
        separate kernels would run them. serial (small pools, PARTICLE_LOOP_ITEMS): the launch is one task on the
        launching thread that runs `substeps` substeps, then the sort if last_sort, so a whole step is one launch (a
        launch costs 16 us from Python with no argument, 42 with the 18 this one had before step_values)."""
        if ti.static(serial):
            ti.loop_config(serialize=True)
            for _ in range(1):  # one serial task: the passes' loops run inside it, in order
                values = self._step_scalars()
                for _substep in range(substeps):
                    self._substep(passes, serial, n, *values)
                if last_sort:
                    self._sort(serial, n, values[1], values[2])
        else:
            self._substep(passes, serial, n, *self._step_scalars())
        return self.alive_count[None]

    @ti.func
    def _step_scalars(self):
        """The values of step_values, in the order of STEP_VALUES (_substep's arguments after n)."""
        return [self.step_values[index] for index in ti.static(range(len(STEP_VALUES)))]

    @ti.func
    def _substep(self, passes: ti.template(), serial: ti.template(), n, dt, size_x, size_y, h, nu, film, rest, pinning,
                 lifetime, push, push_near, inertia, max_speed, clotting, rest_speed, sigma, beta, half_dt, inv_h2,
                 coincident):
        """The passes in `passes`, in the order of a substep (the scalars: STEP_VALUES)."""
        if ti.static(passes & PREDICT):
            self._predict(serial, n, dt, nu, film, rest, pinning, lifetime)
        if ti.static(passes & SORT):
            self._sort(serial, n, size_x, size_y)
        if ti.static(passes & DENSITY):
            self._density_pass(serial, n, rest, push, push_near, inv_h2)
        if ti.static(passes & RELAX):
            self._relax(serial, n, dt, h, sigma, beta, half_dt, inv_h2, coincident)
        if ti.static(passes & FINISH):
            self._finish(serial, n, dt, inertia, max_speed, clotting, rest_speed)

    def _cell_size_for(self, radius_mm: float):
        """Cells never shrink below the size the grid was allocated for (a smaller radius stays correct)."""
        wanted = self._cell_size(radius_mm)
        return (max(wanted[0], self.width / self.cells_x), max(wanted[1], self.height / self.cells_y))

    def _apply_suction(self, dt_s: float, tools: list) -> None:
        """Take blood within reach of `tools` (sims.blood.methods.active_suction), at most their rate allows."""
        if not tools:
            self._suction_budget = 0.0
            return
        data = np.zeros((MAX_SUCTION_TOOLS, 4), np.float32)
        for index, (position, radius, _) in enumerate(tools):
            data[index] = [*position, radius]
        self.suction_tools.from_numpy(data)
        self._suction_budget += sum(rate for _, _, rate in tools) * dt_s / self.particle_volume_ml
        self._count_suction(self.count, len(tools))
        candidates = int(self.suction_candidates[None])
        if candidates:
            take = min(candidates, int(self._suction_budget))
            self._suction_budget -= take
            self._remove_suctioned(self.count, len(tools), take / candidates, self.step_index)
        # unused capacity does not pile up while the tool hovers over dry tissue
        self._suction_budget = min(self._suction_budget, 1.0 + sum(rate for _, _, rate in tools) * dt_s / self.particle_volume_ml)

    @ti.func
    def _texel(self, x):
        """(row, col, inside) of grid position x, indices clamped to the texture; inside is 0 off the
        texture or on a masked texel."""
        col = ti.cast(ti.floor(x[0]), ti.i32)
        row = ti.cast(ti.floor(x[1]), ti.i32)
        on_texture = (0 <= col < self.width) & (0 <= row < self.height)
        row, col = ti.min(ti.max(row, 0), self.height - 1), ti.min(ti.max(col, 0), self.width - 1)
        return row, col, ti.cast(on_texture & (self.texel_record[row, col][5] > 0.0), ti.i32)

    @ti.func
    def _record_metric(self, record):
        return ti.Vector([record[2], record[3], record[4]])

    @ti.func
    def _locate(self, i):
        """Particle i's metric and gravity from the texel at its position (one record read); 1 if that texel is
        valid, 0 if it is masked or off the texture."""
        row, col, inside = self._texel(self.pos[i])
        record = self.texel_record[row, col]
        self.metric[i] = self._record_metric(record)
        self.gravity[i] = ti.Vector([record[0], record[1]])
        return inside

    @ti.func
    def _entered_another_texel(self, i, before):
        """1 if particle i, moved from grid position `before` (whose texel's record it holds), now sits in another
        texel, else 0."""
        return ti.cast((ti.floor(self.pos[i]) != ti.floor(before)).any(), ti.i32)

    @ti.func
    def _relocate_marked(self, serial: ti.template(), n):
        """_locate the particles marked in texel_moved; those now off the surface leave. A loop of its own, after the
        pass that moved them: each read of a record misses the caches on a large texture (a 2048^2 texture's records
        are 128 MB, one particle per 20 texels), and this short loop keeps several of those misses in flight where the
        pass's long body kept about one (predict at 100,000 particles: 5.4-5.9 -> 2.4-2.7 ms per launch)."""
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None] and self.texel_moved[i]:
                if not self._locate(i):
                    self.fate[i] = LEFT_SURFACE

    @ti.func
    def _keep_inside(self, x):
        """x moved onto the nearest valid texel (walls): clamped to the texture, then to the box of the
        nearest valid texel when its own texel is masked."""
        lo, hi = WALL_MARGIN, 1.0 - WALL_MARGIN
        x = ti.Vector([ti.min(ti.max(x[0], lo), self.width - lo), ti.min(ti.max(x[1], lo), self.height - lo)])
        row, col, inside = self._texel(x)
        if not inside:
            target = self.wall_texel[row, col]
            r, c = target // self.width, target % self.width
            x = ti.Vector([ti.min(ti.max(x[0], c + lo), c + hi), ti.min(ti.max(x[1], r + lo), r + hi)])
        return x

    @ti.func
    def world_position(self, x):
        """World position (mm) of grid position x, linear within its texel."""
        row, col, inside = self._texel(x)
        result = ti.Vector([0.0, 0.0, 0.0])
        if inside:
            result = self.texel_position[row, col] + self.texel_ex[row, col] * (x[0] - col - 0.5) + self.texel_ey[row, col] * (x[1] - row - 0.5)
        return result

    @ti.func
    def _predict(self, serial: ti.template(), n, dt, nu, film, rest, pinning, lifetime):
        """Gravity with film drag (exact), advance; particles off the surface or too old leave (off the surface first:
        _relocate_marked reads the texel records of those that entered another texel, or are fresh, where nothing has
        checked their texel yet)."""
        ti.loop_config(serialize=serial)
        for i in range(n):
            marked = 0
            if i < self.alive_count[None] and self.fate[i] == ALIVE:
                g = self.gravity[i]
                rho = self.density[i][0]
                if pinning > 0.0:
                    g *= ti.min(rho / pinning, 1.0)
                thickness = film * ti.max(rho / rest, 0.25)
                drag = 3.0 * nu / (thickness * thickness)
                self.drag[i] = drag
                v = self.vel[i]
                if drag > 0.0:
                    decay = ti.exp(-drag * dt)
                    v = v * decay + g * (1.0 - decay) / drag
                else:
                    v += g * dt
                self.vel[i] = v
                before = self.pos[i]
                self.pos_prev[i] = before
                self.pos[i] += v * dt
                if ti.static(self.walls):
                    self.pos[i] = self._keep_inside(self.pos[i])
                marked = ti.max(ti.cast(self.age[i] == 0.0, ti.i32), self._entered_another_texel(i, before))
                self.age[i] += dt
                if self.age[i] > lifetime:
                    self.fate[i] = EXPIRED
            self.texel_moved[i] = marked
        self._relocate_marked(serial, n)

    @ti.func
    def _sort(self, serial: ti.template(), n, size_x, size_y):
        """Alive particles in cell order at the front of the pool (neighbours sit close in memory), the others counted
        by fate and dropped: a stable counting sort, then a gather. Its prefix sum and scatter run serially on a CPU;
        with parallel_sort (a GPU, where a serial loop is one thread) the prefix sum runs by blocks (_prefix_sum) and
        each particle takes any free slot of its key, then each cell's slots are put in index order: the same order,
        so the same bytes. Kept serial on a CPU, where the parallel one is slower (the sort launched alone at 100,000
        particles on 2 cores: 1.90 against 2.43 ms). size_x, size_y: cell size in texels."""
        cells = self.cells_x * self.cells_y
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None]:
                key = cells + self.fate[i] - 1
                if self.fate[i] == ALIVE:
                    x = self.pos[i]
                    cx = ti.min(ti.max(ti.cast(ti.floor(x[0] / size_x), ti.i32), 0), self.cells_x - 1)
                    cy = ti.min(ti.max(ti.cast(ti.floor(x[1] / size_y), ti.i32), 0), self.cells_y - 1)
                    key = cy * self.cells_x + cx
                ti.atomic_add(self.cell_count[key], 1)
                self.cell[i] = key
        in_parallel = ti.static(self.parallel_sort and not serial)
        self._prefix_sum(in_parallel, cells + 3)
        if ti.static(not in_parallel):
            ti.loop_config(serialize=True)
            for t in range(n):  # the last particle first, into its key's last free slot: stable, and the counts end at 0
                i = n - 1 - t
                if i < self.alive_count[None]:
                    key = self.cell[i]
                    self.cell_count[key] -= 1
                    self.sorted[self.cell_start[key] + self.cell_count[key]] = i
        else:  # in parallel: any free slot of its key (the counts end at 0), then each cell's slots put in index order
            for i in range(n):
                if i < self.alive_count[None]:
                    key = self.cell[i]
                    self.sort_scratch[self.cell_start[key] + ti.atomic_sub(self.cell_count[key], 1) - 1] = i
            self._order_cells(n, cells)
        for fate in ti.static(range(SUCTIONED, EXPIRED + 1)):  # unrolled: one serial task with the count below
            self.counters[fate] += self.cell_start[cells + fate] - self.cell_start[cells + fate - 1]
        self.alive_count[None] = self.cell_start[cells]
        ti.loop_config(serialize=serial)
        for s in range(n):
            if s < self.alive_count[None]:
                i = self.sorted[s]
                self.pos_new[s] = self.pos[i]
                self.vel_new[s] = self.vel[i]
                self.back_v2[0, s] = self.pos_prev[i]
                self.back_v2[1, s] = self.density[i]
                self.back_v2[2, s] = self.gravity[i]
                self.back_f3[0, s] = ti.Vector([self.age[i], self.clot[i], self.drag[i]])
                self.back_f3[1, s] = self.metric[i]
                self.back_i2[s] = ti.Vector([self.uid[i], self.cell[i]])
        ti.loop_config(serialize=serial)
        for s in range(n):
            if s < self.alive_count[None]:
                self.pos[s] = self.pos_new[s]
                self.vel[s] = self.vel_new[s]
                self.pos_prev[s] = self.back_v2[0, s]
                self.density[s] = self.back_v2[1, s]
                self.gravity[s] = self.back_v2[2, s]
                self.metric[s] = self.back_f3[1, s]
                back_f, back_i = self.back_f3[0, s], self.back_i2[s]
                self.age[s], self.clot[s], self.drag[s] = back_f[0], back_f[1], back_f[2]
                self.uid[s], self.cell[s] = back_i[0], back_i[1]
                self.fate[s] = ALIVE

    @ti.func
    def _order_cells(self, n, cells):
        """The GPU sort's last part: the alive particles, in sort_scratch in any order within each cell, into `sorted`
        in index order within each cell, bounded for a dense clump. Each slot is ranked by counting within its run of
        SORT_RUN slots; then, in cells larger than a run, runs of SORT_RUN^k are merged SORT_RUN at a time (level k),
        each slot finding its place by a binary search in each other run of its group. Per slot and level at most
        SORT_RUN searches, not a cell's square on one thread; the levels alternate buffers, a cell finished in the
        scratch copied back by the next level."""
        scratch = ti.static(self.sort_scratch)
        for s in range(n):
            if s < self.cell_start[cells]:
                value = scratch[s]
                lo, hi = self._slots_of_cell(value)
                run = lo + (s - lo) // SORT_RUN * SORT_RUN
                rank = 0
                for t in range(run, ti.min(run + SORT_RUN, hi)):
                    rank += ti.cast(scratch[t] < value, ti.i32)
                self.sorted[run + rank] = value
        for level in ti.static(range(1, self._merge_levels + 1)):
            width = ti.static(SORT_RUN ** level)  # runs of width, each in order, merged into runs of SORT_RUN width
            source, target = ti.static((self.sorted, scratch) if level % 2 else (scratch, self.sorted))
            for s in range(n):
                if s < self.cell_start[cells]:
                    value = source[s]
                    lo, hi = self._slots_of_cell(value)
                    if hi - lo > width:
                        group = lo + (s - lo) // (SORT_RUN * width) * (SORT_RUN * width)
                        own = lo + (s - lo) // width * width
                        rank = s - own
                        for j in range(SORT_RUN):
                            run = group + j * width
                            if run != own and run < hi:
                                a, b = run, ti.min(run + width, hi)
                                while a < b:  # a: the first of the run not below value
                                    middle = (a + b) // 2
                                    if source[middle] < value:
                                        a = middle + 1
                                    else:
                                        b = middle
                                rank += a - run
                        target[group + rank] = value
                    elif ti.static(level % 2 == 0):
                        if hi - lo > width // SORT_RUN:  # finished by the level before, in the scratch
                            target[s] = value
        if ti.static(self._merge_levels % 2 == 1):  # the last level wrote the scratch
            for s in range(n):
                if s < self.cell_start[cells]:
                    value = scratch[s]
                    lo, hi = self._slots_of_cell(value)
                    if hi - lo > SORT_RUN ** self._merge_levels:
                        self.sorted[s] = value

    @ti.func
    def _slots_of_cell(self, i):
        """The sorted pool's slots lo <= s < hi of particle i's key."""
        key = self.cell[i]
        return self.cell_start[key], self.cell_start[key + 1]

    @ti.func
    def _prefix_sum(self, in_parallel: ti.template(), keys):
        """cell_start[k] = sum of cell_count[:k] for k <= keys. Integer sums: the same in any order. Parallel: blocks of
        PREFIX_BLOCK keys summed at once, their offsets added up in order, then each block's starts."""
        if ti.static(not in_parallel):
            ti.loop_config(serialize=True)
            for c in range(keys + 1):
                if c == 0:
                    self.cell_start[0] = 0
                else:
                    self.cell_start[c] = self.cell_start[c - 1] + self.cell_count[c - 1]
        else:
            blocks = (keys + PREFIX_BLOCK - 1) // PREFIX_BLOCK
            for b in range(blocks):
                total = 0
                for k in range(b * PREFIX_BLOCK, ti.min((b + 1) * PREFIX_BLOCK, keys)):
                    total += self.cell_count[k]
                self.block_start[b + 1] = total
            scan.add_up_blocks(self.block_start, blocks)
            for b in range(blocks):
                start = self.block_start[b]
                for k in range(b * PREFIX_BLOCK, ti.min((b + 1) * PREFIX_BLOCK, keys)):
                    self.cell_start[k] = start
                    start += self.cell_count[k]
            self.cell_start[keys] = self.block_start[blocks]

    @ti.func
    def _candidates(self, i):
        """The particles i examines: three runs lo[k] <= j < hi[k] of the sorted pool (the rows of its
        3 x (2 CELL_COLUMNS + 1) cells), MAX_CANDIDATES in all at most, the first in cell order. A pass walks
        lo[k] + t for t < _span(lo, hi) in every run at once and _pair gives weight 0 past hi[k]: whole vectors, no
        scalar remainder (measured 2.7 times faster on a CPU)."""
        cx, cy = self.cell[i] % self.cells_x, self.cell[i] // self.cells_x
        x0, x1 = ti.max(cx - CELL_COLUMNS, 0), ti.min(cx + CELL_COLUMNS, self.cells_x - 1)
        lo, hi = ti.Vector([0, 0, 0]), ti.Vector([0, 0, 0])
        examined = 0
        for k in ti.static(range(3)):
            row = cy - 1 + k
            if 0 <= row < self.cells_y:
                lo[k] = self.cell_start[row * self.cells_x + x0]
                hi[k] = ti.min(self.cell_start[row * self.cells_x + x1 + 1], lo[k] + MAX_CANDIDATES - examined)
                examined += hi[k] - lo[k]
        return lo, hi

    @ti.func
    def _span(self, lo, hi):
        """How far a pass walks into each of the three runs: the longest run, rounded up to a whole number of LANES."""
        longest = ti.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
        return (longest + LANES - 1) // LANES * LANES

    @ti.func
    def _norm2(self, m, v):
        """Squared length (mm^2) of grid vector v through metric m (gxx, gxy, gyy)."""
        return ti.max(m[0] * v[0] * v[0] + 2.0 * m[1] * v[0] * v[1] + m[2] * v[1] * v[1], 0.0)

    @ti.func
    def _pair(self, xi, mi, j, hi, inv_h2):
        """Grid offset d = x_j - x_i, g = (m_i + m_j) d, s = sqrt(d.g) and kernel weight q = 1 - s inv_h2, 0 for
        j >= hi (past the run) or out of range. m_i + m_j is twice the pair's mean metric, so s = sqrt(2) r with r the
        distance in mm, and inv_h2 = 1 / (sqrt(2) h) (one product fewer per pair than the mean). j == i gives d = 0 and
        q = 1: the passes take i itself out after its walk rather than test every candidate. Past hi the walks read
        other particles or the pool's tail (finite: every slot holds zeros or a copy of an earlier particle) and weigh
        them 0. xi, mi: particle i's position and metric, held in registers over its candidates. The walks clamp with
        selects, not ti.max / ti.min: those lower to LLVM's maxnum / minnum, whose rule for NaN costs x86 a compare and
        a blend per vector besides the max (the same bytes either way; relaxation 4 %, density 7 % faster)."""
        d = self.pos[j] - xi
        m = mi + self.metric[j]
        g = ti.Vector([m[0] * d[0] + m[1] * d[1], m[1] * d[0] + m[2] * d[1]])
        s2 = d.dot(g)
        s = ti.sqrt(ti.select(s2 > 0.0, s2, 0.0))
        falloff = 1.0 - s * inv_h2
        q = ti.select((j < hi) & (falloff > 0.0), falloff, 0.0)
        return d, s, q, g

    @ti.func
    def _walks_itself(self, i, lo, hi):
        """1.0 if particle i is among its own candidates (the middle run; always, unless MAX_CANDIDATES cut it), else 0.0:
        the q = 1 its walk adds for itself."""
        return ti.cast((lo[1] <= i) & (i < hi[1]), ti.f32)

    @ti.func
    def _density_pass(self, serial: ti.template(), n, rest, push, push_near, inv_h2):
        """Density and near density over the candidates in range; pressure and near pressure stored times
        dt / SQRT_HALF (push, push_near: the stiffnesses times that), the factor _relax's sum needs."""
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None]:
                lo, hi = self._candidates(i)
                xi, mi = self.pos[i], self.metric[i]
                rho = rho_near = -self._walks_itself(i, lo, hi)  # i itself adds q = 1
                for t in range(self._span(lo, hi)):
                    for run in ti.static(range(3)):
                        _d, _s, q, _g = self._pair(xi, mi, lo[run] + t, hi[run], inv_h2)
                        rho += q * q
                        rho_near += q * q * q
                self.density[i] = ti.Vector([rho, rho_near])
                self.pressure[i] = ti.Vector([push * (rho - rest), push_near * rho_near])

    @ti.func
    def _relax(self, serial: ti.template(), n, dt, h, sigma, beta, half_dt, inv_h2, coincident):
        """Double density relaxation, symmetric gather: each pair moves i by -dt^2/2 (P_i + P_j)(q, q^2) r_hat; and
        Clavet's viscosity in the same walk: an approaching pair (speed u along r_hat) changes v_i by -min(I, u)/2 r_hat,
        I = dt q (sigma u + beta u^2), which moves i by that times dt (one pair walk fewer than a pass of its own).
        Both in one sum, in _pair's units (s = sqrt(2) r, g = 2 G d, so r_hat = sqrt(2) d / s and u = U / sqrt(2) with
        U = (v_i - v_j).g / s): i moves by -dt/2 sum (q (P'_i + P'_j).(1, q) + min(sqrt(2) I, U) if U > 0) d / s, where
        P' = sqrt(2) dt P (_density_pass stores it) and sqrt(2) I = q U (sigma + beta U), sigma and beta here being dt
        sigma and dt beta / sqrt(2) (host products, STEP_VALUES). Pairs with s at most `coincident` are separated
        along a hashed direction instead."""
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None]:
                shift = ti.Vector([0.0, 0.0])
                lo, hi = self._candidates(i)
                xi, mi, pi, vi = self.pos[i], self.metric[i], self.pressure[i], self.vel[i]
                close = -self._walks_itself(i, lo, hi)  # i itself (s = 0, q = 1) is summed below
                for t in range(self._span(lo, hi)):
                    for run in ti.static(range(3)):
                        j = lo[run] + t
                        d, s, q, g = self._pair(xi, mi, j, hi[run], inv_h2)
                        p = pi + self.pressure[j]
                        apart = s > coincident
                        inv_s = ti.select(apart, 1.0 / s, 0.0)
                        approach = (vi - self.vel[j]).dot(g) * inv_s  # sqrt(2) times the approach speed, mm/s
                        impulse = q * approach * (sigma + beta * approach)
                        w = q * (p[0] + p[1] * q) + ti.select(approach > 0.0, ti.select(impulse < approach, impulse, approach), 0.0)
                        shift -= (w * inv_s) * d
                        close += ti.select(apart, 0.0, q)
                shift *= half_dt
                if close > 0.0:  # rare: separate coincident pairs along a deterministic direction
                    for run in ti.static(range(3)):
                        for j in range(lo[run], hi[run]):
                            _d, s, q, _g = self._pair(xi, mi, j, hi[run], inv_h2)
                            if q > 0.0 and s <= coincident and j != i:
                                angle = 2.0 * math.pi * hash01(ti.u32(self.uid[i]), ti.u32(self.uid[j]))
                                shift -= 0.05 * h * ti.Vector([ti.cos(angle), ti.sin(angle)]) / ti.sqrt(mi[0] + mi[2])
                damping = self.drag[i] * dt  # pressure moves the film against the same drag as gravity
                if damping > 1e-6:
                    shift *= (1.0 - ti.exp(-damping)) / damping
                length = ti.sqrt(self._norm2(mi, shift))
                limit = MAX_RELAX_FRACTION * h
                if length > limit:
                    shift *= limit / length
                self.pos_new[i] = xi + shift

    @ti.func
    def _finish(self, serial: ti.template(), n, dt, inertia, max_speed, clotting, rest_speed):
        """Velocity from displacement (inertia, clamp), clotting; leaving the surface. The displacement waits in vel
        while _relocate_marked reads the records of the texels entered: the velocity takes the metric where it ends."""
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None]:
                start = self.pos_prev[i]
                moved = (self.pos_new[i] - start) * (1.0 - self.clot[i])
                if ti.static(self.walls):  # the velocity below loses the part that went into the wall
                    moved = self._keep_inside(start + moved) - start
                before = self.pos[i]
                self.pos[i] = start + moved
                self.vel[i] = moved
                self.texel_moved[i] = self._entered_another_texel(i, before)
        self._relocate_marked(serial, n)
        ti.loop_config(serialize=serial)
        for i in range(n):
            if i < self.alive_count[None]:
                v, speed = self._clamp_speed(inertia * self.vel[i] / dt, self.metric[i], max_speed)
                self.vel[i] = v
                if speed < rest_speed:
                    self.clot[i] = ti.min(self.clot[i] + clotting * dt, 1.0)

    @ti.func
    def _clamp_speed(self, v, m, max_speed):
        """(v scaled to at most max_speed mm/s through metric m, its speed in mm/s)."""
        speed = ti.sqrt(self._norm2(m, v))
        if speed > max_speed:
            v *= max_speed / speed
            speed = max_speed
        return v, speed

    @ti.kernel
    def _count_suction(self, n: ti.i32, tools: ti.i32):
        self.suction_candidates[None] = 0
        for i in range(n):
            if i < self.alive_count[None] and self.fate[i] == ALIVE and self._in_suction(i, tools):
                ti.atomic_add(self.suction_candidates[None], 1)

    @ti.func
    def _in_suction(self, i, tools):
        hit = 0
        p = self.world_position(self.pos[i])
        for t in range(tools):
            tool = self.suction_tools[t]
            if (p - ti.Vector([tool[0], tool[1], tool[2]])).norm() < tool[3]:
                hit = 1
        return hit

    @ti.kernel
    def _remove_suctioned(self, n: ti.i32, tools: ti.i32, probability: ti.f32, step: ti.i32):
        for i in range(n):
            if i < self.alive_count[None] and self.fate[i] == ALIVE and self._in_suction(i, tools):
                if hash01(ti.u32(self.uid[i]), ti.u32(step) + ti.u32(7)) < probability:
                    self.fate[i] = SUCTIONED

    # --- outputs ------------------------------------------------------------------------------
    def memory_bytes(self) -> dict:
        """Bytes held in Taichi fields: 'particles' (sized by the capacity) and 'grid' (texel maps, cells, splat)."""
        fields = [value for value in [*vars(self).values(), *vars(self.splatter).values()] if isinstance(value, ti.Field)]
        sizes = {"particles": 0, "grid": 0}
        for field in fields:
            lanes = getattr(field, "n", 1) * getattr(field, "m", 1)
            size = int(np.prod(field.shape)) * lanes * np.dtype(to_numpy_type(field.dtype)).itemsize
            sizes["particles" if self.pool_size in field.shape else "grid"] += size
        return sizes

    def accounting(self) -> dict:
        counters = self.counters.to_numpy()
        result = {key: int(counters[index]) for index, key in enumerate(KEYS)}
        result["alive"] = self.count
        return result

    def particle_arrays(self) -> dict:
        """particle_uv (N, 2) in [0, 1], particle_position_mm (N, 3), particle_velocity_mm_s (N, 3)."""
        n = self.count
        pos = self.pos.to_numpy()[:n].astype(np.float64)
        vel = self.vel.to_numpy()[:n].astype(np.float64)
        rows = np.clip(np.floor(pos[:, 1]).astype(int), 0, self.height - 1)
        cols = np.clip(np.floor(pos[:, 0]).astype(int), 0, self.width - 1)
        ex, ey = self.surface.tangent_u[rows, cols], -self.surface.tangent_v[rows, cols]
        position = self.surface.position_mm[rows, cols] + ex * (pos[:, :1] - cols[:, None] - 0.5) + ey * (pos[:, 1:] - rows[:, None] - 0.5)
        uv = np.stack([pos[:, 0] / self.width, 1.0 - pos[:, 1] / self.height], axis=1)
        return {
            "particle_uv": uv.astype(np.float32),
            "particle_position_mm": position.astype(np.float32),
            "particle_velocity_mm_s": (ex * vel[:, :1] + ey * vel[:, 1:]).astype(np.float32),
        }

    def metrics(self) -> dict:
        """metrics.json `bleeding` (sims.blood.methods.BleedingMethod): the common keys in ml, mm^2 and mm, then the pool's
        counts (particles)."""
        counts, ml = self.accounting(), self.particle_volume_ml
        thickness = self.blood_thickness_mm()
        return {"method": self.method, "blood_area_mm2": self.blood_area_mm2(),
                "max_thickness_mm": float(thickness.max(initial=0.0)), "volume_ml": counts["alive"] * ml,
                "spawned_ml": counts["spawned"] * ml, "on_surface_ml": counts["alive"] * ml,
                "suctioned_ml": counts["suctioned"] * ml, "left_surface_ml": counts["left_surface"] * ml,
                "dried_ml": counts["expired"] * ml, **counts, "capacity": self.capacity, "particle_volume_ml": ml}

    def state_arrays(self, display_grid: bool = True) -> dict:
        """state.npz: blood_thickness_mm (H, W) from the splat of this step's particles, and particle_arrays(); the
        particles have no grid of their own (display_grid is part of the method interface)."""
        return {"blood_thickness_mm": self.blood_thickness_mm(), **self.particle_arrays()}

    def blood_thickness_mm(self) -> np.ndarray:
        """(H, W) film thickness (mm) of this step's particles, splatted as the look does (sims.look.film)."""
        self.fresh_film(self.fresh_thickness)
        return self.fresh_thickness.to_numpy()

    def take_warning(self) -> str | None:
        """Once: why blood was lost (the pool filled up), else None."""
        if not self.pool_full_reported or self.pool_full_logged:
            return None
        self.pool_full_logged = True
        return (f"bleeding pool full ({self.capacity} particles): new blood is dropped and counted in metrics.json; "
                "raise bleeding.capacity, or use bleeding.method: height_field, whose cost does not grow with the volume")

    def blood_area_mm2(self) -> float:
        """Surface area (mm^2) of texels whose film is at least a quarter of the rest thickness."""
        covered = self.blood_thickness_mm() >= 0.25 * self.params["film_thickness_mm"]
        return float(self.surface.texel_area_mm2[covered & self.surface.mask].sum(dtype=np.float64))

    def fresh_film(self, out) -> None:
        """out (H, W) = the film (mm) of this step's particles: splatted and smoothed over 0.6 interaction radii."""
        self.splatter.film(self.pos, self.count, self.particle_volume_ml * 1e3, 0.6 * self.params["interaction_radius_mm"], out)


def auto_capacity(bleed_points: list, params: dict, duration_s: float) -> int:
    """Pool size for the scene: 1.25 x the most blood alive at once (rates x min(duration, lifetime)) + 4096."""
    if params["capacity"]:
        return int(params["capacity"])
    horizon = min(max(duration_s, 1.0), params["lifetime_s"])
    peak = sum(max([point["rate_ml_s"]] + [frame["rate_ml_s"] or 0.0 for frame in point["path"]]) for point in bleed_points)
    return int(min(2_000_000, math.ceil(1.25 * peak * horizon / particle_volume_ml(params)) + 4096))
