"""Cost against activity: what a lab pays per simulated second when nothing happens, when one or two tools burn and
when one or four vessels bleed, at several texture sizes, per stage; and what an idle `python -m lab serve` costs
(Linux: it reads /proc)."""
import time

import numpy as np

from lab.bench.common import TEXTURE_UPDATES_PER_S, free_port, lab_stream, pyplot, save, stream_frame
from sims.core import backend
from sims.scene.config import REPO_ROOT

STAGES = ("cautery", "bleeding", "compose", "encoding")
CASES = ("idle", "one tool", "two tools", "one bleed point", "four bleed points")
PARKED_Z_MM = 40.0           # tools wait this high above the patch, off
STROKE_MM_S = 4.0            # a burning tool moves along x at this speed
TOOL_PATHS = (((-12.0, 4.0), 1.0), ((-12.0, -6.0), 1.0))  # (start x, y) mm and direction along x of each tool
BLEED_XY_MM = ((8.0, 14.0), (-7.5, 9.0), (-14.0, -4.0), (14.0, -8.0))
BASE = ["instruments=[{name: ball_a, shape: {type: ball, radius_mm: 1.5}, tip_temperature_c: 250, "
        f"position_mm: [0, 0, {PARKED_Z_MM}]}}, {{name: ball_b, shape: {{type: ball, radius_mm: 1.5}}, "
        f"tip_temperature_c: 250, position_mm: [5, 0, {PARKED_Z_MM}]}}]", "bleed_points=[]"]



def _drive(scene, case: str, points_added: list) -> None:
    """Before a step: move the burning tools along their strokes; add the case's bleed points once."""
    tools = {"one tool": 1, "two tools": 2}.get(case, 0)
    for index, ((x0, y), sign) in enumerate(TOOL_PATHS[:tools]):
        name = ("ball_a", "ball_b")[index]
        x = x0 + sign * STROKE_MM_S * scene.time_s
        scene.rest_on_tissue(name, [x, y, PARKED_Z_MM], 0.3)
        scene.set_energized(name, True)
    points = {"one bleed point": 1, "four bleed points": 4}.get(case, 0)
    for index in range(len(points_added), points):
        x, y = BLEED_XY_MM[index]
        hit = scene.surface_hit([x, y, PARKED_Z_MM], [0.0, 0.0, -1.0])
        scene.add_bleed_point(f"p{index}", hit, 0.03, 0.6)
        points_added.append(index)


def case_cost(size: int, case: str, seconds: float, server) -> dict:
    """Wall ms per simulated second in each stage for one case on the patch with both models (hemostasis.yaml's
    tissue and bleeding), the display composed and streamed as often as the lab does to a stream without
    browsers made as the lab makes it, on simulated time (encoding: change detection and the published tiles' PNGs in
    GLBs, at most the lab's rate limit of tile versions per simulated second)."""
    from sims.scene.assembly import Scene

    scene = Scene.from_file(REPO_ROOT / "scenes" / "hemostasis.yaml", [f"texture_size={size}", *BASE])
    stream = lab_stream(server, scene, f"/activity/{size}")
    points: list = []
    every = max(1, int(round(1.0 / (TEXTURE_UPDATES_PER_S * scene.time_step_s))))
    warm = int(round(0.3 / scene.time_step_s))  # compile, the first step's pass over every tile, the first frame
    steps = warm + max(1, int(round(seconds / scene.time_step_s)))
    encoding, sent, updates, maps_s = 0.0, 0, 0, 0.0
    for step in range(1, steps + 1):
        if step == warm + 1:
            scene.profile, scene.model_seconds, encoding, sent, updates, maps_s = True, {}, 0.0, 0, 0, 0.0
        _drive(scene, case, points)
        scene.step()
        if step % every == 0:
            frame = stream_frame(scene, stream)
            maps_s, encoding, sent, updates = maps_s + frame[0], encoding + frame[1], sent + frame[2], updates + 1
    stream.close()
    simulated = (steps - warm) * scene.time_step_s
    cost = {stage: 1000.0 * scene.model_seconds.get(stage, 0.0) / simulated for stage in STAGES[:3]}
    cost["compose"] += 1000.0 * maps_s / simulated
    cost["encoding"] = 1000.0 * encoding / simulated
    row = {"texture_size": size, "case": case, "simulated_s": simulated, "ms_per_simulated_s": cost,
           "total_ms_per_simulated_s": sum(cost.values()), "kb_per_update": sent / 1000.0 / max(updates, 1),
           "hot_tiles_awake": int(scene.cautery.tiles.awake), "blood_ml": float(scene.metrics()["bleeding"].get("volume_ml", 0.0))}
    backend.restart()  # a fresh Taichi runtime on the same device for the next run: a section's scenes outgrow one
    return row


def idle_lab_process(seconds: float, settle_s: float = 20.0) -> dict:
    """Share of one core that `python -m lab serve` takes, as a process of its own with no browser, on the default
    scene at 512² without its tools (nothing burns or bleeds): CPU seconds (user + system, every thread: simulation,
    viser server, GUI) over `seconds` of wall time, once it serves and settle_s have passed (the build compiles)."""
    import os
    import subprocess
    import sys
    import urllib.request

    def cpu_s(pid: int) -> float:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    port = free_port()
    command = [sys.executable, "-m", "lab", "serve", str(REPO_ROOT / "scenes" / "default.yaml"), "--port", str(port),
               "--set", "instruments=[]"]
    lab = subprocess.Popen(command, cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300.0
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1.0)
                break
            except OSError:
                if lab.poll() is not None:
                    raise RuntimeError(f"the lab exited with code {lab.returncode}") from None
                time.sleep(0.5)
        time.sleep(settle_s)
        cpu, wall = cpu_s(lab.pid), time.perf_counter()
        time.sleep(seconds)
        share = (cpu_s(lab.pid) - cpu) / (time.perf_counter() - wall)
    finally:
        lab.terminate()
        lab.wait(timeout=30)
    return {"seconds": seconds, "cpu_share": share}


def run(quick: bool) -> dict:
    import viser

    sizes = (256,) if quick else (256, 512, 1024)
    seconds = 0.3 if quick else 2.0
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        rows = [case_cost(size, case, seconds, server) for size in sizes for case in CASES]
    finally:
        server.stop()
    return {"rows": rows, "idle_lab": idle_lab_process(2.0 if quick else 10.0, 5.0 if quick else 20.0)}


def render(results: dict) -> list[str]:
    lab = results["idle_lab"]
    lines = [
        "## Cost against activity",
        "",
        "The liver patch with both models (hemostasis.yaml's tissue and height-field bleeding) and two ball electrodes,",
        f"run for {results['rows'][0]['simulated_s']:g} simulated s after a warm-up: idle (tools parked and off, no bleeding), one or two",
        f"tools burning along strokes at {STROKE_MM_S:g} mm/s, one or four vessels bleeding 0.03 ml/s. Wall ms per simulated second in",
        f"each stage (device synchronised around each), the display composed and streamed {TEXTURE_UPDATES_PER_S} times per simulated second",
        "(encoding: the stream's change detection and the changed tiles' maps as PNG in GLB, at most the lab's rate limit of",
        "tile versions per simulated second). % of a core: the total at",
        "real time, as the lab runs.",
        "",
        "| texels | case | " + " | ".join(STAGES) + " | total | % of a core | kB per update |",
        "|---|---|" + "---|" * len(STAGES) + "---|---|---|",
    ]
    for row in results["rows"]:
        costs = " | ".join(f"{row['ms_per_simulated_s'][stage]:.1f}" for stage in STAGES)
        lines.append(f"| {row['texture_size']}² | {row['case']} | {costs} | {row['total_ms_per_simulated_s']:.1f} | "
                     f"{row['total_ms_per_simulated_s'] / 10:.1f} | {row['kb_per_update']:.1f} |")
    lines += ["", f"An idle lab (`python -m lab serve scenes/default.yaml --set instruments=[]`, 512², a process of its own "
              f"with no browser: simulation thread, viser server and GUI) took {100 * lab['cpu_share']:.1f} % of one "
              f"core over {lab['seconds']:g} s of wall time."]
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    sizes = sorted({row["texture_size"] for row in results["rows"]})
    fig, axes = plt.subplots(1, len(sizes), figsize=(3.4 * len(sizes), 3.0), sharey=True)
    for ax, size in zip(np.atleast_1d(axes), sizes):
        rows = [row for row in results["rows"] if row["texture_size"] == size]
        left = np.zeros(len(rows))
        for stage in STAGES:
            values = np.array([row["ms_per_simulated_s"][stage] for row in rows])
            ax.barh([row["case"] for row in rows], values, left=left, label=stage)
            left += values
        ax.axvline(50.0, color="k", ls=":", lw=1, label="5 % of a core")
        ax.set_title(f"{size}²")
        ax.set_xlabel("wall ms per simulated s")
    np.atleast_1d(axes)[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside: no bar hidden
    fig.suptitle("Cost against activity")
    return [save(fig, out_dir, "activity.png")]
