"""Analytic reference solutions (DESIGN section 7) used by tests and benchmarks."""
import math

import numpy as np


def gaussian_on_plane(r2_mm2: np.ndarray, amplitude: float, sigma_mm: float, alpha_mm2_s: float, t_s: float) -> np.ndarray:
    """Excess temperature of a 2D Gaussian bump after diffusing for t: same integral, variance s^2 + 2 alpha t."""
    variance = sigma_mm**2 + 2.0 * alpha_mm2_s * t_s
    return amplitude * sigma_mm**2 / variance * np.exp(-r2_mm2 / (2.0 * variance))


def arrhenius_time_to_omega(omega: float, temperature_c: float, ln_a: float, activation_j_mol: float) -> float:
    """Seconds at constant temperature until the Arrhenius integral reaches omega."""
    rate = math.exp(ln_a - activation_j_mol / (8.314462618 * (temperature_c + 273.15)))
    return omega / rate
