"""Headless scene runs: steps with a progress bar, frames, and the output files of docs/guide/headless.md ("Outputs").

Outputs are complete or absent: a run writes everything into a fresh temporary folder beside the output folder
(`.<name>.run<pid>.<host>.<random>`), then swaps it in (the previous folder renamed aside, the new one renamed into place, the
previous one deleted), so an interrupted or failed run leaves the previous complete set or the new complete set,
never a mix. The output folder is the run's own: it is replaced as a whole, and a folder holding anything a run
does not write is refused before the run starts (nothing is deleted that a run did not make). Temporary folders
that a killed run left (SIGKILL, power loss) are removed by the next run into the same folder: their names hold the
process id and host of the run that made them, and that process is gone.
"""
import contextlib
import errno
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from PIL import Image
from tqdm import tqdm

from lab import interrupts
from lab.views import PngFrames
from sims.scene import checks
from sims.scene.assembly import Scene, save_npz_atomic

FINITE_CHECK_EVERY = 50  # steps between NaN/inf checks
PNG_COMPRESS_LEVEL = 3  # zlib level of the PNGs written (write_png)
_HOST = re.sub(r"[^A-Za-z0-9-]", "-", os.uname().nodename)[:32]  # in temporary folder names: pids are per host
OUTPUTS = ("metrics.json", "final.png", "final_normal.png", "final_roughness.png", "state.npz", "frames")  # what a run writes into its folder


class SimulationDiverged(RuntimeError):
    """A field became NaN or inf; the message names the field and the step."""


class RunInterrupted(Exception):
    """Ctrl-C (KeyboardInterrupt) during a run; the message says when and what the output folder holds."""


def write_png(path: Path, rgb) -> None:
    """An (H, W, 3) or (H, W) uint8 image as PNG. zlib level 3: a 512² texture in 0.04 s, not 0.15 s as at Pillow's
    default 6, for files 8-11 % larger."""
    Image.fromarray(rgb).save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def _warn_what_was_lost(scene: Scene, bar) -> None:
    """Say once, on stderr, why a model lost something (the bleeding method blood; metrics count all of it)."""
    for _, warning in scene.take_warnings():
        bar.write(f"warning: {scene.name}: at t = {scene.time_s:.2f} s: {warning}", file=sys.stderr)


def check_scene(scene: Scene) -> None:
    """Before a run: the scene's notes on stderr (sims.scene.checks.notes); ConfigError when it cannot run
    (sims.scene.checks.check_runnable)."""
    for level, text in checks.notes(scene):
        print(f"{level}: {scene.file}: {text}", file=sys.stderr)
    checks.check_runnable(scene)


def _check_output_folder(out: Path) -> None:
    """Raise OSError unless `out` is absent, empty, or holds only what a run writes (OUTPUTS)."""
    if not out.exists():
        return
    if not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder")
    foreign = sorted(entry.name for entry in out.iterdir() if entry.name not in OUTPUTS)
    frames = out / "frames"
    if frames.is_dir():
        foreign += sorted(f"frames/{entry.name}" for entry in frames.iterdir()
                          if not (entry.name.startswith("frame_") and entry.suffix == ".png"))
    if foreign:
        raise FileExistsError(errno.ENOTEMPTY, f"holds files a run does not write ({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); "
                                  "use a new folder, an empty one or a previous run's")


def _temporary_folder(out: Path, kind: str = "") -> Path:
    """A new empty folder beside `out` named `.<out name>.<kind>run<pid>.<host>.<random>` (see _remove_stale_folders)."""
    return Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.{kind}run{os.getpid()}.{_HOST}."))


def _remove_stale_folders(out: Path) -> None:
    """Delete the temporary folders beside `out` (_temporary_folder) of runs on this host whose process is gone."""
    pattern = re.compile(rf"\.{re.escape(out.name)}\.(?:old\.)?run(\d+)\.{re.escape(_HOST)}\.[a-z0-9_]{{8}}")
    for entry in out.parent.iterdir():
        match = pattern.fullmatch(entry.name)
        if match and not _alive(int(match[1])) and entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's; a number no process has is never removed either
        pass
    return True


@contextlib.contextmanager
def _interrupts_held():
    """Hold Ctrl-C (SIGINT) over the block. One that arrived meanwhile is dropped: the block has finished (and
    its outcome, the new outputs in place or an error, stands)."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        try:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
        except KeyboardInterrupt:
            pass


def _swap_in(new: Path, out: Path) -> None:
    """Put folder `new` at `out`, Ctrl-C held throughout: the previous `out` is renamed aside (onto an empty folder
    of a unique name), `new` renamed into place (or the previous one back on failure), the previous one deleted."""
    with _interrupts_held():
        aside = _temporary_folder(out, "old.")
        try:
            moved = out.exists()
            if moved:
                os.rename(out, aside)
            try:
                os.rename(new, out)
            except OSError:
                if moved:
                    os.rename(aside, out)
                raise
        finally:
            shutil.rmtree(aside, ignore_errors=True)


def _steps_per_s(steps: int, wall_s: float) -> float | None:
    """Steps per wall second after the first step, None (JSON null) without such steps or measurable time."""
    return steps / wall_s if steps > 0 and wall_s > 0 else None


def _simulate(scene: Scene, folder: Path, total: int, frame_every: int, progress: bool) -> dict:
    """Run `total` steps, writing frames then final.png (and its final_normal.png and final_roughness.png), state.npz and metrics.json into `folder`; return metrics."""
    frames = PngFrames(folder / "frames", write_png) if frame_every else None
    if frames is not None:
        frames.show(scene)
    start = time.perf_counter()
    first_step = None  # wall s of step 1 with its check: the kernels load from the cache or compile then
    bar = tqdm(total=total, desc=scene.name, unit="step", file=sys.stderr, delay=1.0, disable=not progress, dynamic_ncols=True)
    with bar:
        for index in range(1, total + 1):
            interrupts.check()  # a Ctrl-C that a library swallowed (the CLI's handler remembers it)
            scene.step()
            bar.update(1)
            if index % FINITE_CHECK_EVERY == 0 or index in (1, total):  # step 1: the check's kernel loads with the rest
                bad = scene.non_finite_field()  # reads the device, so waits for the step
                if bad:
                    raise SimulationDiverged(f"{bad} became non-finite at step {index} (t = {scene.time_s:.4g} s)")
            if index == 1:
                first_step = time.perf_counter() - start
            _warn_what_was_lost(scene, bar)
            if frames is not None and index % frame_every == 0:
                frames.show(scene)
    wall = time.perf_counter() - start
    metrics = scene.metrics()
    metrics.update(wall_s=wall, finite=True, first_step_s=first_step, steps_per_s=_steps_per_s(total - 1, wall - (first_step or 0.0)))
    # PNG and zip compression release the GIL: the files compress side by side and while the next arrays are read
    # (0.7 s of compression one after the other for a 512² texture; the bytes are the same). state.npz first: the
    # longest to compress, it does so while the look composes (0.2 s, its kernels loading)
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        writes = [pool.submit(save_npz_atomic, folder / "state.npz", scene.state_arrays())]
        writes.append(pool.submit(write_png, folder / "final.png", scene.composite()))
        normal, roughness = scene.material_maps()
        writes += [pool.submit(write_png, folder / "final_normal.png", normal),
                   pool.submit(write_png, folder / "final_roughness.png", roughness)]
        (folder / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        for write in writes:
            write.result()  # a failed write raises its error (OSError) here
    return metrics


def run(scene: Scene, out_dir, duration_s: float | None = None, frames_every_s: float | None = None, progress: bool = True) -> dict:
    """Run `scene` for duration_s (default: the scene's) and replace the folder out_dir by its outputs; return metrics.

    Raises ConfigError (check_scene), OSError (out_dir not usable: _check_output_folder, or a write failed),
    SimulationDiverged, RunInterrupted (Ctrl-C). On any of them out_dir is as it was before the run."""
    out = Path(out_dir)
    check_scene(scene)
    _check_output_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    duration = scene.config["duration_s"] if duration_s is None else duration_s
    total = int(round(duration / scene.time_step_s))
    frame_every = max(1, int(round(frames_every_s / scene.time_step_s))) if frames_every_s else 0
    had_outputs = out.exists()
    _remove_stale_folders(out)
    folder = _temporary_folder(out)
    try:
        metrics = _simulate(scene, folder, total, frame_every, progress)
        interrupts.check()
        _swap_in(folder, out)
    except KeyboardInterrupt:
        kept = f"previous outputs in {out} kept" if had_outputs else f"nothing written to {out}"
        raise RunInterrupted(f"interrupted at t = {scene.time_s:.2f} s; {kept}") from None
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return metrics
