"""Heat in depth: the layers under each surface texel and the implicit solve along a column (NumPy, float64).

Layers run along the inward normal from the surface (depth 0) to depth_mm; each is LAYER_GROWTH times thicker than
the one above it, so the top layer is thin (where the tool's heat enters and the gradients are steep) and the deep
ones are coarse. A column's heat balance per layer l (thickness dz_l, centre z_l, temperatures in C, time in s):

    dT_l/dt = alpha / dz_l * [ (T_{l-1} - T_l) / (z_l - z_{l-1}) + (T_{l+1} - T_l) / (z_{l+1} - z_l) ]
              + w (T_body - T_l) + [l = 0] q (T_ext - T_0)

with alpha the diffusivity (mm^2/s), w the Pennes perfusion rate (1/s) and q the surface exchange rate of the top
layer (tool contact and air, per texel). Below the last layer the tissue is held at body temperature at depth_mm
(bottom "body": perfusion keeps tissue deeper than its penetration depth sqrt(alpha / w), about 6 mm in liver, at
body temperature, so a held bottom at 8 mm changes the burn by less than the grid does), or the bottom is insulated
("insulated": a thin slab of tissue on an insulator, and the test case in which a field uniform in depth spreads
exactly as the surface-only model did).

Backward Euler along the column (thin layers are stiff: dt alpha / dz^2 reaches 1e6 at the slider extremes) gives a
tridiagonal M-matrix: every new temperature is a convex combination of the old ones, T_body, T_ext and the value
below the solved part, so the maximum principle holds for any dt. It is eliminated from the bottom up, so the
elimination factors do not depend on the per-texel exchange q, which only enters the top row: the factors are
tabulated here once per (dt, alpha, w) for every solved depth n (the first n layers, the layer below held at its
value), and a kernel only runs the two sweeps (elimination_tables).
"""
from __future__ import annotations

import numpy as np

LAYER_GROWTH = 1.4    # thickness ratio of adjacent layers
BOTTOMS = ("body", "insulated")  # the condition below the deepest layer (sims.scene.config.CAUTERY_BOTTOMS lists the same)


def layer_faces(count: int, depth_mm: float, growth: float = LAYER_GROWTH) -> np.ndarray:
    """Depths of the layer faces (mm, (count + 1,), 0 first, depth_mm last), each layer `growth` times the one above."""
    if count < 1 or not depth_mm > 0:
        raise ValueError(f"need at least one layer and a positive depth, got {count} layers, {depth_mm} mm")
    widths = growth ** np.arange(count, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(widths * (depth_mm / widths.sum()))])


def layer_centres(faces_mm: np.ndarray) -> np.ndarray:
    """Depths of the layer centres (mm, (L,))."""
    return 0.5 * (faces_mm[1:] + faces_mm[:-1])


def column_coupling(faces_mm: np.ndarray, bottom: str) -> tuple[np.ndarray, np.ndarray]:
    """Conduction per unit diffusivity (1/mm^2, (L,) each): `upper[l]` couples layer l to the one above (0 for the
    top), `lower[l]` to the one below; the last layer's `lower` couples it to body temperature at depth_mm (bottom
    "body") or is 0 ("insulated")."""
    if bottom not in BOTTOMS:
        raise ValueError(f"unknown bottom condition {bottom!r}; expected one of: {', '.join(BOTTOMS)}")
    dz, centres = np.diff(faces_mm), layer_centres(faces_mm)
    between = 1.0 / np.diff(centres)                      # 1/mm, between layer l and l + 1
    upper = np.concatenate([[0.0], between]) / dz
    last = 1.0 / (faces_mm[-1] - centres[-1]) if bottom == "body" else 0.0
    lower = np.concatenate([between, [last]]) / dz
    return upper, lower


def elimination_tables(faces_mm: np.ndarray, bottom: str, dt_s: float, alpha_mm2_s: float, perfusion_1_s: float):
    """Backward-Euler column factors for a step of dt_s.

    The system for the first n layers (the layer below, or the bottom condition, held) is
        -up_l T_{l-1} + b_l T_l - down_l T_{l+1} = T*_l + dt w T_body  (+ down_{n-1} T_held, + the top exchange)
    with up = dt alpha upper, down = dt alpha lower, b = 1 + up + down + dt w. Eliminating from row n - 1 upward:
        pivot[n, n-1] = b_{n-1},  pivot[n, l] = b_l - down_l up_{l+1} / pivot[n, l+1],  carry[n, l] = down_l / pivot[n, l+1]
    so the right sides go D_l = d_l + carry[n, l] D_{l+1} (upward) and T_l = (D_l + up_l T_{l-1}) / pivot[n, l]
    (downward; the top row adds dt q to its pivot). Returns up (L,), down (L,), pivot (L + 1, L), carry (L + 1, L)
    (rows n = 0 and entries l >= n unused), all float64."""
    upper, lower = column_coupling(faces_mm, bottom)
    up, down = dt_s * alpha_mm2_s * upper, dt_s * alpha_mm2_s * lower
    diagonal = 1.0 + up + down + dt_s * perfusion_1_s
    count = len(upper)
    pivot, carry = np.ones((count + 1, count)), np.zeros((count + 1, count))
    for n in range(1, count + 1):
        pivot[n, n - 1] = diagonal[n - 1]
        for layer in range(n - 2, -1, -1):
            carry[n, layer] = down[layer] / pivot[n, layer + 1]
            pivot[n, layer] = diagonal[layer] - carry[n, layer] * up[layer + 1]
    return up, down, pivot, carry


def rest_profile(faces_mm: np.ndarray, bottom: str, alpha_mm2_s: float, perfusion_1_s: float, body_c: float,
                 air_rate_1_s: float, air_c: float) -> np.ndarray:
    """Steady temperature per layer (C, (L,)) of an undisturbed column: perfusion and the bottom pull it to body
    temperature, the air exchange of the top layer (air_rate_1_s, 1/s) toward air_c. Without any of them every
    temperature is at rest; body temperature is returned."""
    upper, lower = column_coupling(faces_mm, bottom)
    count = len(upper)
    sink = perfusion_1_s > 0 or air_rate_1_s > 0 or (bottom == "body")
    if not sink:
        return np.full(count, body_c)
    matrix = np.diag(alpha_mm2_s * (upper + lower) + perfusion_1_s)
    matrix[0, 0] += air_rate_1_s
    rhs = np.full(count, perfusion_1_s * body_c)
    rhs[0] += air_rate_1_s * air_c
    rhs[-1] += alpha_mm2_s * lower[-1] * body_c
    for layer in range(count - 1):
        matrix[layer, layer + 1] = -alpha_mm2_s * lower[layer]
        matrix[layer + 1, layer] = -alpha_mm2_s * upper[layer + 1]
    return np.linalg.solve(matrix, rhs)

