"""Test meshes the bench and the tests share: flat rectangles with UVs over [0, 1]^2."""
import numpy as np


def plane_mesh(width_mm: float, height_mm: float, u_scale: float = 1.0, vertical: bool = False, cells: int = 8,
               slope_deg: float = 0.0):
    """A flat width x height rectangle centred at the origin with UV = (x / width, y / height) in [0, 1] (so the UV
    stretch is width / height), as a trimesh.Trimesh of cells x cells squares.

    vertical: the rectangle stands in the x-z plane (z up) instead of lying in x-y.
    slope_deg: the rectangle tilted about the x axis, rising toward +y (ignored when vertical).
    u_scale: only the first u_scale of the U range is used, so a texel is stretched 1/u_scale : 1 (anisotropic UVs).
    """
    import trimesh

    n = cells + 1
    xs, ys = np.meshgrid(np.linspace(-width_mm / 2, width_mm / 2, n), np.linspace(-height_mm / 2, height_mm / 2, n))
    if vertical:
        vertices = np.stack([xs.ravel(), np.zeros(xs.size), ys.ravel()], axis=1)
    else:
        slope = np.radians(slope_deg)
        vertices = np.stack([xs.ravel(), ys.ravel() * np.cos(slope), ys.ravel() * np.sin(slope)], axis=1)
    uv = np.stack([(xs.ravel() / width_mm + 0.5) * u_scale, ys.ravel() / height_mm + 0.5], axis=1)
    return trimesh.Trimesh(vertices, grid_faces(cells, cells), visual=trimesh.visual.TextureVisuals(uv=uv), process=False)


def grid_faces(cells_x: int, cells_y: int) -> np.ndarray:
    """(2 cells_x cells_y, 3) triangles of a (cells_y + 1) x (cells_x + 1) vertex grid numbered row by row."""
    n = cells_x + 1
    faces = [[j * n + i, j * n + i + 1, j * n + i + n + 1] for j in range(cells_y) for i in range(cells_x)]
    faces += [[j * n + i, j * n + i + n + 1, j * n + i + n] for j in range(cells_y) for i in range(cells_x)]
    return np.array(faces)
