"""Whether a change keeps the lab's outputs: every scene in scenes/ (the bleeding scenes with both methods) run headless
by two checkouts, their state.npz and metrics.json compared byte for byte (metrics without the timings), their final*.png
pixel for pixel (the PNG encoder's settings are not an output).

    python tools/same_outputs.py OTHER_CHECKOUT [--out DIR] [--duration S]

OTHER_CHECKOUT is a tree of the lab (a `git worktree` or `git archive` of the commit before the change); this checkout is
the other side. Prints one line per case and exits 0 when every file is the same, 1 otherwise.
"""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from PIL import Image

REPO = Path(__file__).resolve().parents[1]
BLEEDING_METHODS = ("height_field", "particles")
TIMINGS = ("wall_s", "first_step_s", "steps_per_s")  # metrics.json keys that differ from run to run
FILES = ("state.npz", "final.png", "final_normal.png", "final_roughness.png")


def cases() -> list[tuple[str, str, list[str]]]:
    """(name, scene file name, --set overrides) for every scene, each bleeding scene once per method."""
    found = []
    for scene in sorted((REPO / "scenes").glob("*.yaml")):
        if "bleeding:" in scene.read_text():
            found += [(f"{scene.stem}-{method}", scene.name, [f"bleeding.method={method}"]) for method in BLEEDING_METHODS]
        else:
            found.append((scene.stem, scene.name, []))
    return found


def run(checkout: Path, scene: str, overrides: list[str], out: Path, duration_s: float | None) -> None:
    """`python -m lab run` of checkout's scenes/<scene> into out, from checkout (its own code and scenes)."""
    command = [sys.executable, "-m", "lab", "run", f"scenes/{scene}", "--out", str(out), "--quiet", "--arch", "cpu"]
    command += [item for override in overrides for item in ("--set", override)]
    if duration_s is not None:
        command += ["--duration", str(duration_s)]
    subprocess.run(command, cwd=checkout, check=True, env=dict(os.environ, PYTHONPATH=str(checkout)))


def _content(path: Path):
    """A PNG's mode, size and pixels; any other file's bytes."""
    if path.suffix != ".png":
        return path.read_bytes()
    with Image.open(path) as image:
        return image.mode, image.size, image.tobytes()


def differences(a: Path, b: Path) -> list[str]:
    """Names of the outputs that differ between run folders a and b (metrics.json without TIMINGS)."""
    differ = [name for name in FILES if _content(a / name) != _content(b / name)]
    metrics = [json.loads((folder / "metrics.json").read_text()) for folder in (a, b)]
    for values in metrics:
        for key in TIMINGS:
            values.pop(key, None)
    if metrics[0] != metrics[1]:
        differ.append("metrics.json (" + ", ".join(sorted(k for k in metrics[0].keys() | metrics[1].keys()
                                                          if metrics[0].get(k) != metrics[1].get(k))) + ")")
    return differ


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("other", type=Path, help="the other checkout of the lab")
    parser.add_argument("--out", type=Path, default=Path("/tmp/same_outputs"), help="where both sides' runs go")
    parser.add_argument("--duration", type=float, help="simulated seconds (default: each scene's duration_s)")
    args = parser.parse_args()
    same = True
    for name, scene, overrides in cases():
        folders = [args.out / side / name for side in ("other", "this")]
        for checkout, folder in zip((args.other.resolve(), REPO), folders):
            run(checkout, scene, overrides, folder, args.duration)
        differ = differences(*folders)
        same &= not differ
        print(f"{name}: {'same outputs' if not differ else 'DIFFERENT: ' + ', '.join(differ)}", flush=True)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
