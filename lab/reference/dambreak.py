"""The dam break's reference: Martin & Moyce's 1952 surge-front measurements (a water column of width a released on a
dry floor; T = t sqrt(2 g / a), Z = front / a) and the front of a particle set measured the same way for every
method and peer (lab.bench.dambreak, lab.bench.peer, lab.bench.bleeding_methods)."""
import math

import numpy as np

FRONT_QUANTILE = 0.002

MARTIN_MOYCE = (
    (0.849, 1.245), (1.212, 1.443), (1.602, 1.884), (2.283, 2.689), (2.950, 3.728),
    (3.598, 4.528), (3.905, 4.999), (4.592, 5.841), (4.961, 6.271), (5.316, 6.717),
)


def martin_moyce_front(T):
    """Martin & Moyce's Z at T, linear between their points; NaN outside [0.849, 5.316] (no extrapolation).
    Scalar in, float out; array in, array out."""
    data = np.asarray(MARTIN_MOYCE, np.float64)
    T = np.asarray(T, np.float64)
    inside = (T >= data[0, 0]) & (T <= data[-1, 0])
    Z = np.where(inside, np.interp(T, data[:, 0], data[:, 1]), np.nan)
    return float(Z) if Z.ndim == 0 else Z


def front_error(times_T, fronts_Z) -> dict:
    """Our front (linear in T between samples) at Martin & Moyce's times inside [min T, max T] against their Z.

    {points, mean_abs_a, max_abs_a, mean_signed_a (> 0: ahead of Martin & Moyce), signed_a (per point),
    T (their times used)}, errors in units of a; NaN errors when no point lies in the range.
    """
    times_T, fronts_Z = np.asarray(times_T, np.float64), np.asarray(fronts_Z, np.float64)
    order = np.argsort(times_T, kind="stable")
    times_T, fronts_Z = times_T[order], fronts_Z[order]
    data = np.asarray(MARTIN_MOYCE, np.float64)
    use = data[(data[:, 0] >= times_T[0]) & (data[:, 0] <= times_T[-1])] if len(times_T) else data[:0]
    if not len(use):
        return {"points": 0, "mean_abs_a": math.nan, "max_abs_a": math.nan, "mean_signed_a": math.nan, "signed_a": [], "T": []}
    signed = np.interp(use[:, 0], times_T, fronts_Z) - use[:, 1]
    return {
        "points": int(len(use)),
        "mean_abs_a": float(np.abs(signed).mean()),
        "max_abs_a": float(np.abs(signed).max()),
        "mean_signed_a": float(signed.mean()),
        "signed_a": [float(v) for v in signed],
        "T": [float(v) for v in use[:, 0]],
    }


def front_position(x_a: np.ndarray) -> float:
    """The front from particle x (in a, from the left wall): rank floor(FRONT_QUANTILE N) from the largest."""
    x = np.sort(np.asarray(x_a, np.float64))
    return float(x[-1 - int(FRONT_QUANTILE * len(x))])
