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


def arrhenius_omega_under_relaxation(t_s, start_c: float, target_c: float, rate_1_s: float, ln_a: float, activation_j_mol: float):
    """Arrhenius integral Omega(t) for T(t) = target + (start - target) exp(-rate t) (contact heating toward a tip),
    by adaptive quadrature. t_s: scalar or array of seconds."""
    from scipy.integrate import quad

    def integrand(s):
        kelvin = target_c + (start_c - target_c) * math.exp(-rate_1_s * s) + 273.15
        return math.exp(ln_a - activation_j_mol / (8.314462618 * kelvin))

    times = np.atleast_1d(np.asarray(t_s, np.float64))
    edges = np.concatenate([[0.0], np.sort(times)])
    pieces = [quad(integrand, a, b, epsabs=0.0, epsrel=1e-10, limit=200)[0] for a, b in zip(edges[:-1], edges[1:])]
    totals = dict(zip(np.sort(times), np.cumsum(pieces)))
    result = np.array([totals[t] for t in times])
    return result if np.ndim(t_s) else float(result[0])


def arrhenius_time_under_relaxation(omega: float, start_c: float, target_c: float, rate_1_s: float, ln_a: float, activation_j_mol: float) -> float:
    """Seconds until Omega reaches omega while T relaxes from start toward target (see arrhenius_omega_under_relaxation)."""
    from scipy.optimize import brentq

    f = lambda t: arrhenius_omega_under_relaxation(t, start_c, target_c, rate_1_s, ln_a, activation_j_mol) - omega
    upper = 1.0
    while f(upper) < 0.0:
        upper *= 2.0
        if upper > 1e7:
            raise ValueError("omega is not reached: the target temperature is too low")
    return brentq(f, 0.0, upper, xtol=1e-12, rtol=1e-12)
