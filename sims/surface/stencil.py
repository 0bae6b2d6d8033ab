"""The texel-metric stencil: conductances between a texel and its 8 neighbours in the surface's metric, shared by
every model that spreads something across the surface (heat in sims.heat.cautery, blood's pipes in
sims.blood.height_field)."""
import numpy as np

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
