"""Heat links across UV chart seams: which texels touch on the surface though not in the texture.

A texel at a chart border has stencil neighbours outside its chart. Stepping from its centre one
texel that way along the surface (the tangent maps: P + dc dP/dcol + dr dP/drow) lands, at a seam,
on another chart (or another part of the same chart). If a surface texel lies within tolerance of
that point and is not the texel's own grid neighbour, the pair gets a conductance link with the
weight the stencil would have given that direction. Links are made symmetric (each found direction
adds half its weight to both ends), so heat stays conserved exactly and every explicit update stays
a convex combination. At an open mesh border the step lands off the surface and nothing links.
"""
from __future__ import annotations

import numpy as np

from sims.core.backend import cache_key, cached_arrays, source_digest

TOLERANCE = 0.75  # a link's far texel lies within this many of the step's lengths of the point stepped to
LINKS_CACHE_BYTES = 256 << 20  # links on disk (a few kB per surface: the texels of its seams)
_CODE_VERSION = source_digest(__file__)  # a change here finds the links anew


def seam_links(surface, coefficients: np.ndarray, neighbours) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR links per texel, in flat (row * W + col) indices.

    surface: a sims.surface.texels.TissueSurface. coefficients: (H, W, 8) the texel's conductance along each direction of
    `neighbours` ((row, col) offsets). Returns (start (H*W + 1,) int32, target (L,) int32, weight (L,) float32):
    texel f links to target[start[f]:start[f + 1]] with those weights; weight[l] is the same both ways.
    Kept on disk by what they are found from: a surface read before finds its links without a k-d tree (and without
    importing scipy.spatial, 0.1-0.3 s of a headless run's start-up)."""
    names = ("start", "target", "weight")
    key = cache_key(_CODE_VERSION, surface.mask, surface.position_mm, surface.tangent_u, surface.tangent_v,
                    np.asarray(coefficients), np.asarray(neighbours))
    stored = cached_arrays("seams", key, names, lambda: dict(zip(names, _find_links(surface, coefficients, neighbours))),
                           LINKS_CACHE_BYTES)
    return tuple(stored[name] for name in names)


def _find_links(surface, coefficients: np.ndarray, neighbours) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """seam_links, found with a k-d tree of the surface texels' positions."""
    from scipy.spatial import cKDTree

    mask = surface.mask
    height, width = mask.shape
    rows, cols = np.nonzero(mask)
    empty = (np.zeros(height * width + 1, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32))
    if len(rows) == 0:
        return empty
    positions = surface.position_mm[rows, cols].astype(np.float64)
    tree = cKDTree(positions)
    ex = surface.tangent_u[rows, cols].astype(np.float64)   # mm per +1 column
    ey = -surface.tangent_v[rows, cols].astype(np.float64)  # mm per +1 row
    padded = np.pad(mask, 1)
    sources, targets, weights = [], [], []
    for k, (dr, dc) in enumerate(neighbours):
        outside = ~padded[rows + 1 + dr, cols + 1 + dc]
        candidates = np.flatnonzero(outside & (coefficients[rows, cols, k] > 0))
        if len(candidates) == 0:
            continue
        step = dc * ex[candidates] + dr * ey[candidates]
        length = np.linalg.norm(step, axis=1)
        distance, nearest = tree.query(positions[candidates] + step)
        far = np.maximum(np.abs(rows[nearest] - rows[candidates]), np.abs(cols[nearest] - cols[candidates])) > 2
        keep = (distance < TOLERANCE * length) & far
        sources.append(candidates[keep])
        targets.append(nearest[keep])
        weights.append(coefficients[rows[candidates[keep]], cols[candidates[keep]], k].astype(np.float64))
    if not sources or sum(len(s) for s in sources) == 0:
        return empty
    source, target, weight = np.concatenate(sources), np.concatenate(targets), np.concatenate(weights)
    # symmetric: half of each found direction to both ends, same pairs merged
    a, b = np.minimum(source, target), np.maximum(source, target)
    pairs, inverse = np.unique(np.stack([a, b], axis=1), axis=0, return_inverse=True)
    pair_weight = np.bincount(inverse.ravel(), weights=0.5 * weight, minlength=len(pairs))
    flat = rows * width + cols
    ends = np.concatenate([flat[pairs[:, 0]], flat[pairs[:, 1]]])
    others = np.concatenate([flat[pairs[:, 1]], flat[pairs[:, 0]]])
    both = np.concatenate([pair_weight, pair_weight])
    order = np.lexsort((others, ends))  # grouped by texel, fixed order within (deterministic sums)
    ends, others, both = ends[order], others[order], both[order]
    start = np.zeros(height * width + 1, np.int64)
    np.add.at(start, ends + 1, 1)
    return np.cumsum(start).astype(np.int32), others.astype(np.int32), both.astype(np.float32)
