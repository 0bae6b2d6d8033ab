"""Cautery: Pennes bioheat on the surface (Laplace-Beltrami from the texel metric), contact heating,
Arrhenius damage and charring. Fields are (H, W) in the image orientation of sims.surface.

Heat: rho c dT/dt = k LB(T) + w_b rho_b c_b (T_body - T) + Q_tool.
- LB(T) is discretised as a symmetric graph Laplacian on the 8-neighbour texel grid. The
  conductance tensor K = sqrt|g| g^-1 (grid units) is split into non-negative weights along the
  two grid axes and one diagonal (a - |b|, c - |b|, |b|), so every explicit update is a convex
  combination of neighbour values: heat is conserved exactly (symmetric weights) and the maximum
  principle holds. Diffusion is isotropic in millimetres whatever the UV stretch.
- Explicit substeps are added automatically below the stability limit, for any parameter value.
- Perfusion and contact heating relax T exponentially (exactly) toward a weighted target, so they
  are bounded for any rate: Q_tool = h w(d) (T_tip - T) / L with contact conductance h, heated
  layer L and w(d) falling from 1 at contact (signed distance d <= 0) to 0 at the contact distance.
- Damage: Omega += exp(ln A - Ea / (R T_K)) dt; coagulated fraction 1 - exp(-Omega).
- Char: char += rate (T - T_char) dt above the charring temperature, capped at 1.
Chart borders and masked texels are insulated (zero flux).
"""
import math

import numpy as np
import taichi as ti

GAS_CONSTANT = 8.314462618  # J/(mol K)
KELVIN = 273.15
OMEGA_MAX = 1.0e6           # Omega is capped here: 1 - exp(-Omega) is 1 in float32 long before
STABILITY_MARGIN = 0.9      # explicit substep at this fraction of the convexity limit
CHARRED_LEVEL = 0.5         # char at or above this counts as charred area
# neighbour offsets (row, col): +x, -x, +y, -y, (+x,+y), (-x,-y), (+x,-y), (-x,+y) with x = col, y = row
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (-1, 1), (1, -1))


def edge_weights(metric: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Symmetric conductance weights (H, W, 8) to the neighbours in NEIGHBOURS (dimensionless).

    metric: (H, W, 2, 2) in grid coordinates (x = columns, y = rows), mm^2 per texel^2.
    """
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
    height, width = mask.shape
    weights = np.zeros((height, width, 8))
    padded_mask = np.pad(mask, 1)
    for index, (dr, dc) in enumerate(NEIGHBOURS):
        name = axis.get((dr, dc)) or axis[(-dr, -dc)]
        c = np.where(mask, coef[name], 0.0)
        c_pad = np.pad(c, 1)
        neighbour_c = c_pad[1 + dr: 1 + dr + height, 1 + dc: 1 + dc + width]
        neighbour_in = padded_mask[1 + dr: 1 + dr + height, 1 + dc: 1 + dc + width]
        weights[..., index] = np.where(mask & neighbour_in, 0.5 * (c + neighbour_c), 0.0)
    return weights.astype(np.float32)


@ti.data_oriented
class Cautery:
    """Temperature, damage and char on a TissueSurface, heated by InstrumentFields."""

    def __init__(self, surface, tissue: dict, cautery: dict, instruments):
        self.surface, self.tissue, self.cautery, self.instruments = surface, tissue, cautery, instruments
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
        weights = edge_weights(surface.metric, surface.mask)
        area = surface.texel_area_mm2
        inv_area = np.where(surface.mask, 1.0 / np.where(surface.mask, area, 1.0), 0.0).astype(np.float32)
        self.max_exchange_1_mm2 = float((weights.sum(axis=2) * inv_area).max())  # max over texels of sum(w)/A
        self.mask.from_numpy(surface.mask.astype(np.int32))
        self.inv_area.from_numpy(inv_area)
        self.weights.from_numpy(weights)
        self.position.from_numpy(surface.position_mm)
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
        """Explicit heat substeps needed for a step of dt_s to stay a convex update."""
        limit = STABILITY_MARGIN / max(self.diffusivity_mm2_s * self.max_exchange_1_mm2, 1e-30)
        return max(1, math.ceil(dt_s / limit))

    # --- state --------------------------------------------------------------------------------
    def reset(self) -> None:
        self.current = 0
        self.temperature[0].from_numpy(np.where(self.surface.mask, self.tissue["initial_temperature_c"], 0.0).astype(np.float32))
        self.omega.fill(0.0)
        self.char.fill(0.0)

    def set_temperature(self, values: np.ndarray) -> None:
        """Set T (H, W) in C on the surface (masked texels stay 0)."""
        self.temperature[self.current].from_numpy(np.where(self.surface.mask, values, 0.0).astype(np.float32))

    def temperature_c(self) -> np.ndarray:
        return self.temperature[self.current].to_numpy()

    def damage_omega(self) -> np.ndarray:
        return self.omega.to_numpy()

    def char_level(self) -> np.ndarray:
        return self.char.to_numpy()

    def step(self, dt_s: float) -> None:
        """Advance dt_s seconds: contact field from the current instrument poses, then heat substeps."""
        t, c = self.tissue, self.cautery
        contact = (self.perfusion_rate_1_s, t["body_temperature_c"], self.contact_rate_1_s, c["contact_distance_mm"])
        if self.instruments.any_energized or contact != self._idle_contact:
            self._contact(*contact)
            self._idle_contact = None if self.instruments.any_energized else contact
        count = self.substeps(dt_s)
        sub = dt_s / count
        ea_r = t["activation_energy_j_mol"] / GAS_CONSTANT
        for _ in range(count):
            src, dst = self.temperature[self.current], self.temperature[1 - self.current]
            self._substep(src, dst, sub, self.diffusivity_mm2_s, t["arrhenius_ln_a"], ea_r, t["char_temperature_c"], t["char_rate_1_s_c"])
            self.current = 1 - self.current

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
    def _substep(self, src: ti.template(), dst: ti.template(), dt: ti.f32, alpha: ti.f32, ln_a: ti.f32, ea_r: ti.f32, t_char: ti.f32, char_rate: ti.f32):
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
                t1 = t0 + dt * alpha * self.inv_area[r, c] * flux
                rate = self.relax_rate[r, c]
                if rate > 0.0:
                    target = self.relax_target[r, c]
                    t1 = target + (t1 - target) * ti.exp(-rate * dt)
                dst[r, c] = t1
                mid = 0.5 * (t0 + t1)
                exponent = ti.min(ln_a - ea_r / (mid + KELVIN), 80.0)
                self.omega[r, c] = ti.min(self.omega[r, c] + ti.exp(exponent) * dt, OMEGA_MAX)
                if mid > t_char:
                    self.char[r, c] = ti.min(self.char[r, c] + char_rate * (mid - t_char) * dt, 1.0)

    # --- outputs ------------------------------------------------------------------------------
    def metrics(self) -> dict:
        mask, area = self.surface.mask, self.surface.texel_area_mm2.astype(np.float64)
        temperature = self.temperature_c()
        return {
            "max_temperature_c": float(temperature[mask].max()),
            "coagulated_area_mm2": float(area[self.damage_omega() >= 1.0].sum()),
            "charred_area_mm2": float(area[self.char_level() >= CHARRED_LEVEL].sum()),
        }
