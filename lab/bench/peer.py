"""Peer: the dam break of lab.bench.dambreak in SPlisHSPlasH (`pysplishsplash` 2.19, DFSPH), for scale.

Same dimensionless problem as ours: a column of width a and height 2a at the left end of a 10a x 2.5a tank,
gravity 9.81 m/s^2, released at t = 0; the front is measured the same way (the rank rule of
lab.reference.dambreak.front_position on the particles' x) and compared with Martin & Moyce 1952 (its front_error).
The scene is the wheel's example `DamBreakModel_2D.json` (DFSPH, volume-map walls after Bender et al. 2019,
micropolar vorticity, CFL time step) with the tank and column changed: the column is `particles_per_a`
particles wide, its particles two radii from the walls as in the example. It runs at the example's scale,
a = 1 m, with the example's artificial viscosity at the example's particle Reynolds number
sqrt(g a) r / nu = 9.6 (nu = 0.01 m^2/s for r = 25 mm in a 1.5 m column), so the viscosity shrinks with the
particle radius like our numerical dissipation. Only T and Z = x / a are compared, so a drops out. (At
a = 25 mm with 50 particles per a, holes opened under the column with water's 1e-6 m^2/s and with the same
particle Reynolds number; only 1e-4 m^2/s ran clean there.)

The peer is optional: `available()` says whether it imports (checked in a subprocess: its import segfaults
unless the system's libGLdispatch is loaded first, and may segfault anyway), and `run` simulates in a
subprocess (this file run as a script, writing JSON), so a crash or a missing wheel gives
{"available": False, "reason": ...} and never takes the bench down. Install: `pip install pysplishsplash==2.19`.
Its cost is measured from its first time step to the end (its wall map is built before; reported apart), with
OMP_NUM_THREADS = TISSUE_LAB_THREADS or all cores. Particle-steps: particles x its time steps (each a DFSPH step
with several pressure iterations; ours count substeps, each a full relaxation step).
"""
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

A_M = 1.0                   # column width a (m): the example's scale (see above)
G_M_S2 = 9.81
TANK_LENGTH_A, TANK_HEIGHT_A = 10.0, 2.5
T_END = 5.5                 # last dimensionless time T = t sqrt(2 g / a) simulated
FRAME_T = 0.028             # front sampling interval in T (our dam break samples every 1 ms: 0.028 in T)
PARTICLE_REYNOLDS = 9.6     # sqrt(g a) r / nu of the example: 1.5 m column, r = 25 mm, nu = 0.01 m^2/s
MAP_CELL_RADII = 5.0        # volume-map cell size, in particle radii (the example's 4 m / 30 cells at r = 0.025 m)
QUICK_TIMEOUT_S, FULL_TIMEOUT_S = 60.0, 240.0
QUICK, FULL = (25,), (25, 50)   # particles across a (quick: 1250 particles, full: also 5000)



def _import_splishsplash():
    """Import pysplishsplash the way that does not segfault: the system's libGLdispatch loaded first (when there is one)."""
    import ctypes

    try:
        ctypes.CDLL("libGLdispatch.so.0", mode=ctypes.RTLD_GLOBAL)
    except OSError:
        pass
    import pysplishsplash

    return pysplishsplash


def _threads() -> int:
    return int(os.environ.get("TISSUE_LAB_THREADS", 0)) or (os.cpu_count() or 1)


def _environment() -> dict:
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = str(_threads())
    return env


def _why_unavailable() -> str | None:
    """None when pysplishsplash imports (in a subprocess), else why not."""
    import importlib.util

    if importlib.util.find_spec("pysplishsplash") is None:
        return "pysplishsplash is not installed (pip install pysplishsplash==2.19)"
    try:
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--check"], capture_output=True, text=True, timeout=60,
                              env=_environment())
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"importing pysplishsplash failed: {exc}"
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        return f"importing pysplishsplash failed ({'segmentation fault' if done.returncode == -11 else tail})"
    return None


def available() -> bool:
    """Whether SPlisHSPlasH can be imported here (never crashes the calling process)."""
    return _why_unavailable() is None


def run(quick: bool) -> dict:
    """Dam break in SPlisHSPlasH at each resolution; {"available": False, "reason": ...} when it cannot run."""
    from lab.bench.common import json_finite
    from lab.reference import dambreak

    reason = _why_unavailable()
    if reason:
        return {"available": False, "reason": reason}
    budget = QUICK_TIMEOUT_S if quick else FULL_TIMEOUT_S
    started = time.perf_counter()
    runs, skipped = [], []
    for per_a in QUICK if quick else FULL:
        left = budget - (time.perf_counter() - started)
        if left < 5.0:
            skipped.append(f"{per_a} particles per a: out of time ({budget:.0f} s for the section)")
            continue
        try:
            raw = _run_subprocess(per_a, dambreak.FRONT_QUANTILE, timeout_s=left)
        except RuntimeError as exc:
            skipped.append(f"{per_a} particles per a: {exc}")
            continue
        error = dambreak.front_error(raw["T"], raw["Z"])
        runs.append({**raw, "error": error, "viscosity_m2_s": viscosity_m2_s(per_a)})
    if not runs:
        return {"available": False, "reason": "; ".join(skipped) or "no run finished"}
    return json_finite({"available": True, "version": runs[0].pop("version"), "threads": _threads(), "runs": runs, "skipped": skipped,
            "setup": {"a_m": A_M, "tank_a": [TANK_LENGTH_A, TANK_HEIGHT_A], "particle_reynolds": PARTICLE_REYNOLDS,
                      "method": "DFSPH", "walls": "volume maps (Bender et al. 2019)"}})


def _run_subprocess(per_a: int, front_quantile: float, timeout_s: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="peer-dambreak-") as work:
        out = Path(work) / "result.json"
        command = [sys.executable, str(Path(__file__).resolve()), "--per-a", str(per_a), "--front-quantile", repr(front_quantile),
                   "--work", work, "--out", str(out)]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, env=_environment())
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"took longer than {timeout_s:.0f} s") from None
        if done.returncode != 0 or not out.is_file():
            tail = (done.stderr.strip().splitlines() or [""])[-1][:200]
            raise RuntimeError(f"exit code {done.returncode}" + (f": {tail}" if tail else ""))
        return json.loads(out.read_text())


def viscosity_m2_s(per_a: int) -> float:
    """The example's artificial viscosity at its particle Reynolds number, for per_a particles across a."""
    return math.sqrt(G_M_S2 * A_M) * (A_M / (2 * per_a)) / PARTICLE_REYNOLDS


def _scene(per_a: int, work: Path) -> Path:
    """The example DamBreakModel_2D.json with our tank and column; written to work/, returns its path."""
    import importlib.metadata

    files = importlib.metadata.files("pysplishsplash") or []
    example = next(f for f in files if str(f).endswith("Scenes/DamBreakModel_2D.json"))
    box = next(f for f in files if str(f).endswith("models/UnitBox.obj"))
    scene = json.loads(Path(example.locate()).read_text())
    radius = A_M / (2 * per_a)
    length, height = TANK_LENGTH_A * A_M, TANK_HEIGHT_A * A_M
    cell = MAP_CELL_RADII * radius
    scene["Configuration"].update(pause=False, particleRadius=radius, gravitation=[0.0, -G_M_S2, 0.0])
    scene["Materials"][0]["Standard viscosity"] = {"viscosity": viscosity_m2_s(per_a)}
    wall = scene["RigidBodies"][0]
    wall.update(geometryFile=str(Path(box.locate()).resolve()), translation=[length / 2, height / 2, 0.0], scale=[length, height, 1.0],
                mapResolution=[math.ceil(length / cell), math.ceil(height / cell), 2])
    # a block [start, end] gets round((end - start) / d) - 1 particles per axis (d = 2 r), centres at start + d, start + 2d, ...:
    # [0, a + d] gives centres d .. a (per_a of them), so the fluid (a d x d cell per particle) covers [r, a + r] x [r, 2a + r]
    # and the centres nearest the walls are two radii from them, as in the example
    scene["FluidBlocks"] = [{"denseMode": 0, "start": [0.0, 0.0, -1.0], "end": [A_M + 2 * radius, 2 * A_M + 2 * radius, 1.0],
                             "translation": [0.0, 0.0, 0.0], "scale": [1, 1, 1]}]
    path = work / "dambreak.json"
    path.write_text(json.dumps(scene, indent=1))
    return path


def simulate(per_a: int, front_quantile: float, work: Path) -> dict:
    """Run the dam break in this process (call only in a subprocess: the import may segfault)."""
    import importlib.metadata

    import numpy as np

    sph = _import_splishsplash()

    scale = math.sqrt(2.0 * G_M_S2 / A_M)
    t_end = T_END / scale
    base = sph.Exec.SimulatorBase()
    base.init(sceneFile=str(_scene(per_a, work)), useGui=False, stopAt=t_end, useCache=False, outputDir=str(work / "output"))
    history = {"T": [], "Z": [], "steps": 0, "first_step": None, "first_time": 0.0}

    def front(model):
        n = model.numActiveParticles()
        x = np.sort(np.array(model.getFieldBuffer("position"), copy=False)[:n, 0].astype(np.float64))
        return x[-1 - int(front_quantile * n)] / A_M  # lab.reference.dambreak.front_position: same rank

    def on_step():
        now = time.perf_counter()
        time_s = sph.TimeManager.getCurrent().getTime()
        if history["first_step"] is None:  # the clock starts after the first step
            history["first_step"], history["first_time"] = now, time_s
        history["steps"] += 1
        T = time_s * scale
        if T >= len(history["T"]) * FRAME_T:
            history["T"].append(T)
            history["Z"].append(front(sph.Simulation.getCurrent().getFluidModel(0)))

    base.setTimeStepCB(on_step)
    setup_start = time.perf_counter()
    base.initSimulation()
    model = sph.Simulation.getCurrent().getFluidModel(0)
    n = model.numActiveParticles()
    history["T"].append(0.0)
    history["Z"].append(front(model))
    base.runSimulation()
    end = time.perf_counter()
    simulated = sph.TimeManager.getCurrent().getTime()
    base.cleanup()
    first = history["first_step"] or end
    wall = max(end - first, 1e-9)
    timed_steps = max(history["steps"] - 1, 0)
    return {
        "particles_per_a": per_a,
        "particles": int(n),
        "T": history["T"],
        "Z": history["Z"],
        "steps": history["steps"],
        "simulated_s": simulated,
        "setup_s": first - setup_start,
        "wall_s": wall,
        "ms_per_simulated_s": 1000.0 * wall / max(simulated - history["first_time"], 1e-9),  # at a = A_M
        "particle_steps_per_s": n * timed_steps / wall,
        "version": importlib.metadata.version("pysplishsplash"),
    }


def render(results: dict) -> list[str]:
    lines = ["## Peer: SPlisHSPlasH dam break", ""]
    if not results.get("available"):
        return lines + [f"Not run: {results.get('reason', 'unavailable')}.", ""]
    setup = results["setup"]
    lines += [
        f"The same dimensionless dam break (column a x 2a, tank {setup['tank_a'][0]:g}a x {setup['tank_a'][1]:g}a, run at a = {setup['a_m']:g} m) "
        f"in SPlisHSPlasH {results['version']}: its 2D example scene ({setup['method']}, walls by {setup['walls']}, micropolar vorticity, "
        f"CFL time step) with its artificial viscosity at its particle Reynolds number sqrt(g a) r / nu = {setup['particle_reynolds']:g}; "
        f"{results['threads']} OpenMP thread(s). Front and error as in the dam break section; a particle-step here is one DFSPH "
        "time step (several pressure iterations), timed from its first step (the wall map is built before, column \"set-up\").",
        "",
        "| particles per a | particles | mean abs error (a) | max abs error (a) | mean signed (a) | time steps | release wall (s) | "
        "particle-steps/s | wall-map set-up (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in results["runs"]:
        error = row["error"]
        lines.append(
            f"| {row['particles_per_a']} | {row['particles']:,} | {error['mean_abs_a']:.3f} | {error['max_abs_a']:.3f} | "
            f"{error['mean_signed_a']:+.3f} | "
            f"{row['steps']} | {row['wall_s']:.1f} | {row['particle_steps_per_s']:.3g} | {row['setup_s']:.1f} |"
        )
    for note in results.get("skipped", []):
        lines.append(f"\nSkipped: {note}.")
    lines.append("")
    return lines


def _main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="one SPlisHSPlasH dam break; writes JSON to --out (--check: only import it)")
    parser.add_argument("--check", action="store_true")
    parser.add_argument("--per-a", type=int)
    parser.add_argument("--front-quantile", type=float)
    parser.add_argument("--work")
    parser.add_argument("--out")
    args = parser.parse_args(argv)
    if args.check:
        _import_splishsplash()
        return 0
    if None in (args.per_a, args.front_quantile, args.work, args.out):
        parser.error("--per-a, --front-quantile, --work and --out are required")
    result = simulate(args.per_a, args.front_quantile, Path(args.work))
    Path(args.out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
