"""A scene built in Python: a 30 x 20 mm tissue patch with a bump made with trimesh, a scene dict (a ball electrode
held on it, a bleed point uphill of the bump, gravity tilted 20 degrees), written out as OBJ and YAML, loaded, run for
DURATION_S; saves the final texture as final.png and prints the burn (mm, mm^2) and the blood (ml, mm^2).

Run: python examples/scene_in_python.py [--out DIR] [--arch cpu|gpu|auto]   (about 5 s on 2 CPU cores once the kernels
are cached; without --out it writes into a new temporary folder and prints its path)
"""
import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
import trimesh
import yaml
from PIL import Image

from sims.core.backend import ARCH_CHOICES
from sims.scene.assembly import Scene
from sims.scene.config import load_scene_config

DURATION_S = 1.5
SLOPE_DEG = 20.0  # the patch lies flat; gravity leans toward -y as on a patch tilted this much


def patch_mesh(width_mm: float = 30.0, height_mm: float = 20.0, cells: int = 48) -> trimesh.Trimesh:
    """A grid in the x-y plane (z up), a 1.5 mm Gaussian bump at (4, -3) mm, UVs (x / width, y / height) + 0.5."""
    xs, ys = np.meshgrid(np.linspace(-width_mm / 2, width_mm / 2, cells + 1),
                         np.linspace(-height_mm / 2, height_mm / 2, cells + 1))
    zs = 1.5 * np.exp(-((xs - 4.0) ** 2 + (ys + 3.0) ** 2) / (2 * 2.5**2))
    n = cells + 1
    faces = [[j * n + i, j * n + i + 1, (j + 1) * n + i + 1] for j in range(cells) for i in range(cells)]
    faces += [[j * n + i, (j + 1) * n + i + 1, (j + 1) * n + i] for j in range(cells) for i in range(cells)]
    uv = np.stack([xs.ravel() / width_mm + 0.5, ys.ravel() / height_mm + 0.5], axis=1)
    return trimesh.Trimesh(np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1), np.array(faces),
                           visual=trimesh.visual.TextureVisuals(uv=uv), process=False)


SCENE = {  # the same keys as a scenes/*.yaml file; what is left out takes its default (sims/scene/config.py)
    "name": "bump_in_python",
    "mesh": "bump.obj",  # relative paths are read from the scene file's folder first
    "texture_size": 256,
    "models": ["cautery", "bleeding"],
    "duration_s": DURATION_S,
    "gravity_mm_s2": [0.0, -9810.0 * math.sin(math.radians(SLOPE_DEG)), -9810.0 * math.cos(math.radians(SLOPE_DEG))],
    "tissue": {"preset": "liver"},
    "bleeding": {"method": "height_field"},
    "bleed_points": [{"name": "cut", "position_mm": [4.0, 6.0, 0.0], "rate_ml_s": 0.03, "radius_mm": 0.6}],
    "instruments": [{"name": "ball", "shape": {"type": "ball", "radius_mm": 1.5}, "tip_temperature_c": 250.0,
                     "position_mm": [-7.0, 0.0, 1.2], "energized": True}],  # centre 1.5 - 0.3 mm above the tissue
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="folder for its files (default: a new temporary one)")
    parser.add_argument("--arch", default="auto", choices=ARCH_CHOICES)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="scene_in_python."))
    out.mkdir(parents=True, exist_ok=True)
    obj_text, _ = trimesh.exchange.obj.export_obj(patch_mesh(), return_texture=True)  # (its material files not needed)
    (out / "bump.obj").write_text(obj_text)
    (out / "scene.yaml").write_text(yaml.safe_dump(SCENE, sort_keys=False))
    config = load_scene_config(out / "scene.yaml")  # validated, defaults filled; ConfigError names file and key
    scene = Scene(config, arch=args.arch)
    for _ in range(round(DURATION_S / scene.time_step_s)):
        scene.step()
    image = scene.composite()  # (H, W, 3) uint8, row 0 = v 1: the display texture after the last step
    Image.fromarray(image).save(out / "final.png")
    metrics = scene.metrics()
    burn, blood = metrics["cautery"], metrics["bleeding"]
    print(f"{scene.name} on {scene.arch}: {scene.steps} steps, t = {scene.time_s:.2f} s, "
          f"tissue {scene.surface.texel_area_mm2[scene.surface.mask].sum():.0f} mm^2")
    print(f"burn: {burn['coagulation_depth_mm']:.2f} mm deep, coagulated area {burn['coagulated_area_mm2']:.1f} mm^2")
    print(f"blood: {blood['on_surface_ml']:.4f} ml on {blood['blood_area_mm2']:.1f} mm^2, "
          f"of {blood['spawned_ml']:.4f} ml spawned")
    print(f"final.png: {image.shape[1]} x {image.shape[0]} px in {out}")
    print(f"the same scene from the command line: python -m lab run {out / 'scene.yaml'} --out {out / 'run'}")


if __name__ == "__main__":
    main()
