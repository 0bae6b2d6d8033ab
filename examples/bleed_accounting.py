"""A bleed and its accounting: scenes/hemostasis.yaml run headless (lab.runner.run) while the vessel bleeds and the
sucker clears the field, then the blood balance from metrics.json: spawned = on the surface + suctioned + left + dried.

Run: python examples/bleed_accounting.py [--out DIR] [--method height_field|particles] [--arch cpu|gpu|auto]
(about 5 s on 2 CPU cores once the kernels are cached; without --out the outputs go to a temporary folder)
"""
import argparse
import json
import tempfile
from pathlib import Path

from lab import runner
from sims.core.backend import ARCH_CHOICES
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT
from sims.scene.params import BLEEDING_METHODS

DURATION_S = 4.0  # the vessel bleeds from t = 0; the sucker comes down at 2.5 s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="output folder (the run replaces it; default: a temporary one)")
    parser.add_argument("--method", default="height_field", choices=tuple(BLEEDING_METHODS))
    parser.add_argument("--arch", default="auto", choices=ARCH_CHOICES)
    args = parser.parse_args()
    overrides = ["texture_size=128", f"bleeding.method={args.method}"]  # 128 texels a side: small and quick
    scene = Scene.from_file(REPO_ROOT / "scenes" / "hemostasis.yaml", overrides=overrides, arch=args.arch)
    with tempfile.TemporaryDirectory() as temporary:
        out = args.out or Path(temporary) / "hemostasis"
        runner.run(scene, out, duration_s=DURATION_S, progress=False)
        metrics = json.loads((out / "metrics.json").read_text())  # what runner.run returned, as written
        print(f"{metrics['scene']} ({args.method}) on {metrics['arch']}: {metrics['steps']} steps, "
              f"{metrics['duration_s']:.2f} s simulated in {metrics['wall_s']:.1f} s; "
              f"outputs in {out if args.out else 'a temporary folder'}")
    blood = metrics["bleeding"]
    parts = {"on the surface": blood["on_surface_ml"], "suctioned": blood["suctioned_ml"],
             "left the tissue": blood["left_surface_ml"], "dried": blood["dried_ml"]}
    for name, ml in [("spawned", blood["spawned_ml"]), *parts.items()]:
        print(f"  {name:16s} {ml:9.5f} ml")
    total = sum(parts.values())
    print(f"  {'sum of the four':16s} {total:9.5f} ml (spawned - sum = {blood['spawned_ml'] - total:+.2e} ml)")
    print(f"blood covers {blood['blood_area_mm2']:.1f} mm^2, {blood['max_thickness_mm']:.2f} mm deep at most; "
          f"vessel now bleeds {blood['bleed_rates_ml_s']['vessel']:.3f} ml/s")


if __name__ == "__main__":
    main()
