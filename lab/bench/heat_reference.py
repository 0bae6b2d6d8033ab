"""Heat reference: a converged 3D axisymmetric model of a ball electrode pressed into a flat liver plane (issue 10).

The lab's heat model is layered in depth (docs/model/heat.md, "Layers in depth"); it is compared with
this reference. Finite volumes in r (radius) and z (depth into the tissue) with the cylindrical metric, implicit in
time, no Taichi.

Model (SI inside, millimetres / seconds / degrees Celsius at the interface):

    rho c dT/dt = div(k grad T) + w_b rho_b c_b (T_body - T)            in 0 < r < R_max, 0 < z < Z_max
    -k dT/dz = h w(d(r)) (T_tip - T_s) + h_air (1 - w) (T_air - T_s)    on the surface z = 0 (into the tissue)
    dT/dr = 0 on the axis; far faces r = R_max and z = Z_max insulated (or held at T_body, far_boundary="body")
    dOmega/dt = exp(ln A - Ea / (R T_K)) where T > damage_threshold_c, else 0

with w(d) = 1 where the ball's signed distance d <= 0, falling linearly to 0 at d = contact_distance_mm, and
d(r) = sqrt(r^2 + (R - press)^2) - R for a ball of radius R whose lowest point is `press` below the plane. The contact
flux enters through the top face of the top cell row: the face temperature T_s is eliminated with the half-cell
conductance 2k/dz0 in series with h w (linear in the cell temperature, so implicit). The contact weight of a top face
is its area-weighted mean of w(d(r)). At lift-off the tool is gone at once (w = 0 everywhere).

Grid: uniform cells of `grid_mm` in a core (r <= core_r_mm = 2, z <= core_z_mm = 1.5 mm) holding the whole coagulated
zone (about 1.6 mm in radius, 1.2 mm deep), then cells growing geometrically by `growth` = 1.08 per cell up to
`max_cell_mm` = 1 mm out to R_max = Z_max = 20 mm (mildly graded; 133 x 114 cells at 0.025 mm). The heat reaches
about 3 mm in 62 s (sqrt(alpha t)); doubling the domain, holding the far faces at body temperature instead of
insulating them, or doubling the uniform core changes no reported digit (convergence()).
Time: Crank-Nicolson with a Rannacher start (two backward-Euler half steps after every change of the boundary: at
contact and at lift-off), or backward Euler throughout (scheme="euler": an M-matrix, so the maximum principle holds
at any step). One sparse LU factorisation (scipy splu) per (dt, boundary) pair, reused across steps. Arrhenius per
cell (and per surface face, with the face temperature) with the step's mean temperature. Time step 0.01 s up to 10 s
after lift-off, 0.05 s after. Cost: the 0.025 mm run (2200 steps) takes about 8 CPU seconds. Dot products are
elementwise numpy, not BLAS: OpenBLAS threads made a step 30 times slower on a loaded shared machine.

Outputs: surface temperature at the axis, coagulated area at the surface (Omega >= 1 at z = 0, log Omega interpolated
linearly between column centres), coagulation depth on the axis (largest z with Omega >= 1, interpolated likewise from
the surface value and the cell centres), coagulated volume (the same interpolation along z in every column, times the
column's annulus area).
"""
import math
import time

import numpy as np

GAS_CONSTANT = 8.314462618  # J/(mol K), as sims.heat.cautery
KELVIN = 273.15

# Issue 10's figures for this contact, from an earlier session's run whose contact model is not recorded.
ISSUE_FIGURES = {
    "samples": {2.0: {"surface_center_c": 224.0, "coagulated_area_mm2": 7.1},
                7.0: {"surface_center_c": 62.0, "coagulated_area_mm2": 8.0},
                12.0: {"surface_center_c": 48.0, "coagulated_area_mm2": 8.0},
                32.0: {"surface_center_c": 39.0, "coagulated_area_mm2": 8.0},
                62.0: {"surface_center_c": 38.0, "coagulated_area_mm2": 8.0}},
    "coagulation_depth_mm": 1.2,
    "stops_growing_after_lift_off_s": 5.0,
}


def tissue_defaults() -> dict:
    """sims.scene.params TISSUE defaults (the liver preset), imported when called."""
    from sims.scene import params

    return {name: spec.default for name, spec in params.TISSUE.items()}


def cautery_defaults() -> dict:
    """sims.scene.params CAUTERY defaults (contact conductance, contact distance, ...), imported when called."""
    from sims.scene import params

    return {name: spec.default for name, spec in params.CAUTERY.items()}


def graded_faces(cell_mm: float, core_mm: float, extent_mm: float, growth: float = 1.08, max_cell_mm: float = 0.5) -> np.ndarray:
    """Face positions (mm, increasing from 0 to extent_mm, shape (n + 1,)): uniform cells of cell_mm up to core_mm
    (rounded to a whole number of cells), then each cell `growth` times the previous one, capped at max_cell_mm;
    the graded cells are scaled by a common factor (close to 1) so the last face lands on extent_mm."""
    n_core = max(1, int(round(core_mm / cell_mm)))
    core = min(n_core * cell_mm, extent_mm)
    n_core = max(1, int(round(core / cell_mm)))
    widths = [core / n_core] * n_core
    graded, width, rest = [], cell_mm, extent_mm - core
    while sum(graded) < rest - 1e-12:
        width = min(width * growth, max(max_cell_mm, cell_mm))
        graded.append(width)
    if graded:
        graded = list(np.asarray(graded) * (rest / sum(graded)))
    return np.concatenate([[0.0], np.cumsum(widths + graded)])


def ball_contact_weights(r_faces_mm: np.ndarray, radius_mm: float, press_mm: float, contact_distance_mm: float,
                         samples: int = 64) -> np.ndarray:
    """Area-weighted mean contact weight w(d(r)) over each top face ring (shape (nr,)): w = 1 for d <= 0, linear to 0
    at d = contact_distance_mm; d(r) = sqrt(r^2 + (R - press)^2) - R (mm). Midpoint rule in r^2 (equal areas)."""
    inner, outer = r_faces_mm[:-1, None] ** 2, r_faces_mm[1:, None] ** 2
    s = inner + (outer - inner) * (np.arange(samples) + 0.5) / samples
    d = np.sqrt(s + (radius_mm - press_mm) ** 2) - radius_mm
    if contact_distance_mm > 0:
        w = np.clip(1.0 - d / contact_distance_mm, 0.0, 1.0)
    else:
        w = (d <= 0).astype(float)
    return w.mean(axis=1)


class AxisymmetricHeat:
    """Pennes bioheat and Arrhenius damage on an axisymmetric r-z finite-volume grid.

    r_faces_mm (nr + 1,), z_faces_mm (nz + 1,): face positions in mm, both starting at 0 (axis, surface).
    Fields: temperature_c (nz, nr) cell temperatures in C; omega (nz, nr) Arrhenius integral per cell; omega_surface
    (nr,) the same for the surface faces (z = 0), from the face temperature. Row 0 is the top (surface) row.
    tissue: sims.scene.params TISSUE names. far_boundary: "insulated" (zero flux through r = R_max and z = Z_max) or "body"
    (those faces held at body temperature, through the half cell).
    """

    def __init__(self, r_faces_mm, z_faces_mm, tissue: dict, far_boundary: str = "insulated"):
        from scipy import sparse

        if far_boundary not in ("insulated", "body"):
            raise ValueError("far_boundary is 'insulated' or 'body'")
        self.tissue = dict(tissue)
        self.r_faces = np.asarray(r_faces_mm, float) * 1e-3  # m
        self.z_faces = np.asarray(z_faces_mm, float) * 1e-3
        self.nr, self.nz = len(self.r_faces) - 1, len(self.z_faces) - 1
        self.r_centres = 0.5 * (self.r_faces[1:] + self.r_faces[:-1])
        self.z_centres = 0.5 * (self.z_faces[1:] + self.z_faces[:-1])
        dz = np.diff(self.z_faces)
        self.ring_area = math.pi * (self.r_faces[1:] ** 2 - self.r_faces[:-1] ** 2)  # m^2, (nr,)
        self.volume = dz[:, None] * self.ring_area[None, :]  # m^3, (nz, nr)
        t = self.tissue
        k = t["conductivity_w_mk"]
        self.k = k
        self.body_c = t["body_temperature_c"]
        self.capacity = (t["density_kg_m3"] * t["specific_heat_j_kgk"] * self.volume).ravel()  # J/K per cell
        blood = t["perfusion_1_s"] * t["blood_density_kg_m3"] * t["blood_specific_heat_j_kgk"]  # W/(m^3 K)
        self.perfusion = (blood * self.volume).ravel()  # W/K per cell
        index = np.arange(self.nz * self.nr).reshape(self.nz, self.nr)
        rows, cols, values = [], [], []

        def link(a, b, g):
            rows.extend([a.ravel(), b.ravel(), a.ravel(), b.ravel()])
            cols.extend([a.ravel(), b.ravel(), b.ravel(), a.ravel()])
            g = g.ravel()
            values.extend([g, g, -g, -g])

        if self.nr > 1:  # radial faces between columns j and j + 1: area 2 pi r dz
            g = k * 2 * math.pi * self.r_faces[None, 1:-1] * dz[:, None] / np.diff(self.r_centres)[None, :]
            link(index[:, :-1], index[:, 1:], g)
        if self.nz > 1:  # vertical faces between rows i and i + 1: area pi (r_out^2 - r_in^2)
            g = k * self.ring_area[None, :] / np.diff(self.z_centres)[:, None]
            link(index[:-1, :], index[1:, :], g)
        far = np.zeros((self.nz, self.nr))
        if far_boundary == "body":
            far[:, -1] += k * 2 * math.pi * self.r_faces[-1] * dz / (self.r_faces[-1] - self.r_centres[-1])
            far[-1, :] += k * self.ring_area / (self.z_faces[-1] - self.z_centres[-1])
        self.far = far.ravel()
        n = self.nz * self.nr
        conduction = sparse.coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)) \
            if values else sparse.coo_matrix((n, n))
        self._static = (conduction.tocsr() + sparse.diags(self.perfusion + self.far)).tocsc()
        self.half_cell_conductance = 2 * k / dz[0]  # W/(m^2 K): top cell centre to the surface
        self.temperature_c = np.full((self.nz, self.nr), t["initial_temperature_c"], float)
        self.omega = np.zeros((self.nz, self.nr))
        self.omega_surface = np.zeros(self.nr)
        self.time_s = 0.0
        self.delivered_j = 0.0  # heat in through the top face (contact and air)
        self.perfused_j = 0.0  # heat in from perfusion (negative when blood carries heat away)
        self.far_j = 0.0  # heat in through the far faces
        self._factors = {}
        self.set_top(np.zeros(self.nr), np.full(self.nr, self.body_c))
        self._restart = True

    def set_top(self, conductance_w_m2k, temperature_c) -> None:
        """The surface exchange per top face (shape (nr,) each): flux into the tissue H (T_ext - T_s), W/m^2, with
        H = h w + h_air (1 - w) and T_ext its weighted temperature. A change is a discontinuity: the next step
        restarts Crank-Nicolson with backward-Euler half steps."""
        self.top_h = np.asarray(conductance_w_m2k, float).copy()
        self.top_c = np.asarray(temperature_c, float).copy()
        with np.errstate(divide="ignore"):
            resistance = 1.0 / np.maximum(self.top_h, 1e-300) + 1.0 / self.half_cell_conductance  # m^2 K / W
            series = np.where(self.top_h > 0, 1.0 / resistance, 0.0)
        self.top_g = series * self.ring_area  # W/K per top cell
        diag = np.zeros(self.nz * self.nr)
        diag[: self.nr] = self.top_g
        self._diag = diag
        self._source = self.perfusion * self.body_c + self.far * self.body_c
        self._source[: self.nr] += self.top_g * self.top_c
        self._factors = {}
        self._key = object()
        self._restart = True

    def set_temperature(self, temperature_c) -> None:
        """Cell temperatures (C, broadcast to (nz, nr))."""
        self.temperature_c = np.broadcast_to(np.asarray(temperature_c, float), (self.nz, self.nr)).copy()

    def surface_temperature_c(self, cells_c=None) -> np.ndarray:
        """Face temperature at z = 0 per column (C, (nr,)) from the flux balance H (T_ext - T_s) = (2k/dz0)(T_s - T_top)."""
        top = (self.temperature_c if cells_c is None else cells_c)[0]
        k_half = self.half_cell_conductance
        return (self.top_h * self.top_c + k_half * top) / (self.top_h + k_half)

    def heat_content_j(self) -> float:
        """Sum of rho c V T over the cells (J, relative to 0 C)."""
        return float((self.capacity * self.temperature_c.ravel()).sum())

    def _factor(self, a: float):
        """splu of C + a L (a = dt for backward Euler, dt/2 for Crank-Nicolson and its half steps), cached."""
        from scipy import sparse
        from scipy.sparse.linalg import splu

        key = round(a, 15)
        if key not in self._factors:
            matrix = sparse.diags(self.capacity) + a * (self._static + sparse.diags(self._diag))
            # the matrix is symmetric: minimum degree on its pattern, no pivoting needed (diagonally dominant)
            self._factors[key] = splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                      options={"SymmetricMode": True})
        return self._factors[key]

    def _apply(self, x):
        return self._static @ x + self._diag * x

    def _fluxes(self, x):
        """Heat flows into the tissue (W): top face, perfusion, far faces, for cell temperatures x (flat)."""
        # elementwise products, not BLAS dot: OpenBLAS threads crawl on a loaded machine
        top = float((self.top_g * (self.top_c - x[: self.nr])).sum())
        return top, float((self.perfusion * (self.body_c - x)).sum()), float((self.far * (self.body_c - x)).sum())

    def _damage(self, before, after, dt):
        """Arrhenius with the step's mean temperature, in the cells and at the surface faces."""
        ln_a, ea_r = self.tissue["arrhenius_ln_a"], self.tissue["activation_energy_j_mol"] / GAS_CONSTANT
        threshold = self.tissue["damage_threshold_c"]
        for mean, omega in ((0.5 * (before + after), self.omega),
                            (0.5 * (self.surface_temperature_c(before) + self.surface_temperature_c(after)), self.omega_surface)):
            hot = mean > threshold
            if hot.any():
                omega[hot] += np.exp(ln_a - ea_r / (mean[hot] + KELVIN)) * dt

    def _backward_euler(self, dt):
        x = self.temperature_c.ravel()
        new = self._factor(dt).solve(self.capacity * x + dt * self._source)
        top, perf, far = self._fluxes(new)
        self.delivered_j += dt * top
        self.perfused_j += dt * perf
        self.far_j += dt * far
        return new

    def step(self, dt_s: float, scheme: str = "cn") -> None:
        """Advance dt_s seconds. scheme "cn": Crank-Nicolson, except right after a boundary change, when the step is two
        backward-Euler half steps (Rannacher start: damps the stiff modes a jump excites); "euler": backward Euler."""
        before = self.temperature_c.copy()
        if scheme == "euler":
            new = self._backward_euler(dt_s).reshape(self.nz, self.nr)
            self._damage(before, new, dt_s)
        elif scheme == "cn":
            if self._restart:
                for _ in range(2):
                    start = self.temperature_c.copy()
                    self.temperature_c = self._backward_euler(0.5 * dt_s).reshape(self.nz, self.nr)
                    self._damage(start, self.temperature_c, 0.5 * dt_s)
                self._restart = False
                self.time_s += dt_s
                return
            x = before.ravel()
            new = self._factor(0.5 * dt_s).solve(self.capacity * x - 0.5 * dt_s * self._apply(x) + dt_s * self._source)
            old_fluxes, new_fluxes = self._fluxes(x), self._fluxes(new)
            self.delivered_j += 0.5 * dt_s * (old_fluxes[0] + new_fluxes[0])
            self.perfused_j += 0.5 * dt_s * (old_fluxes[1] + new_fluxes[1])
            self.far_j += 0.5 * dt_s * (old_fluxes[2] + new_fluxes[2])
            new = new.reshape(self.nz, self.nr)
            self._damage(before, new, dt_s)
        else:
            raise ValueError("scheme is 'cn' or 'euler'")
        self.temperature_c = new
        self.time_s += dt_s

    # --- coagulation measures (Omega >= 1), mm units -------------------------------------------------------------

    def _log_omega(self):
        return (np.log(np.maximum(self.omega_surface, 1e-300)), np.log(np.maximum(self.omega, 1e-300)))

    def coagulated_area_mm2(self) -> float:
        """Area of Omega >= 1 at z = 0 (mm^2): log Omega of the surface faces linear between column centres (constant
        from the axis to the first centre)."""
        f = self._log_omega()[0]
        r = self.r_centres * 1e3
        a, b, fa, fb = r[:-1], r[1:], f[:-1], f[1:]
        with np.errstate(invalid="ignore", divide="ignore"):
            cross = a + (b - a) * fa / (fa - fb)
        lo = np.where(fa >= 0, a, np.where(fb >= 0, cross, a))
        hi = np.where(fa >= 0, np.where(fb >= 0, b, cross), np.where(fb >= 0, b, a))
        total = float(math.pi * (hi ** 2 - lo ** 2).sum())
        if f[0] >= 0:
            total += math.pi * r[0] ** 2
        if f[-1] >= 0:
            total += math.pi * ((self.r_faces[-1] * 1e3) ** 2 - r[-1] ** 2)
        return total

    def coagulated_radius_mm(self) -> float:
        """Largest surface radius with Omega >= 1 (mm), log Omega linear between column centres; 0 if none."""
        f = self._log_omega()[0]
        return _last_crossing(self.r_centres * 1e3, f, start=0.0)

    def coagulation_depth_mm(self, column: int = 0) -> float:
        """Largest depth with Omega >= 1 in a column (mm; column 0 is at r = dr/2, the axis to second order): the surface
        value at z = 0 then the cell centres, log Omega linear between them; 0 if none."""
        fs, fc = self._log_omega()
        z = np.concatenate([[0.0], self.z_centres * 1e3])
        return _last_crossing(z, np.concatenate([[fs[column]], fc[:, column]]), start=0.0)

    def coagulated_volume_mm3(self) -> float:
        """Volume with Omega >= 1 (mm^3): per column the length along z where the interpolated log Omega >= 0 (surface
        value, then the cell centres), times the column's annulus area."""
        fs, fc = self._log_omega()
        f = np.vstack([fs[None, :], fc])  # (nz + 1, nr)
        z = np.concatenate([[0.0], self.z_centres * 1e3])[:, None]
        fa, fb, length = f[:-1], f[1:], np.diff(z, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            part = np.where((fa >= 0) & (fb >= 0), 1.0,
                            np.where((fa >= 0) & (fb < 0), fa / (fa - fb), np.where((fa < 0) & (fb >= 0), fb / (fb - fa), 0.0)))
        column_length = (part * length).sum(axis=0)
        return float((column_length * self.ring_area).sum() * 1e6)


def _last_crossing(x, f, start=0.0):
    """Largest x where the piecewise-linear f is >= 0 (f[k] at x[k]); `start` if f < 0 everywhere."""
    above = np.nonzero(f >= 0)[0]
    if above.size == 0:
        return start
    k = above[-1]
    if k == len(f) - 1:
        return float(x[-1])
    return float(x[k] + (x[k + 1] - x[k]) * f[k] / (f[k] - f[k + 1]))


def _split_overrides(overrides: dict):
    tissue, cautery = tissue_defaults(), cautery_defaults()
    for name, value in overrides.items():
        if name in tissue:
            tissue[name] = float(value)
        elif name in cautery:
            cautery[name] = float(value)
        else:
            raise ValueError(f"unknown parameter {name!r}: not in sims.scene.params TISSUE or CAUTERY")
    return tissue, cautery


def ball_contact_reference(grid_mm: float = 0.05, dt_s: float = 0.01, tip_c: float = 250.0, radius_mm: float = 1.5,
                           press_mm: float = 0.2, contact_s: float = 2.0, end_s: float = 62.0,
                           sample_times_s=(2.0, 7.0, 12.0, 32.0, 62.0), scheme: str = "cn", dt_late_s: float | None = None,
                           late_after_s: float = 10.0, r_max_mm: float = 20.0, z_max_mm: float = 20.0,
                           core_r_mm: float = 2.0, core_z_mm: float = 1.5, growth: float = 1.08, max_cell_mm: float = 1.0,
                           far_boundary: str = "insulated", air_conductance_w_m2k: float = 0.0,
                           air_temperature_c: float = 22.0, **overrides) -> dict:
    """The ball electrode (radius_mm, at tip_c) pressed press_mm into a flat liver plane for contact_s seconds, then
    lifted at once; simulated until end_s. Time step dt_s, and dt_late_s (default 5 dt_s) from late_after_s after
    lift-off on (slow cooling; Crank-Nicolson goes on across the change of step). Every sample time and the lift-off
    fall on a step (a segment between them is cut into equal steps no longer than its dt). Grid and domain: see the
    module docstring; far_boundary "insulated" or "body"; air_conductance_w_m2k (W/(m^2 K), default 0: insulated)
    toward air_temperature_c where the ball does not touch. overrides: any sims.scene.params TISSUE or CAUTERY name
    (perfusion_1_s, contact_conductance_w_m2k, contact_distance_mm, ...). Times in s, lengths in mm, temperatures in C.

    Returns a JSON-ready dict:
      model: the parameters and grid (cells nr x nz, smallest and largest cell);
      samples: one dict per sample time (t_s, surface_center_c the face temperature at the axis column, surface_max_c,
        max_c over the cells, coagulated_area_mm2, coagulated_radius_mm, coagulation_depth_mm on the axis,
        coagulated_volume_mm3); the sample at contact_s is taken before lift-off;
      history: lists, one entry per step plus t = 0: time_s, surface_center_c, coagulated_area_mm2,
        coagulation_depth_mm, coagulated_volume_mm3;
      settled: seconds after lift-off at which area, depth and volume reach 99 % and 99.9 % of their end values;
      energy_j: heat in through the surface, by perfusion, through the far faces, and the heat content change;
      wall_s and cpu_s (this process's CPU seconds: the machine may be shared), steps."""
    started, cpu_started = time.perf_counter(), time.process_time()
    tissue, cautery = _split_overrides(overrides)
    r_faces = graded_faces(grid_mm, core_r_mm, r_max_mm, growth, max_cell_mm)
    z_faces = graded_faces(grid_mm, core_z_mm, z_max_mm, growth, max_cell_mm)
    model = AxisymmetricHeat(r_faces, z_faces, tissue, far_boundary)
    h = cautery["contact_conductance_w_m2k"]
    w = ball_contact_weights(r_faces, radius_mm, press_mm, cautery["contact_distance_mm"])

    def exchange(weight):
        conductance = h * weight + air_conductance_w_m2k * (1.0 - weight)
        with np.errstate(invalid="ignore"):
            ext = np.where(conductance > 0, (h * weight * tip_c + air_conductance_w_m2k * (1.0 - weight) * air_temperature_c)
                           / np.maximum(conductance, 1e-300), tissue["body_temperature_c"])
        return conductance, ext

    contact, lifted = exchange(w), exchange(np.zeros_like(w))
    marks = sorted({0.0, float(end_s), *(float(t) for t in sample_times_s if 0 < t <= end_s),
                    *([float(contact_s)] if 0 < contact_s < end_s else []),
                    *([float(contact_s + late_after_s)] if 0 < contact_s + late_after_s < end_s else [])})
    energy_start = model.heat_content_j()
    history = {name: [] for name in ("time_s", "surface_center_c", "coagulated_area_mm2", "coagulation_depth_mm",
                                     "coagulated_volume_mm3")}

    def record():
        history["time_s"].append(model.time_s)
        history["surface_center_c"].append(float(model.surface_temperature_c()[0]))
        history["coagulated_area_mm2"].append(model.coagulated_area_mm2())
        history["coagulation_depth_mm"].append(model.coagulation_depth_mm())
        history["coagulated_volume_mm3"].append(model.coagulated_volume_mm3())

    def sample():
        surface = model.surface_temperature_c()
        return {"t_s": model.time_s, "surface_center_c": float(surface[0]), "surface_max_c": float(surface.max()),
                "max_c": float(model.temperature_c.max()), "coagulated_area_mm2": model.coagulated_area_mm2(),
                "coagulated_radius_mm": model.coagulated_radius_mm(), "coagulation_depth_mm": model.coagulation_depth_mm(),
                "coagulated_volume_mm3": model.coagulated_volume_mm3()}

    model.set_top(*(contact if contact_s > 0 else lifted))
    in_contact = contact_s > 0
    record()
    samples, steps = [], 0
    for begin, finish in zip(marks[:-1], marks[1:]):
        if in_contact and begin >= contact_s - 1e-12:
            model.set_top(*lifted)
            in_contact = False
        segment_dt = dt_s if begin < contact_s + late_after_s - 1e-9 else (dt_late_s or 5 * dt_s)
        count = max(1, int(math.ceil((finish - begin) / segment_dt - 1e-9)))
        step = (finish - begin) / count
        for index in range(count):
            model.step(step, scheme)
            steps += 1
            if index == count - 1:
                model.time_s = finish  # no drift from summing steps
            record()
        if any(abs(finish - float(t)) < 1e-9 for t in sample_times_s):
            samples.append(sample())
    times = np.asarray(history["time_s"])
    settled = {}
    for name in ("coagulated_area_mm2", "coagulation_depth_mm", "coagulated_volume_mm3"):
        values = np.asarray(history[name])
        final = values[-1]
        for fraction in (0.99, 0.999):
            reached = np.nonzero(values >= fraction * final)[0] if final > 0 else np.array([0])
            settled[f"{name}_{fraction:g}"] = float(times[reached[0]] - contact_s)
    dz_min, dz_max = np.diff(z_faces).min(), np.diff(z_faces).max()
    return {
        "model": {"grid_mm": grid_mm, "dt_s": dt_s, "dt_late_s": dt_late_s or 5 * dt_s, "late_after_s": late_after_s,
                  "scheme": scheme, "tip_c": tip_c, "radius_mm": radius_mm,
                  "press_mm": press_mm, "contact_s": contact_s, "end_s": end_s, "r_max_mm": r_max_mm, "z_max_mm": z_max_mm,
                  "core_r_mm": core_r_mm, "core_z_mm": core_z_mm, "growth": growth, "max_cell_mm": max_cell_mm,
                  "far_boundary": far_boundary, "air_conductance_w_m2k": air_conductance_w_m2k,
                  "air_temperature_c": air_temperature_c, "tissue": tissue,
                  "contact_conductance_w_m2k": h, "contact_distance_mm": cautery["contact_distance_mm"],
                  "nr": model.nr, "nz": model.nz, "cells": model.nr * model.nz,
                  "smallest_cell_mm": float(min(np.diff(r_faces).min(), dz_min)),
                  "largest_cell_mm": float(max(np.diff(r_faces).max(), dz_max)),
                  "full_contact_radius_mm": float(math.sqrt(max(radius_mm ** 2 - (radius_mm - press_mm) ** 2, 0.0))),
                  "contact_area_mm2": float((w * model.ring_area).sum() * 1e6)},
        "samples": samples,
        "history": history,
        "settled": settled,
        "energy_j": {"surface": model.delivered_j, "perfusion": model.perfused_j, "far": model.far_j,
                     "content_change": model.heat_content_j() - energy_start},
        "steps": steps,
        "wall_s": time.perf_counter() - started,
        "cpu_s": time.process_time() - cpu_started,
    }


SAMPLE_KEYS = ("surface_center_c", "coagulated_area_mm2", "coagulation_depth_mm", "coagulated_volume_mm3")


def _differences(run: dict, best: dict) -> dict:
    """Largest absolute difference per sample key between two runs, over the sample times."""
    return {key: max(abs(a[key] - b[key]) for a, b in zip(run["samples"], best["samples"])) for key in SAMPLE_KEYS}


def convergence(grids_mm=(0.1, 0.05, 0.025), dt_s: float = 0.01, dt_check_grid_mm: float = 0.05,
                domain_check: bool = True, history_every_s: float = 0.1, **kwargs) -> dict:
    """ball_contact_reference on each grid (time step dt_s), then on dt_check_grid_mm with dt_s / 2 and 2 dt_s (time
    convergence) and, with domain_check, with R_max and Z_max doubled, with the far faces held at body temperature
    instead of insulated, and with the uniform core doubled (less grading). Differences: largest over the sample times
    of |run - reference| per quantity, the reference being the finest grid (for the grids), the dt_s / 2 run (for time
    steps) and the run on the same grid with the default domain (for the domain checks). Histories thinned to one
    point per history_every_s."""
    runs = [dict(ball_contact_reference(grid_mm=g, dt_s=dt_s, **kwargs), kind="grid") for g in grids_mm]
    finest = runs[-1]
    for run in runs:
        run["difference"] = _differences(run, finest)
    base = next((run for run in runs if abs(run["model"]["grid_mm"] - dt_check_grid_mm) < 1e-12), None)
    if base is None:
        base = dict(ball_contact_reference(grid_mm=dt_check_grid_mm, dt_s=dt_s, **kwargs), kind="grid")
    time_runs = [dict(ball_contact_reference(grid_mm=dt_check_grid_mm, dt_s=step, **kwargs), kind="time step")
                 for step in (2 * dt_s, dt_s / 2)]
    for run in (time_runs[0], base):
        run_diff = _differences(run, time_runs[1])
        run.setdefault("difference_dt", run_diff)
    time_runs[1]["difference_dt"] = _differences(time_runs[1], time_runs[1])
    domain_runs = []
    if domain_check:
        r_max, z_max = kwargs.get("r_max_mm", 20.0), kwargs.get("z_max_mm", 20.0)
        core_r, core_z = kwargs.get("core_r_mm", 2.0), kwargs.get("core_z_mm", 1.5)
        variants = (("domain doubled", dict(r_max_mm=2 * r_max, z_max_mm=2 * z_max)),
                    ("far faces at body temperature", dict(far_boundary="body")),
                    ("uniform core doubled", dict(core_r_mm=2 * core_r, core_z_mm=2 * core_z)))
        for kind, change in variants:
            variant = dict(ball_contact_reference(grid_mm=dt_check_grid_mm, dt_s=dt_s, **dict(kwargs, **change)), kind=kind)
            variant["difference_domain"] = _differences(variant, base)
            domain_runs.append(variant)
    everything = runs + ([] if any(base is run for run in runs) else [base]) + time_runs + domain_runs
    for run in everything:
        history = run["history"]
        times = np.asarray(history["time_s"])
        keep, last = [], -math.inf
        for index, t in enumerate(times):
            if t >= last + history_every_s - 1e-9 or index == len(times) - 1:
                keep.append(index)
                last = t
        run["history"] = {name: [values[i] for i in keep] for name, values in history.items()}
    return {"grids": runs, "time_steps": [time_runs[0], base, time_runs[1]], "domain": domain_runs}


def run(quick: bool) -> dict:
    """Bench section: the convergence study (quick: grids 0.1 and 0.05 mm, dt 0.02 s, no domain check)."""
    if quick:
        return convergence(grids_mm=(0.1, 0.05), dt_s=0.02, dt_check_grid_mm=0.1, domain_check=False)
    return convergence()


def render(results: dict) -> list[str]:
    finest = results["grids"][-1]
    m = finest["model"]
    lines = [
        "## Heat reference: ball electrode on a liver plane, axisymmetric 3D",
        "",
        f"A ball of radius {m['radius_mm']} mm at {m['tip_c']:g} C pressed {m['press_mm']} mm into a flat liver plane for "
        f"{m['contact_s']:g} s, then lifted at once. Finite volumes in r and z (cylindrical metric), core cells of the grid",
        f"size out to r = {m['core_r_mm']} mm, z = {m['core_z_mm']} mm, then growing by {m['growth']} per cell up to "
        f"{m['max_cell_mm']} mm, domain {m['r_max_mm']:g} x {m['z_max_mm']:g} mm ({m['far_boundary']} far faces).",
        f"Contact flux h w(d) (T_tip - T_s) on the top face, h = {m['contact_conductance_w_m2k']:g} W/(m² K), w falling "
        f"linearly to 0 at d = {m['contact_distance_mm']} mm (full contact out to r = {m['full_contact_radius_mm']:.3f} mm);",
        f"surface insulated elsewhere (h_air = {m['air_conductance_w_m2k']:g}). Pennes perfusion "
        f"{m['tissue']['perfusion_1_s']:g} 1/s, Arrhenius above {m['tissue']['damage_threshold_c']:g} C. Time: {m['scheme']} "
        "(Crank-Nicolson with backward-Euler half steps after contact and lift-off).",
        "",
        f"Finest grid ({m['grid_mm']} mm, {m['nr']} x {m['nz']} cells, dt {m['dt_s']} s, {finest['wall_s']:.0f} s wall) "
        "beside issue 10's figures (an earlier run, contact model unrecorded):",
        "",
        "| t (s) | surface T at axis (C) | issue | coagulated area (mm²) | issue | depth on axis (mm) | volume (mm³) |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in finest["samples"]:
        quoted = ISSUE_FIGURES["samples"].get(float(s["t_s"]), {})
        lines.append(f"| {s['t_s']:g} | {s['surface_center_c']:.1f} | {quoted.get('surface_center_c', '')} | "
                     f"{s['coagulated_area_mm2']:.2f} | {quoted.get('coagulated_area_mm2', '')} | "
                     f"{s['coagulation_depth_mm']:.3f} | {s['coagulated_volume_mm3']:.2f} |")
    st = finest["settled"]
    lines += ["", f"Issue: depth {ISSUE_FIGURES['coagulation_depth_mm']} mm, growth stops within "
              f"{ISSUE_FIGURES['stops_growing_after_lift_off_s']:g} s of lift-off. Here area, depth, volume reach 99 % of their "
              f"end values {st['coagulated_area_mm2_0.99']:.2f}, {st['coagulation_depth_mm_0.99']:.2f}, "
              f"{st['coagulated_volume_mm3_0.99']:.2f} s after lift-off (99.9 %: {st['coagulated_area_mm2_0.999']:.2f}, "
              f"{st['coagulation_depth_mm_0.999']:.2f}, {st['coagulated_volume_mm3_0.999']:.2f} s).", "",
              "Convergence: largest difference over the sample times against the reference run of each group "
              "(grids: the finest; time steps: dt/2; domain checks: the same grid and dt with the default domain). "
              "dt is the step to 10 s after lift-off, 5 dt after.", "",
              "| run | grid (mm) | dt (s) | cells | wall (s) | CPU (s) | ΔT surface (C) | Δarea (mm²) | Δdepth (mm) | Δvolume (mm³) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    groups = [("grid", results["grids"], "difference"), ("time step", results["time_steps"], "difference_dt"),
              (None, results["domain"], "difference_domain")]
    for label, runs, key in groups:
        for r in runs:
            if key not in r:
                continue
            label_here = label or r["kind"]
            d, rm = r[key], r["model"]
            lines.append(f"| {label_here} | {rm['grid_mm']} | {rm['dt_s']:g} | {rm['cells']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                         f"{d['surface_center_c']:.3f} | {d['coagulated_area_mm2']:.4f} | {d['coagulation_depth_mm']:.4f} | "
                         f"{d['coagulated_volume_mm3']:.4f} |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    from lab.bench.common import pyplot, save

    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.6, 4.0))
    for r in results["grids"]:
        h = r["history"]
        label = f"{r['model']['grid_mm']} mm"
        left.plot(h["time_s"], h["surface_center_c"], label=label)
        right.plot(h["time_s"], h["coagulated_area_mm2"], label=f"area, {label}")
        right.plot(h["time_s"], h["coagulated_volume_mm3"], "--", label=f"volume (mm³), {label}")
    for t, quoted in ISSUE_FIGURES["samples"].items():
        left.plot([t], [quoted["surface_center_c"]], "kx")
        right.plot([t], [quoted["coagulated_area_mm2"]], "kx")
    left.set_xscale("symlog", linthresh=2.0)
    right.set_xscale("symlog", linthresh=2.0)
    left.set_xlabel("t (s)")
    right.set_xlabel("t (s)")
    left.set_ylabel("surface temperature at the axis (C)")
    right.set_ylabel("coagulated area (mm²) / volume (mm³)")
    left.set_title("Ball 250 C, 2 s contact (x: issue 10)")
    left.legend(fontsize=7)
    right.legend(fontsize=7)
    return [save(fig, out_dir, "heat_reference.png")]
