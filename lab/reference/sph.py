"""The bleeding step of sims.blood.particles written with NumPy and scipy's cKDTree, on a flat plane (metric = I).

Used only by the benchmark, to time the Taichi step against a well-known vectorised baseline doing
the same work: gravity with film drag, advance, neighbour pairs, density and near density, double
density relaxation damped by the drag, velocity from displacement with the clamp, viscosity impulses.
Positions and velocities are (N, 2) float64 in mm and mm/s.
"""
import math

import numpy as np
from scipy.spatial import cKDTree

from sims.blood.particles import lattice_density


class NumpyBleeding:
    def __init__(self, positions_mm: np.ndarray, params: dict, gravity_mm_s2=(0.0, 0.0)):
        self.pos = np.array(positions_mm, np.float64)
        self.vel = np.zeros_like(self.pos)
        self.rho = np.zeros(len(self.pos))
        self.params, self.gravity = params, np.asarray(gravity_mm_s2, np.float64)

    def step(self, dt_s: float) -> None:
        p = self.params
        h = p["interaction_radius_mm"]
        rest = p["rest_density"] * lattice_density(p["particle_spacing_mm"], h)
        nu = p["blood_viscosity_mpa_s"] * 1e-3 / p["blood_density_kg_m3"] * 1e6
        sub = dt_s / p["substeps"]
        for _ in range(p["substeps"]):
            thickness = p["film_thickness_mm"] * np.maximum(self.rho / rest, 0.25)
            drag = 3.0 * nu / thickness**2
            decay = np.exp(-drag * sub)
            self.vel = self.vel * decay[:, None] + self.gravity * ((1.0 - decay) / np.maximum(drag, 1e-30))[:, None]
            start = self.pos.copy()
            self.pos += self.vel * sub
            pairs = cKDTree(self.pos).query_pairs(h, output_type="ndarray")
            i, j = pairs[:, 0], pairs[:, 1]
            offset = self.pos[j] - self.pos[i]
            r = np.linalg.norm(offset, axis=1)
            q = 1.0 - r / h
            n = len(self.pos)
            self.rho = np.bincount(i, q**2, n) + np.bincount(j, q**2, n)
            rho_near = np.bincount(i, q**3, n) + np.bincount(j, q**3, n)
            pressure, near = p["stiffness_mm_s2"] * (self.rho - rest), p["near_stiffness_mm_s2"] * rho_near
            push = 0.5 * sub**2 * ((pressure[i] + pressure[j]) * q + (near[i] + near[j]) * q**2)
            unit = offset / np.maximum(r, 1e-12)[:, None]
            shift = np.zeros_like(self.pos)
            for axis in range(2):
                shift[:, axis] = np.bincount(j, push * unit[:, axis], n) - np.bincount(i, push * unit[:, axis], n)
            damping = drag * sub
            shift *= np.where(damping > 1e-6, (1.0 - np.exp(-damping)) / np.maximum(damping, 1e-30), 1.0)[:, None]
            self.pos += shift
            self.vel = self._clamp(p["inertia"] * (self.pos - start) / sub)
            approach = np.einsum("nd,nd->n", self.vel[i] - self.vel[j], unit)
            active = approach > 0
            impulse = sub * q * (p["viscosity_sigma_1_s"] * approach + p["viscosity_beta_s_mm"] * approach**2)
            impulse = np.where(active, np.minimum(impulse, approach), 0.0)
            for axis in range(2):
                self.vel[:, axis] += 0.5 * (np.bincount(j, impulse * unit[:, axis], n) - np.bincount(i, impulse * unit[:, axis], n))
            self.vel = self._clamp(self.vel)

    def _clamp(self, velocity: np.ndarray) -> np.ndarray:
        speed = np.linalg.norm(velocity, axis=1)
        limit = self.params["max_speed_mm_s"]
        return velocity * np.minimum(1.0, limit / np.maximum(speed, 1e-30))[:, None]


def disk_positions(count: int, spacing_mm: float, seed: int = 0) -> np.ndarray:
    """count points uniformly in a disk holding them at the hexagonal rest spacing (mm)."""
    radius = math.sqrt(count * math.sqrt(3.0) / 2.0 * spacing_mm**2 / math.pi)
    rng = np.random.default_rng(seed)
    angle, reach = rng.uniform(0, 2 * math.pi, count), radius * np.sqrt(rng.uniform(0, 1, count))
    return np.stack([reach * np.cos(angle), reach * np.sin(angle)], axis=1)
