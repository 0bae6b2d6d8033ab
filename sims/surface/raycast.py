"""Rays against a triangle mesh (Moeller-Trumbore, vectorised over the triangles): where a click or a tool's axis
meets the tissue."""
import numpy as np


def first_hit(origin, direction, triangles: np.ndarray, max_distance: float = np.inf) -> float | None:
    """Distance along the ray origin + s * direction (direction need not be unit; s is in its units) to the nearest
    triangle it crosses, from either side, or None. triangles: (F, 3, 3) corners, mm."""
    origin, direction = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac = b - a, c - a
    p = np.cross(direction, ac)
    det = np.einsum("ij,ij->i", ab, p)
    usable = np.abs(det) > 1e-12 * np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
    inverse = np.divide(1.0, det, out=np.zeros_like(det), where=usable)
    t = origin - a
    u = np.einsum("ij,ij->i", t, p) * inverse
    q = np.cross(t, ab)
    v = (q @ direction) * inverse
    s = np.einsum("ij,ij->i", q, ac) * inverse
    hit = usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= max_distance)
    return float(s[hit].min()) if hit.any() else None
