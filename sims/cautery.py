"""Cautery: Pennes bioheat on the surface (Laplace-Beltrami from the texel metric), contact heating,
Arrhenius damage and charring. Fields are (H, W) in the image orientation of sims.surface.

Heat: rho c dT/dt = k LB(T) + w_b rho_b c_b (T_body - T) + Q_tool.
- LB(T) is discretised as a symmetric graph Laplacian on the 8-neighbour texel grid. The
  conductance tensor K = sqrt|g| g^-1 (grid units) is split into non-negative weights along the
  two grid axes and one diagonal (a - |b|, c - |b|, |b|), so every explicit update is a convex
  combination of neighbour values: heat is conserved exactly (symmetric weights) and the maximum
  principle holds. Diffusion is isotropic in millimetres whatever the UV stretch.
- Two time-stepping schemes (SCHEMES; Cautery(..., scheme=...), scene key `cautery.scheme`):
  "explicit" (default): forward-Euler diffusion substeps, added automatically below the stability
  limit for any parameter value (explicit_substeps(dt): a few per 0.01 s step at 1024^2 texels for
  liver, growing with k / texel size^2, e.g. hundreds for dt = 1 s at k = 5 W/(m K)), at most
  MAX_SUBSTEPS: substeps(dt) raises SubstepLimit beyond it (a run is refused before its first step).
  "implicit": one backward-Euler diffusion step per time step, unconditionally stable. Backward
  Euler (theta = 1) rather than Crank-Nicolson because it keeps the discrete maximum principle for
  every dt: M = A + dt alpha L is an M-matrix, M^-1 A >= 0 with rows summing to 1, so the diffused
  field is a convex combination of the old one (CN rings where dt alpha / h^2 is large, i.e. at
  sharp tool edges). It is first order in time (at dt = 0.01 s its time error exceeds the explicit
  scheme's, whose substeps are shorter); it pays off for stiff cases (large k, small texels, long
  steps). The increment d = T_new - T solves M d = -dt alpha L T (A = texel areas, L the symmetric
  graph Laplacian above; M is symmetric positive definite) by Jacobi-preconditioned conjugate
  gradient, matrix-free, in plain Taichi kernels that run on a GPU unchanged (two per iteration;
  sums reduced in a fixed order, so results do not depend on the thread count), warm-started from
  the previous step's d. It stops when |r| <= tolerance |dt alpha L T| (default 1e-5) or after
  max_iterations (default 500). Heat is conserved to that tolerance (1^T L = 0: a step's heat error
  is the sum of the final residual). The diffused field is clamped into [min T, max T] of the
  step's start: a no-op (to rounding) after a converged solve, and what keeps a step that hit the
  iteration cap finite and bounded (such a step may then not conserve heat exactly).
  `last_iterations`: CG iterations of the last step ("explicit": its substeps); `last_residual`:
  the relative residual it reached (0 for explicit); substeps(dt) is 1 for the implicit scheme.
- Operator splitting (Lie, first order), both schemes: each (sub)step diffuses, then applies the
  exact relaxation below (a convex step too, so the whole step keeps the maximum principle); damage
  and char then integrate over the (sub)step at the mean of its start and end temperatures.
- Perfusion and contact heating relax T exponentially (exactly) toward a weighted target, so they
  are bounded for any rate: Q_tool = h w(d) (T_tip - T) / L with contact conductance h, heated
  layer L and w(d) falling from 1 at contact (signed distance d <= 0) to 0 at the contact distance.
- Damage: Omega += exp(ln A - Ea / (R T_K)) dt; coagulated fraction 1 - exp(-Omega).
- Char: char += rate (T - T_char) dt above the charring temperature, capped at 1.
UV chart seams conduct: texels that touch on the surface across a seam are linked with the weight
the stencil gives that direction (sims.seams; symmetric, so the two properties above still hold).
Open mesh borders and masked texels are insulated (zero flux).
"""
import math

import numpy as np
import taichi as ti

from sims.seams import seam_links

GAS_CONSTANT = 8.314462618  # J/(mol K)
KELVIN = 273.15
OMEGA_MAX = 1.0e6           # Omega is capped here: 1 - exp(-Omega) is 1 in float32 long before
STABILITY_MARGIN = 0.9      # explicit substep at this fraction of the convexity limit
# Explicit heat substeps a step may take. Past it the implicit scheme is the better choice: an explicit 512^2
# substep costs about 1 ms here, so 256 make a 0.01 s step 25x slower than real time. The lab's scenes stay far
# below (1-3 at 512^2-1024^2); the slider extremes reach 138 at 1024^2 (k = 5 W/(m K), dt = 0.05 s), 551 at 2048^2.
MAX_SUBSTEPS = 256
CHARRED_LEVEL = 0.5         # char at or above this counts as charred area
SCHEMES = ("explicit", "implicit")  # heat time stepping (sims.config.CAUTERY_SCHEMES lists the same)
CG_TOLERANCE = 1e-5         # implicit: relative residual |r| / |dt alpha L T| to stop at
CG_MAX_ITERATIONS = 500     # implicit: iteration cap (the step stays bounded when it is hit)
# slots of Cautery.sums, the CG scalars (sums reduced in the kernels: r.z, r.r, b.b, p.q)
RZ, RR, BB, PQ, RZ_OLD, ALPHA, LOW, HIGH = range(8)
CG_CHUNK = 64               # texels of a row one thread sums; rows per block in the second reduction stage
# neighbour offsets (row, col): +x, -x, +y, -y, (+x,+y), (-x,-y), (+x,-y), (-x,+y) with x = col, y = row
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (-1, 1), (1, -1))


def direction_coefficients(metric: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 8) a texel's own conductance along each direction of NEIGHBOURS (dimensionless, 0 where masked).

    metric: (H, W, 2, 2) in grid coordinates (x = columns, y = rows), mm^2 per texel^2. The conductance tensor
    sqrt|g| g^-1 split into non-negative parts along the two axes and one diagonal."""
    g = metric.astype(np.float64)
    det = np.where(mask, g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] ** 2, 1.0)
    root = np.sqrt(np.maximum(det, 1e-30))
    kxx, kyy, kxy = g[..., 1, 1] / root, g[..., 0, 0] / root, -g[..., 0, 1] / root
    cross = np.minimum(np.abs(kxy), np.minimum(kxx, kyy))  # diagonally dominant split (skewed texels lose a little anisotropy)
    coef = {
        "x": kxx - cross,
        "y": kyy - cross,
        "d": np.where(kxy > 0, cross, 0.0),   # along (+x, +y)
        "a": np.where(kxy < 0, cross, 0.0),   # along (+x, -y)
    }
    axis = {(0, 1): "x", (1, 0): "y", (1, 1): "d", (-1, 1): "a"}
    return np.stack([np.where(mask, coef[axis.get((dr, dc)) or axis[(-dr, -dc)]], 0.0) for dr, dc in NEIGHBOURS], axis=-1)


def edge_weights(coefficients: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Symmetric conductance weights (H, W, 8) to the neighbours in NEIGHBOURS (dimensionless): the mean of both
    texels' coefficients (direction_coefficients) where both lie on the surface."""
    height, width = mask.shape
    weights = np.zeros((height, width, 8))
    padded_mask = np.pad(mask, 1)
    for index, (dr, dc) in enumerate(NEIGHBOURS):
        c = coefficients[..., index]
        neighbour_c = np.pad(c, 1)[1 + dr: 1 + dr + height, 1 + dc: 1 + dc + width]
        neighbour_in = padded_mask[1 + dr: 1 + dr + height, 1 + dc: 1 + dc + width]
        weights[..., index] = np.where(mask & neighbour_in, 0.5 * (c + neighbour_c), 0.0)
    return weights.astype(np.float32)


class SubstepLimit(ValueError):
    """The explicit heat scheme would need more than MAX_SUBSTEPS substeps per step; the message says what to change."""


@ti.data_oriented
class Cautery:
    """Temperature, damage and char on a TissueSurface, heated by InstrumentFields."""

    def __init__(self, surface, tissue: dict, cautery: dict, instruments, scheme: str = "explicit",
                 tolerance: float = CG_TOLERANCE, max_iterations: int = CG_MAX_ITERATIONS):
        """scheme: one of SCHEMES. tolerance, max_iterations: the CG solve of the implicit scheme."""
        if scheme not in SCHEMES:
            raise ValueError(f"unknown heat scheme {scheme!r}; expected one of: {', '.join(SCHEMES)}")
        if not (tolerance > 0.0 and max_iterations >= 1):
            raise ValueError(f"need tolerance > 0 and max_iterations >= 1, got {tolerance}, {max_iterations}")
        self.surface, self.tissue, self.cautery, self.instruments = surface, tissue, cautery, instruments
        self.scheme, self.tolerance, self.max_iterations = scheme, float(tolerance), int(max_iterations)
        self.last_iterations = 0   # CG iterations (implicit) or substeps (explicit) of the last step
        self.last_residual = 0.0   # implicit: relative residual reached in the last step (0 for explicit)
        shape = surface.mask.shape
        self.temperature = [ti.field(ti.f32, shape), ti.field(ti.f32, shape)]
        self.omega = ti.field(ti.f32, shape)
        self.char = ti.field(ti.f32, shape)
        self.relax_rate = ti.field(ti.f32, shape)
        self.relax_target = ti.field(ti.f32, shape)
        self.mask = ti.field(ti.i32, shape)
        self.inv_area = ti.field(ti.f32, shape)
        self.weights = ti.Vector.field(8, ti.f32, shape)
        self.position = ti.Vector.field(3, ti.f32, shape)
        coefficients = direction_coefficients(surface.metric, surface.mask)
        weights = edge_weights(coefficients, surface.mask)
        link_start, link_to, link_weight = seam_links(surface, coefficients, NEIGHBOURS)
        self.seam_links = len(link_to) // 2  # texel pairs linked across UV seams
        self.link_start = ti.field(ti.i32, len(link_start))
        self.link_to, self.link_weight = ti.field(ti.i32, max(len(link_to), 1)), ti.field(ti.f32, max(len(link_to), 1))
        self.link_start.from_numpy(link_start)
        if len(link_to):
            self.link_to.from_numpy(link_to)
            self.link_weight.from_numpy(link_weight)
        area = surface.texel_area_mm2
        inv_area = np.where(surface.mask, 1.0 / np.where(surface.mask, area, 1.0), 0.0).astype(np.float32)
        link_sum = np.bincount(np.repeat(np.arange(len(link_start) - 1), np.diff(link_start)), weights=link_weight,
                               minlength=len(link_start) - 1).reshape(shape)
        self.max_exchange_1_mm2 = float(((weights.sum(axis=2) + link_sum) * inv_area).max())  # max over texels of sum(w)/A
        self.mask.from_numpy(surface.mask.astype(np.int32))
        self.inv_area.from_numpy(inv_area)
        self.weights.from_numpy(weights)
        self.position.from_numpy(surface.position_mm)
        if scheme == "implicit":  # CG work fields: increment d, residual r, z = r / diag, directions p (2 slots), q = M p
            self.delta, self.residual, self.precond = ti.field(ti.f32, shape), ti.field(ti.f32, shape), ti.field(ti.f32, shape)
            self.product, self.diag = ti.field(ti.f32, shape), ti.field(ti.f32, shape)
            self.direction = ti.field(ti.f32, (2,) + tuple(shape))
            self.sums = ti.field(ti.f32, 8)
            self.groups = -(-shape[1] // CG_CHUNK)  # threads per row in the reducing kernels
            self.blocks = -(-shape[0] // CG_CHUNK)
            self.partial = ti.field(ti.f32, (shape[0], self.groups, 3))  # per thread, then per row, per block of rows
            self.row_sum = ti.field(ti.f32, (shape[0], 3))
            self.block_sum = ti.field(ti.f32, (self.blocks, 3))
            self.interleaved = ti.lang.impl.current_cfg().arch not in (ti.x64, ti.arm64)  # GPU: adjacent threads, adjacent texels
        self.current = 0
        self._idle_contact = None  # parameters of the last contact pass made with no tool energized
        self.reset()

    # --- parameters ---------------------------------------------------------------------------
    @property
    def diffusivity_mm2_s(self) -> float:
        t = self.tissue
        return t["conductivity_w_mk"] / (t["density_kg_m3"] * t["specific_heat_j_kgk"]) * 1e6

    @property
    def perfusion_rate_1_s(self) -> float:
        t = self.tissue
        return t["perfusion_1_s"] * t["blood_density_kg_m3"] * t["blood_specific_heat_j_kgk"] / (t["density_kg_m3"] * t["specific_heat_j_kgk"])

    @property
    def contact_rate_1_s(self) -> float:
        t, c = self.tissue, self.cautery
        return c["contact_conductance_w_m2k"] / (t["density_kg_m3"] * t["specific_heat_j_kgk"] * c["heated_layer_mm"] * 1e-3)

    def substeps(self, dt_s: float) -> int:
        """Heat substeps a step of dt_s takes: explicit_substeps(dt_s), or 1 for the implicit scheme.
        Raises SubstepLimit when the explicit scheme would need more than MAX_SUBSTEPS."""
        if self.scheme == "implicit":
            return 1
        count = self.explicit_substeps(dt_s)
        if count > MAX_SUBSTEPS:
            texel_mm = 2.0 / math.sqrt(self.max_exchange_1_mm2)  # a square texel of side h exchanges 4 / h^2
            raise SubstepLimit(f"the explicit heat scheme needs {count:.3g} substeps per {dt_s:g} s step, over the cap of "
                               f"{MAX_SUBSTEPS} (smallest texels about {texel_mm:.2g} mm across); use cautery.scheme=implicit, "
                               "a smaller time_step_s or a smaller texture_size")
        return count

    def explicit_substeps(self, dt_s: float) -> int:
        """Explicit heat substeps needed for a step of dt_s to stay a convex update."""
        limit = STABILITY_MARGIN / max(self.diffusivity_mm2_s * self.max_exchange_1_mm2, 1e-30)
        return max(1, math.ceil(dt_s / limit))

    # --- state --------------------------------------------------------------------------------
    def reset(self) -> None:
        self.current = 0
        self.temperature[0].from_numpy(np.where(self.surface.mask, self.tissue["initial_temperature_c"], 0.0).astype(np.float32))
        self.omega.fill(0.0)
        self.char.fill(0.0)
        self._forget_warm_start()

    def set_temperature(self, values: np.ndarray) -> None:
        """Set T (H, W) in C on the surface (masked texels stay 0)."""
        self.temperature[self.current].from_numpy(np.where(self.surface.mask, values, 0.0).astype(np.float32))
        self._forget_warm_start()

    def _forget_warm_start(self) -> None:
        """The implicit solve starts from the last step's increment; a new state starts from 0 (reproducible runs)."""
        if self.scheme == "implicit":
            self.delta.fill(0.0)

    def temperature_c(self) -> np.ndarray:
        return self.temperature[self.current].to_numpy()

    def damage_omega(self) -> np.ndarray:
        return self.omega.to_numpy()

    def char_level(self) -> np.ndarray:
        return self.char.to_numpy()

    def step(self, dt_s: float) -> None:
        """Advance dt_s seconds: contact field from the current instrument poses, then heat substeps
        (explicit) or one backward-Euler step (implicit)."""
        t, c = self.tissue, self.cautery
        contact = (self.perfusion_rate_1_s, t["body_temperature_c"], self.contact_rate_1_s, c["contact_distance_mm"])
        if self.instruments.any_energized or contact != self._idle_contact:
            self._contact(*contact)
            self._idle_contact = None if self.instruments.any_energized else contact
        ea_r = t["activation_energy_j_mol"] / GAS_CONSTANT
        if self.scheme == "implicit":
            self._implicit_step(dt_s, ea_r)
            return
        count = self.substeps(dt_s)
        sub = dt_s / count
        self.last_iterations = count
        for _ in range(count):
            src, dst = self.temperature[self.current], self.temperature[1 - self.current]
            self._substep(src, dst, sub, self.diffusivity_mm2_s, t["arrhenius_ln_a"], ea_r, t["damage_threshold_c"],
                          t["char_temperature_c"], t["char_rate_1_s_c"])
            self.current = 1 - self.current

    def _implicit_step(self, dt_s: float, ea_r: float) -> None:
        """Backward Euler for the diffusion (Jacobi-preconditioned CG), then the exact relaxation."""
        t = self.tissue
        temperature = self.temperature[self.current]
        coupling = dt_s * self.diffusivity_mm2_s  # mm^2
        self._cg_start(temperature, coupling)
        scale, residual = float(self.sums[BB]), float(self.sums[RR])
        iterations = 0
        if scale > 0.0:
            threshold = self.tolerance**2 * scale
            while residual > threshold and iterations < self.max_iterations:
                old = iterations % 2
                self._cg_direction(old, 1 - old, coupling)
                self._cg_update(1 - old)
                iterations += 1
                residual = float(self.sums[RR])
            self.last_residual = math.sqrt(residual / scale)
        else:  # a uniform field: nothing diffuses
            self.delta.fill(0.0)
            self.last_residual = 0.0
        self.last_iterations = iterations
        self._cg_finish(temperature, dt_s, t["arrhenius_ln_a"], ea_r, t["damage_threshold_c"], t["char_temperature_c"], t["char_rate_1_s_c"])

    @ti.kernel
    def _contact(self, perfusion: ti.f32, body: ti.f32, contact: ti.f32, reach: ti.f32):
        for r, c in self.mask:
            rate = perfusion
            weighted = perfusion * body
            if self.mask[r, c]:
                for k in range(self.instruments.count):
                    near = (self.position[r, c] - self.instruments.position[k]).norm() < self.instruments.extent[k] + reach
                    if self.instruments.energized[k] and near:
                        d = self.instruments.distance(k, self.position[r, c])
                        w = 0.0
                        if d <= 0.0:
                            w = 1.0
                        elif d < reach:
                            w = 1.0 - d / reach
                        rate += contact * w
                        weighted += contact * w * self.instruments.tip_temperature[k]
            self.relax_rate[r, c] = rate
            self.relax_target[r, c] = weighted / rate if rate > 0.0 else body

    @ti.kernel
    def _substep(self, src: ti.template(), dst: ti.template(), dt: ti.f32, alpha: ti.f32, ln_a: ti.f32, ea_r: ti.f32, t_damage: ti.f32,
                 t_char: ti.f32, char_rate: ti.f32):
        height, width = src.shape[0], src.shape[1]
        for r, c in src:
            if self.mask[r, c]:
                t0 = src[r, c]
                flux = 0.0
                w = self.weights[r, c]
                for k in ti.static(range(8)):
                    rr = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1)
                    cc = ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                    flux += w[k] * (src[rr, cc] - t0)
                for m in range(self.link_start[r * width + c], self.link_start[r * width + c + 1]):
                    j = self.link_to[m]
                    flux += self.link_weight[m] * (src[j // width, j % width] - t0)
                t1 = self._relax(r, c, t0 + dt * alpha * self.inv_area[r, c] * flux, dt)
                dst[r, c] = t1
                self._damage(r, c, t0, t1, dt, ln_a, ea_r, t_damage, t_char, char_rate)

    @ti.func
    def _relax(self, r, c, t, dt):
        """Exact exponential relaxation toward relax_target at relax_rate (perfusion and contact)."""
        t1 = t
        rate = self.relax_rate[r, c]
        if rate > 0.0:
            target = self.relax_target[r, c]
            t1 = target + (t - target) * ti.exp(-rate * dt)
        return t1

    @ti.func
    def _damage(self, r, c, t0, t1, dt, ln_a, ea_r, t_damage, t_char, char_rate):
        """Arrhenius damage (above t_damage) and char over dt at the mean of the temperatures before and after."""
        mid = 0.5 * (t0 + t1)
        if mid > t_damage:
            exponent = ti.min(ln_a - ea_r / (mid + KELVIN), 80.0)
            self.omega[r, c] = ti.min(self.omega[r, c] + ti.exp(exponent) * dt, OMEGA_MAX)
        if mid > t_char:
            self.char[r, c] = ti.min(self.char[r, c] + char_rate * (mid - t_char) * dt, 1.0)

    # --- implicit scheme: (A + k L) d = -k L T with k = dt alpha, by Jacobi-preconditioned CG ------
    # (M d)_i = (A_i + k sum_j w_ij) d_i - k sum_j w_ij d_j is symmetric positive definite (w_ij = w_ji >= 0,
    # A_i > 0). The reducing kernels loop over (row, group): each thread sums CG_CHUNK texels of its row
    # (_chunk_column) into `partial`; _reduce then adds those up per row, per block of rows and in
    # total, each in a fixed order: the sums (so every result) are the same whatever the thread count,
    # and float32 sums never have more than a few dozen terms.
    @ti.func
    def _chunk_column(self, group, j):
        """Column of the j-th texel of a thread's chunk: contiguous on a CPU, interleaved on a GPU (coalesced reads)."""
        column = group * CG_CHUNK + j
        if ti.static(self.interleaved):
            column = j * self.groups + group
        return column

    @ti.func
    def _reduce(self, first: ti.template(), count: ti.template()):
        """sums[first + s] = the sum of partial[:, :, s] for s < count, in a fixed order (three stages)."""
        for r in range(self.mask.shape[0]):
            for s in ti.static(range(count)):
                total = 0.0
                for g in range(self.groups):
                    total += self.partial[r, g, s]
                self.row_sum[r, s] = total
        for b in range(self.blocks):
            for s in ti.static(range(count)):
                total = 0.0
                for j in range(CG_CHUNK):
                    row = b * CG_CHUNK + j
                    if row < self.mask.shape[0]:
                        total += self.row_sum[row, s]
                self.block_sum[b, s] = total
        ti.loop_config(serialize=True)
        for _ in range(1):
            for s in ti.static(range(count)):
                total = 0.0
                for b in range(self.blocks):
                    total += self.block_sum[b, s]
                self.sums[first + s] = total

    @ti.kernel
    def _cg_start(self, temperature: ti.template(), coupling: ti.f32):
        """Right-hand side b = -k L T, residual of the warm start d (last step's), z = r / diag; bounds of T."""
        for k in ti.static(range(8)):
            self.sums[k] = 0.0  # RZ_OLD = 0: the first direction is p = z
        self.sums[LOW] = 3.0e38
        self.sums[HIGH] = -3.0e38
        height, width, groups = self.mask.shape[0], self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(height, groups):
            rz, rr, bb, low, high = 0.0, 0.0, 0.0, 3.0e38, -3.0e38
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    t0 = temperature[r, c]
                    w = self.weights[r, c]
                    flux, total, spread = 0.0, 0.0, 0.0
                    for k in ti.static(range(8)):
                        rn = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1)
                        cn = ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                        flux += w[k] * (temperature[rn, cn] - t0)
                        total += w[k]
                        spread += w[k] * self.delta[rn, cn]
                    for m in range(self.link_start[r * width + c], self.link_start[r * width + c + 1]):
                        jr, jc, wl = self.link_to[m] // width, self.link_to[m] % width, self.link_weight[m]
                        flux += wl * (temperature[jr, jc] - t0)
                        total += wl
                        spread += wl * self.delta[jr, jc]
                    rhs = coupling * flux
                    diag = 1.0 / self.inv_area[r, c] + coupling * total
                    res = rhs - (diag * self.delta[r, c] - coupling * spread)
                    z = res / diag
                    self.diag[r, c] = diag
                    self.residual[r, c] = res
                    self.precond[r, c] = z
                    rz += res * z
                    rr += res * res
                    bb += rhs * rhs
                    low = ti.min(low, t0)
                    high = ti.max(high, t0)
            self.partial[r, g, 0] = rz
            self.partial[r, g, 1] = rr
            self.partial[r, g, 2] = bb
            ti.atomic_min(self.sums[LOW], low)  # min and max are exact: any order gives the same
            ti.atomic_max(self.sums[HIGH], high)
        self._reduce(RZ, 3)  # RZ, RR, BB

    @ti.kernel
    def _cg_direction(self, old: ti.i32, new: ti.i32, coupling: ti.f32):
        """p = z + beta p_old (computed for the texel and its neighbours), q = M p, sum p.q."""
        height, width, groups = self.mask.shape[0], self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(height, groups):
            beta = self.sums[RZ] / self.sums[RZ_OLD] if self.sums[RZ_OLD] > 0.0 else 0.0
            pq = 0.0
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    p = self.precond[r, c] + beta * self.direction[old, r, c]
                    w = self.weights[r, c]
                    spread = 0.0
                    for k in ti.static(range(8)):
                        rn = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1)
                        cn = ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                        spread += w[k] * (self.precond[rn, cn] + beta * self.direction[old, rn, cn])
                    for m in range(self.link_start[r * width + c], self.link_start[r * width + c + 1]):
                        jr, jc = self.link_to[m] // width, self.link_to[m] % width
                        spread += self.link_weight[m] * (self.precond[jr, jc] + beta * self.direction[old, jr, jc])
                    q = self.diag[r, c] * p - coupling * spread
                    self.direction[new, r, c] = p
                    self.product[r, c] = q
                    pq += p * q
            self.partial[r, g, 0] = pq
        self._reduce(PQ, 1)

    @ti.kernel
    def _cg_update(self, new: ti.i32):
        """d += a p, r -= a q with a = r.z / p.q; z = r / diag; sums r.z and r.r."""
        pq = self.sums[PQ]
        self.sums[ALPHA] = self.sums[RZ] / pq if pq > 0.0 else 0.0
        self.sums[RZ_OLD] = self.sums[RZ]
        width, groups = self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(self.mask.shape[0], groups):
            a = self.sums[ALPHA]
            rz, rr = 0.0, 0.0
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    self.delta[r, c] += a * self.direction[new, r, c]
                    res = self.residual[r, c] - a * self.product[r, c]
                    z = res / self.diag[r, c]
                    self.residual[r, c] = res
                    self.precond[r, c] = z
                    rz += res * z
                    rr += res * res
            self.partial[r, g, 0] = rz
            self.partial[r, g, 1] = rr
        self._reduce(RZ, 2)  # RZ, RR

    @ti.kernel
    def _cg_finish(self, temperature: ti.template(), dt: ti.f32, ln_a: ti.f32, ea_r: ti.f32, t_damage: ti.f32, t_char: ti.f32,
                   char_rate: ti.f32):
        """T + d clamped into the bounds of T (maximum principle), relaxation, damage and char."""
        for r, c in temperature:
            if self.mask[r, c]:
                t0 = temperature[r, c]
                t1 = t0 + self.delta[r, c]
                if t1 < self.sums[LOW]:  # comparisons, not min/max: a NaN stays NaN (and is reported)
                    t1 = self.sums[LOW]
                if t1 > self.sums[HIGH]:
                    t1 = self.sums[HIGH]
                t1 = self._relax(r, c, t1, dt)
                temperature[r, c] = t1
                self._damage(r, c, t0, t1, dt, ln_a, ea_r, t_damage, t_char, char_rate)

    # --- outputs ------------------------------------------------------------------------------
    def metrics(self) -> dict:
        mask, area = self.surface.mask, self.surface.texel_area_mm2.astype(np.float64)
        temperature = self.temperature_c()
        return {
            "max_temperature_c": float(temperature[mask].max()),
            "coagulated_area_mm2": float(area[self.damage_omega() >= 1.0].sum()),
            "charred_area_mm2": float(area[self.char_level() >= CHARRED_LEVEL].sum()),
        }
