"""Shared test helpers: synthetic meshes and parameter sets."""
import signal

import numpy as np
import trimesh

from sims.scene import params


def plane_mesh(width_mm: float, height_mm: float, cells: int = 8, slope_deg: float = 0.0) -> trimesh.Trimesh:
    """A rectangle centred at the origin, UVs mapping it onto [0, 1]^2 (so UV stretch = width/height).

    slope_deg tilts it about the x axis (rising toward +y).
    """
    xs, ys = np.meshgrid(np.linspace(-width_mm / 2, width_mm / 2, cells + 1), np.linspace(-height_mm / 2, height_mm / 2, cells + 1))
    slope = np.radians(slope_deg)
    vertices = np.stack([xs.ravel(), ys.ravel() * np.cos(slope), ys.ravel() * np.sin(slope)], axis=1)
    uv = np.stack([xs.ravel() / width_mm + 0.5, ys.ravel() / height_mm + 0.5], axis=1)
    faces = []
    for j in range(cells):
        for i in range(cells):
            a = j * (cells + 1) + i
            faces += [[a, a + 1, a + cells + 2], [a, a + cells + 2, a + cells + 1]]
    return trimesh.Trimesh(vertices, np.array(faces), visual=trimesh.visual.TextureVisuals(uv=uv), process=False)


def tissue_values(**changes) -> dict:
    values = dict(params.TISSUE_PRESETS["liver"])
    values.update(changes)
    return values


def cautery_values(**changes) -> dict:
    values = {name: spec.default for name, spec in params.CAUTERY.items()}
    values["bottom"] = "body"
    values.update(changes)
    return values


def surface_only_values(**changes) -> dict:
    """Cautery values under which a field uniform in depth stays uniform: insulated bottom, no loss to air. The layered
    model then spreads heat exactly as a surface-only one."""
    from sims.heat.cautery import SURFACE_ONLY

    return cautery_values(**{**SURFACE_ONLY, **changes})


def interruptible() -> None:
    """Popen preexec_fn: SIGINT back to its default in the child, so the child's Python turns it into
    KeyboardInterrupt even when this test run was started with SIGINT ignored (a background job of a script)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
