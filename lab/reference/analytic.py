"""Analytic reference solutions (docs/model/heat.md "Reference solutions", docs/model/blood.md "Reference solutions and data") used by tests and benchmarks."""
import math

import numpy as np


def gaussian_on_plane(r2_mm2: np.ndarray, amplitude: float, sigma_mm: float, alpha_mm2_s: float, t_s: float) -> np.ndarray:
    """Excess temperature of a 2D Gaussian bump after diffusing for t: same integral, variance s^2 + 2 alpha t."""
    variance = sigma_mm**2 + 2.0 * alpha_mm2_s * t_s
    return amplitude * sigma_mm**2 / variance * np.exp(-r2_mm2 / (2.0 * variance))


def sphere_l1_amplitude(alpha_mm2_s: float, radius_mm: float, t_s: float) -> float:
    """Amplitude ratio after t of the l = 1 mode (cos theta) of diffusion on a sphere: exp(-2 alpha t / R^2)."""
    return math.exp(-2.0 * alpha_mm2_s * t_s / radius_mm**2)


def arrhenius_time_to_omega(omega: float, temperature_c: float, ln_a: float, activation_j_mol: float,
                            threshold_c: float = -math.inf) -> float:
    """Seconds at constant temperature until the Arrhenius integral reaches omega (inf at or below threshold_c, where
    no damage accumulates)."""
    if temperature_c <= threshold_c:
        return math.inf
    rate = math.exp(ln_a - activation_j_mol / (8.314462618 * (temperature_c + 273.15)))
    return omega / rate


def arrhenius_omega_under_relaxation(t_s, start_c: float, target_c: float, rate_1_s: float, ln_a: float, activation_j_mol: float,
                                     threshold_c: float = -math.inf):
    """Arrhenius integral Omega(t) for T(t) = target + (start - target) exp(-rate t) (contact heating toward a tip),
    counting only the time T is above threshold_c, by adaptive quadrature. t_s: scalar or array of seconds."""
    from scipy.integrate import quad

    def integrand(s):
        celsius = target_c + (start_c - target_c) * math.exp(-rate_1_s * s)
        if celsius <= threshold_c:
            return 0.0
        return math.exp(ln_a - activation_j_mol / (8.314462618 * (celsius + 273.15)))

    times = np.atleast_1d(np.asarray(t_s, np.float64))
    edges = [0.0]
    if start_c != target_c and 0.0 < (threshold_c - target_c) / (start_c - target_c) < 1.0:
        edges.append(-math.log((threshold_c - target_c) / (start_c - target_c)) / rate_1_s)  # T crosses the threshold
    edges = np.unique(np.concatenate([edges, times]))
    pieces = [quad(integrand, a, b, epsabs=0.0, epsrel=1e-10, limit=200)[0] for a, b in zip(edges[:-1], edges[1:])]
    totals = dict(zip(edges, np.concatenate([[0.0], np.cumsum(pieces)])))
    result = np.array([totals[t] for t in times])
    return result if np.ndim(t_s) else float(result[0])


def arrhenius_time_under_relaxation(omega: float, start_c: float, target_c: float, rate_1_s: float, ln_a: float, activation_j_mol: float,
                                    threshold_c: float = -math.inf) -> float:
    """Seconds until Omega reaches omega while T relaxes from start toward target (see arrhenius_omega_under_relaxation)."""
    from scipy.optimize import brentq

    f = lambda t: arrhenius_omega_under_relaxation(t, start_c, target_c, rate_1_s, ln_a, activation_j_mol, threshold_c) - omega
    upper = 1.0
    while f(upper) < 0.0:
        upper *= 2.0
        if upper > 1e7:
            raise ValueError("omega is not reached: the target temperature is too low")
    return brentq(f, 0.0, upper, xtol=1e-12, rtol=1e-12)
