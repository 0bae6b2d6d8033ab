"""Headless scene runs: steps with a progress bar, frames, and the output files of DESIGN section 4."""
import json
import math
import sys
import time
from pathlib import Path

from PIL import Image
from tqdm import tqdm

from sims.scene import Scene, save_npz_atomic

FINITE_CHECK_EVERY = 50  # steps between NaN/inf checks


class SimulationDiverged(RuntimeError):
    """A field became NaN or inf; the message names the field and the step."""


def write_png(path: Path, rgb) -> None:
    temp = path.with_name(f".{path.name}.tmp")
    Image.fromarray(rgb).save(temp, format="PNG")
    temp.replace(path)


def _warn_pool_full(scene: Scene, bar) -> None:
    """Say once, on stderr, that the particle pool filled up (metrics count every dropped particle)."""
    bleeding = scene.bleeding
    if bleeding is not None and bleeding.pool_full_reported and not bleeding.pool_full_logged:
        bleeding.pool_full_logged = True
        bar.write(f"warning: {scene.name}: bleeding pool full ({bleeding.capacity} particles) at t = {scene.time_s:.2f} s; "
                  "new blood is dropped and counted in metrics.json (raise bleeding.capacity)", file=sys.stderr)


def run(scene: Scene, out_dir, duration_s: float | None = None, frames_every_s: float | None = None, progress: bool = True) -> dict:
    """Run `scene` for duration_s (default: the scene's), write outputs into out_dir, return metrics."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    duration = scene.config["duration_s"] if duration_s is None else duration_s
    total = int(round(duration / scene.time_step_s))
    frame_every = max(1, int(round(frames_every_s / scene.time_step_s))) if frames_every_s else 0
    frames = out / "frames"
    if frame_every:
        frames.mkdir(exist_ok=True)
        for old in frames.glob("frame_*.png"):
            old.unlink()
        write_png(frames / "frame_00000.png", scene.composite())
    start = time.perf_counter()
    bar = tqdm(total=total, desc=scene.name, unit="step", file=sys.stderr, delay=1.0, disable=not progress, dynamic_ncols=True)
    with bar:
        for index in range(1, total + 1):
            scene.step()
            bar.update(1)
            if index % FINITE_CHECK_EVERY == 0 or index == total:
                bad = scene.non_finite_field()
                if bad:
                    raise SimulationDiverged(f"{bad} became non-finite at step {index} (t = {scene.time_s:.4g} s)")
            _warn_pool_full(scene, bar)
            if frame_every and index % frame_every == 0:
                write_png(frames / f"frame_{index // frame_every:05d}.png", scene.composite())
    wall = time.perf_counter() - start
    metrics = scene.metrics()
    metrics.update(wall_s=wall, finite=True, steps_per_s=total / wall if wall > 0 else math.inf)
    write_png(out / "final.png", scene.composite())
    save_npz_atomic(out / "state.npz", scene.state_arrays())
    temp = out / ".metrics.json.tmp"
    temp.write_text(json.dumps(metrics, indent=2) + "\n")
    temp.replace(out / "metrics.json")
    return metrics
