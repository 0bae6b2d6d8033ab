"""Per-scene cost: wall ms per simulated second in each model (cautery, bleeding, compose, texture encoding), so a
scene is seen to pay only for the models it names; and how long a trainer waits for each scene to be built."""
import time

from lab.bench.common import TEXTURE_UPDATES_PER_S, free_port, lab_stream, pyplot, save, stream_frame
from sims.core import backend
from sims.scene.config import REPO_ROOT

MODELS = ("cautery", "bleeding", "compose", "encoding")
RUNS = 3  # each scene's cost is its fastest of this many runs: a burst of other load on the machine does not count
PRESETS = (("default.yaml", "accurate"),)  # (scene, lab quality preset) also measured under the preset (full runs)
QUICK_BUILD_SCENE = "hemostasis.yaml"  # the one scene whose build a quick run times (the others show "-")



def scene_cost(path, seconds: float, server, preset: str = "scene file") -> dict:
    """Run the first `seconds` of a scene with profiling; every 1/10 simulated s compose the texture and hand the
    changed tiles to a TextureStream made as the lab makes it, on simulated time, on a viser server with no client
    (encoding = change detection and the published tiles' colour, normal and roughness PNGs in GLBs). preset: a lab
    quality preset (lab.session.QUALITY) whose overrides apply."""
    from lab.session import QUALITY, fitting_overrides
    from sims.scene.assembly import Scene

    scene = Scene.from_file(path, fitting_overrides(path, QUALITY[preset]))  # as the lab applies it
    scene.step()  # compile the step kernels, then the display ones
    scene.reset()
    stream = lab_stream(server, scene, f"/bench/{path.stem}")
    stream_frame(scene, stream)
    scene.profile = True
    steps = max(1, int(round(seconds / scene.time_step_s)))
    every = max(1, int(round(1.0 / (TEXTURE_UPDATES_PER_S * scene.time_step_s))))
    sent_bytes, updates, encoding, maps_s = 0, 0, 0.0, 0.0
    for step in range(1, steps + 1):
        scene.step()
        if step % every == 0:
            frame = stream_frame(scene, stream)
            maps_s, encoding, sent_bytes, updates = maps_s + frame[0], encoding + frame[1], sent_bytes + frame[2], updates + 1
    stream.close()
    simulated = steps * scene.time_step_s
    cost = {model: 1000.0 * scene.model_seconds.get(model, 0.0) / simulated for model in MODELS[:3]}
    cost["compose"] += 1000.0 * maps_s / simulated
    cost["encoding"] = 1000.0 * encoding / simulated
    metrics = scene.metrics()
    backend.restart()  # a fresh Taichi runtime on the same device for the next run: a section's scenes outgrow one
    return {
        "scene": path.name if preset == "scene file" else f"{path.name} ({preset})",
        "models": list(scene.models),
        "texture_size": scene.config["texture_size"],
        "time_step_s": scene.time_step_s,
        "simulated_s": simulated,
        "ms_per_simulated_s": cost,
        "total_ms_per_simulated_s": sum(cost.values()),
        "realtime_factor": 1000.0 / sum(cost.values()),
        "bytes_per_update": sent_bytes / max(updates, 1),
        "particles_at_end": int(metrics.get("bleeding", {}).get("alive", 0)),
    }


def build_times(path) -> dict:
    """Wall seconds until a scene shows in the lab: a lab session's build (scene file, mesh and textures, texel maps,
    models, a fresh Taichi runtime) with its first step and composite (the kernels compile then, or load from the
    offline cache); first when the lab starts on it, then when it is built again (a switch or a rebuild)."""
    from lab.session import LabSession

    started = time.perf_counter()
    session = LabSession(path)
    session.scene.step()
    session.scene.composite()
    first = time.perf_counter() - started
    started = time.perf_counter()
    session.back_to_scene_file()
    session.tick()  # the rebuild; its first tick takes no step
    session.scene.step()
    session.scene.composite()
    return {"first_build_s": first, "rebuild_s": time.perf_counter() - started}


def run(quick: bool) -> dict:
    import viser

    paths = sorted((REPO_ROOT / "scenes").glob("*.yaml"))
    built = [path for path in paths if not quick or path.name == QUICK_BUILD_SCENE]  # each build costs 20-25 s
    builds = {path.name: build_times(path) for path in built}
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        repeats = 1 if quick else RUNS
        runs = [(path, "scene file") for path in paths] + ([] if quick else [(REPO_ROOT / "scenes" / name, preset) for name, preset in PRESETS])
        rows = [{**min((scene_cost(path, 1.0 if quick else 5.0, server, preset) for _ in range(repeats)),
                       key=lambda row: row["total_ms_per_simulated_s"]),
                 **(builds[path.name] if preset == "scene file" and path.name in builds else {"first_build_s": None, "rebuild_s": None}),
                 "runs": repeats}
                for path, preset in runs]
    finally:
        server.stop()
    return {"frames_per_simulated_s": TEXTURE_UPDATES_PER_S, "scenes": rows}


def render(results: dict) -> list[str]:
    lines = [
        "## Cost per scene and model",
        "",
        f"Each scene in scenes/ run from t = 0 for {results['scenes'][0]['simulated_s']:g} simulated s at its own texture size and time step, the",
        f"fastest of {results['scenes'][0].get('runs', 1)} runs; wall milliseconds per simulated second in each model (device synchronised around each),",
        f"with {results['frames_per_simulated_s']} display updates per simulated second composed and encoded as the browser lab does (changed 64²",
        "tiles as PNG in GLB, at most the lab's stream rate limit of tile versions per simulated second). A model the scene does not name costs nothing. Real-time factor: simulated seconds per wall second.",
        "Build: wall seconds until the scene shows in the lab (lab session build, first step and composite), when the lab",
        "starts on it and when it is built again (a scene switch or a rebuild slider). A row named with a preset (full runs)",
        "runs the scene under that quality preset of the lab (lab.session.QUALITY; accurate: 1024² texels).",
        "",
        "| scene | models | texels | " + " | ".join(MODELS) + " | total | real-time factor | kB per update | particles at end | build s | rebuild s |",
        "|---|---|---|" + "---|" * len(MODELS) + "---|---|---|---|---|---|",
    ]
    for row in results["scenes"]:
        costs = " | ".join(f"{row['ms_per_simulated_s'][m]:.0f}" if m in row["models"] or m in ("compose", "encoding") else "-" for m in MODELS)
        lines.append(f"| {row['scene']} | {', '.join(row['models'])} | {row['texture_size']}² | {costs} | {row['total_ms_per_simulated_s']:.0f} | "
                     f"{row['realtime_factor']:.2f} | {row['bytes_per_update'] / 1000:.1f} | {row['particles_at_end']:,} | "
                     + " | ".join("-" if row[key] is None else f"{row[key]:.1f}" for key in ("first_build_s", "rebuild_s")) + " |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.2))
    names = [row["scene"] for row in results["scenes"]]
    left = [0.0] * len(names)
    for model in MODELS:
        values = [row["ms_per_simulated_s"][model] for row in results["scenes"]]
        ax.barh(names, values, left=left, label=model)
        left = [a + b for a, b in zip(left, values)]
    ax.axvline(1000.0, color="k", ls="--", lw=1, label="real time")
    ax.set_xlabel("wall ms per simulated second")
    ax.set_title("Cost per scene and model")
    ax.legend(fontsize=7)
    return [save(fig, out_dir, "scene_cost.png")]
