"""Start-up cost of a headless run: where the seconds of `python -m lab run` go for an idle 5 s run of a 512² plane
(a 24 mm flat square, the cautery model, one ball parked 40 mm above it and off), stage by stage, in fresh processes
with the kernel cache warm, as a scripted study meets them."""
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lab.bench.common import pyplot, save
from lab.reference.meshes import plane_mesh
from sims.scene.config import REPO_ROOT

PLANE_MM = 24.0
SCENE = """name: idle_plane
mesh: {mesh}
texture_size: 512
models: [cautery]
duration_s: 5.0
time_step_s: 0.01
tissue: {{preset: liver}}
instruments:
  - {{name: ball, shape: {{type: ball, radius_mm: 1.5}}, tip_temperature_c: 250, position_mm: [0.0, 0.0, 40.0], energized: false}}
"""
# The run as `python -m lab run` makes it, each stage timed by wrapping the function that does it. Printed: JSON.
CHILD = """
import json, sys, time
started = time.perf_counter()
import lab.__main__
lab.__main__.build_parser()  # as the CLI does before it runs
from lab import runner
import sims.scene.assembly, sims.surface.texels
from sims.core import backend
seconds = {"imports": time.perf_counter() - started}

def timed(module, name, stage):
    inner = getattr(module, name)
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            seconds[stage] = seconds.get(stage, 0.0) + time.perf_counter() - start
    setattr(module, name, wrapper)

for module, name, stage in ((sims.scene.assembly, "load_scene_config", "scene file"), (sims.scene.assembly, "load_inputs", "mesh and textures"),
                            (backend, "init", "Taichi start"), (sims.surface.texels, "build_surface", "surface (texel maps)")):
    timed(module, name, stage)
start = time.perf_counter()
scene = sims.scene.assembly.Scene.from_file(sys.argv[1], arch=sys.argv[3])
built = time.perf_counter() - start
seconds["models"] = built - sum(seconds[stage] for stage in ("scene file", "mesh and textures", "Taichi start", "surface (texel maps)"))
start = time.perf_counter()
metrics = runner.run(scene, sys.argv[2], progress=False)
seconds["first step"] = metrics["first_step_s"]
seconds["other steps"] = metrics["wall_s"] - metrics["first_step_s"]
seconds["outputs"] = time.perf_counter() - start - metrics["wall_s"]
seconds["total"] = time.perf_counter() - started
print(json.dumps(seconds))
lab.__main__.exit_now(0)  # as the CLI ends
"""
STAGES = ("interpreter", "imports", "scene file", "mesh and textures", "Taichi start", "surface (texel maps)", "models",
          "first step", "other steps", "outputs")


def _scene(folder: Path) -> Path:
    """Write the idle plane's mesh and scene file into folder; returns the scene file."""
    plane_mesh(PLANE_MM, PLANE_MM).export(folder / "plane.obj")
    path = folder / "idle_plane.yaml"
    path.write_text(SCENE.format(mesh=folder / "plane.obj"))
    return path


def _process(command: list[str]) -> tuple[float, str]:
    """Wall seconds of a fresh process running command from the repository root, and what it printed."""
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, cwd=REPO_ROOT, check=True)
    return time.perf_counter() - start, result.stdout


def run(quick: bool) -> dict:
    """Median seconds per stage over `runs` stage-timed processes, and the median wall of as many plain runs, after
    one of each to fill the kernel cache (a study's first run compiles; the bench measures the runs after it)."""
    from sims.core import backend

    runs = 2 if quick else 5
    arch = backend.started_arch()
    arch = "cpu" if arch in backend.CPU_ARCHS else "gpu"
    with tempfile.TemporaryDirectory() as folder:
        scene = _scene(Path(folder))
        out = str(Path(folder) / "out")
        plain = [sys.executable, "-m", "lab", "run", str(scene), "--out", out, "--quiet", "--arch", arch]
        staged = [sys.executable, "-c", CHILD, str(scene), out, arch]
        walls, stage_rows = [], []
        for index in range(runs + 1):
            wall, _ = _process(plain)
            staged_wall, printed = _process(staged)
            if index:  # the first of each fills the cache
                stages = json.loads(printed.strip().splitlines()[-1])
                stages["interpreter"] = staged_wall - stages.pop("total")  # start-up and exit of the interpreter
                walls.append(wall)
                stage_rows.append(stages)
    seconds = {stage: statistics.median(row[stage] for row in stage_rows) for stage in STAGES}
    return {"runs": runs, "arch": arch, "texture_size": 512, "plane_mm": PLANE_MM, "process_s": statistics.median(walls),
            "process_range_s": [min(walls), max(walls)], "stages_s": seconds}


def render(results: dict) -> list[str]:
    seconds = results["stages_s"]
    total = sum(seconds.values())
    lines = [
        "## Start-up of a headless run",
        "",
        f"`python -m lab run` on an idle 5 s scene of a {results['texture_size']}² {results['plane_mm']:g} mm plane (cautery, one ball parked above it and",
        f"off; 500 steps of 0.01 s), in fresh processes with the kernel cache warm: {results['process_s']:.2f} s per process, the median of {results['runs']}",
        f"({results['process_range_s'][0]:.2f}-{results['process_range_s'][1]:.2f} s). Where it goes (medians of as many processes with each stage timed;",
        "interpreter: Python's start and exit (the CLI skips the teardown: lab.__main__.exit_now); surface: the display's",
        "texel maps; models: the heat grid's texel maps, the heat model, tools and display maps; first step: with its",
        "kernels loaded from the cache;",
        "outputs: final.png, its maps, state.npz, metrics.json):",
        "",
        "| stage | s | share |",
        "|---|---|---|",
    ]
    lines += [f"| {stage} | {seconds[stage]:.2f} | {100 * seconds[stage] / total:.0f} % |" for stage in STAGES]
    lines.append(f"| total | {total:.2f} | 100 % |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.4, 2.0))
    left = 0.0
    for stage in STAGES:
        width = results["stages_s"][stage]
        ax.barh(["run"], [width], left=left, label=stage)
        left += width
    ax.set_xlabel("wall seconds")
    ax.set_title("Start-up of an idle 5 s headless run (512² plane)")
    ax.legend(fontsize=6, ncol=2, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return [save(fig, out_dir, "startup.png")]
