"""Benchmarks: speed next to error. `python -m lab bench [--quick] --out DIR` writes report.md and results.json."""
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sims import analytic, backend
from sims.config import REPO_ROOT

BODY_C = 37.0


def build_plane(side_mm: float, size: int):
    """A flat square of side_mm centred at the origin, rasterised at size^2 texels."""
    from sims.surface import build_surface

    return build_surface(_plane(side_mm, side_mm), size)


def _plane(width_mm: float, height_mm: float):
    import trimesh

    xs, ys = np.meshgrid(np.linspace(-width_mm / 2, width_mm / 2, 9), np.linspace(-height_mm / 2, height_mm / 2, 9))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    uv = np.stack([xs.ravel() / width_mm + 0.5, ys.ravel() / height_mm + 0.5], axis=1)
    faces = [[j * 9 + i, j * 9 + i + 1, j * 9 + i + 10] for j in range(8) for i in range(8)]
    faces += [[j * 9 + i, j * 9 + i + 10, j * 9 + i + 9] for j in range(8) for i in range(8)]
    return trimesh.Trimesh(vertices, np.array(faces), visual=trimesh.visual.TextureVisuals(uv=uv), process=False)


def heat_error(size: int, seconds: float, dt_s: float = 0.01, sigma_mm: float = 1.0) -> dict:
    """Gaussian on a 40 x 40 mm plane (liver, no perfusion) against the analytic solution."""
    from sims import params
    from sims.cautery import Cautery
    from sims.instruments import InstrumentFields
    from sims.surface import build_surface

    surface = build_surface(_plane(40.0, 40.0), size)
    tissue = dict(params.TISSUE_PRESETS["liver"], perfusion_1_s=0.0)
    cautery_params = {name: spec.default for name, spec in params.CAUTERY.items()}
    cautery = Cautery(surface, tissue, cautery_params, InstrumentFields([]))
    r2 = (surface.position_mm[..., :2] ** 2).sum(axis=2)
    amplitude = 50.0
    cautery.set_temperature(BODY_C + analytic.gaussian_on_plane(r2, amplitude, sigma_mm, 0.0, 0.0))
    steps = int(round(seconds / dt_s))
    for _ in range(steps):
        cautery.step(dt_s)
    alpha = cautery.diffusivity_mm2_s
    exact = analytic.gaussian_on_plane(r2, amplitude, sigma_mm, alpha, steps * dt_s)
    excess = cautery.temperature_c() - BODY_C
    area = surface.texel_area_mm2
    variance = (excess * area * r2).sum() / (excess * area).sum() / 2.0
    return {
        "max_error_rel": float(np.abs(excess - exact).max() / exact.max()),
        "variance_error_rel": float(variance / (sigma_mm**2 + 2 * alpha * steps * dt_s) - 1.0),
        "texel_mm": 40.0 / size,
    }


def cautery_speed(size: int, steps: int) -> dict:
    """Steps per second of the default scene (two instruments, 8 s stroke) at size^2 texels."""
    from sims.scene import Scene

    scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", [f"texture_size={size}"])
    scene.step()  # compile
    start = time.perf_counter()
    for _ in range(steps):
        scene.step()
    wall = time.perf_counter() - start
    scene.composite()  # compile
    compose_start = time.perf_counter()
    for _ in range(10):
        scene.composite()
    return {
        "steps_per_s": steps / wall,
        "ms_per_simulated_s": 1000.0 * wall / (steps * scene.time_step_s),
        "heat_substeps_per_step": scene.cautery.substeps(scene.time_step_s),
        "compose_ms": (time.perf_counter() - compose_start) / 10 * 1000.0,
    }


def bleeding_throughput(count: int, steps: int, numpy_steps: int) -> dict:
    """Particle steps per second of sims.sph and of the NumPy + cKDTree step, same particles, flat plane."""
    from lab.sph_reference import NumpyBleeding, disk_positions
    from sims import params
    from sims.sph import Bleeding

    values = {name: spec.default for name, spec in params.BLEEDING.items()}
    positions = disk_positions(count, values["particle_spacing_mm"])
    side = 2.4 * float(np.abs(positions).max())
    size = int(min(2048, max(256, 2 ** math.ceil(math.log2(side / 0.15)))))
    bleeding = Bleeding(build_plane(side, size), values, (0.0, 0.0, 0.0), count)
    grid = (positions / side + 0.5) * size
    grid[:, 1] = size - grid[:, 1]  # rows grow toward -y
    bleeding.place(grid)
    bleeding.step(0.01)  # compile
    start = time.perf_counter()
    for _ in range(steps):
        bleeding.step(0.01)
    taichi_rate = count * steps / (time.perf_counter() - start)
    row = {"particles": count, "texture_size": size, "taichi_particle_steps_per_s": taichi_rate, "taichi_steps_per_s": taichi_rate / count}
    if numpy_steps:
        reference = NumpyBleeding(positions, values)
        reference.step(0.01)
        start = time.perf_counter()
        for _ in range(numpy_steps):
            reference.step(0.01)
        numpy_rate = count * numpy_steps / (time.perf_counter() - start)
        row.update(numpy_particle_steps_per_s=numpy_rate, speedup=taichi_rate / numpy_rate)
    return row


def density_error_against_substeps(substeps: int) -> dict:
    """A blob of 80 particles released in the hollow of the patch: mean density error after 3 s."""
    from sims import params
    from sims.sph import Bleeding
    from sims.surface import build_surface, load_mesh

    surface = build_surface(load_mesh(REPO_ROOT / "static/meshes/patch.obj"), 256)
    values = {name: spec.default for name, spec in params.BLEEDING.items()}
    values["substeps"] = substeps
    bleeding = Bleeding(surface, values, (0.0, 0.0, -9810.0), 200)
    distance = np.linalg.norm(surface.position_mm[..., :2] - (-7.0, 10.0), axis=-1) + np.where(surface.mask, 0, np.inf)
    bleeding.spawn(np.unravel_index(np.argmin(distance), distance.shape), 80, 1.0)
    start = time.perf_counter()
    for _ in range(300):
        bleeding.step(0.01)
    wall = time.perf_counter() - start
    rho = bleeding.density.to_numpy()[: bleeding.count, 0]
    position = bleeding.particle_arrays()["particle_position_mm"]
    reach = np.linalg.norm(position - position.mean(axis=0), axis=1)
    bulk = reach < 0.6 * reach.max()  # away from the free edge, where particles miss neighbours
    return {
        "substeps": substeps,
        "density_error_rel": float(rho.mean() / bleeding.rest_density - 1.0),
        "bulk_density_error_rel": float(rho[bulk].mean() / bleeding.rest_density - 1.0),
        "ms_per_simulated_s": wall / 3.0 * 1000.0,
    }


def run(out_dir, quick: bool = False, arch: str = "auto") -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = backend.init(arch)
    sizes = (256, 512, 1024)
    results = {"device": {"arch": device, "machine": platform.machine(), "processor": platform.processor() or platform.machine(), "python": platform.python_version()}, "quick": quick, "cautery": []}
    for size in tqdm(sizes, desc="cautery", unit="size"):
        row = {"texture_size": size}
        row.update(cautery_speed(size, steps=50 if quick else 200))
        row.update(heat_error(size, seconds=1.0 if quick else 4.0))
        results["cautery"].append(row)
    results["bleeding_throughput"] = []
    counts = (10_000, 100_000) if quick else (10_000, 100_000, 300_000)
    for count in tqdm(counts, desc="bleeding", unit="size"):
        numpy_steps = 0 if count > 100_000 else (3 if count <= 10_000 else 1)
        results["bleeding_throughput"].append(bleeding_throughput(count, steps=5 if quick else 20, numpy_steps=numpy_steps))
    results["bleeding_density"] = [density_error_against_substeps(n) for n in tqdm((1, 2, 4, 8), desc="settling", unit="run")]
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "report.md").write_text(render(results))
    return results


def render(results: dict) -> str:
    device = results["device"]
    lines = [
        "# Speed and accuracy",
        "",
        f"Device: Taichi arch `{device['arch']}` on {device['processor']} ({device['machine']}), Python {device['python']}."
        + (" Quick run." if results["quick"] else ""),
        "",
        "## Cautery",
        "",
        "Speed: the default scene (liver patch, two instruments, dt = 0.01 s). Error: a Gaussian (s = 1 mm) on a",
        "40 x 40 mm liver plane against the analytic solution; max error relative to the exact peak, and the",
        "relative error of the measured variance against s² + 2αt.",
        "",
        "| texels | texel (mm) | steps/s | ms per simulated s | heat substeps | compose (ms) | max error | variance error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in results["cautery"]:
        lines.append(
            f"| {row['texture_size']}² | {row['texel_mm']:.3f} | {row['steps_per_s']:.1f} | {row['ms_per_simulated_s']:.0f} | "
            f"{row['heat_substeps_per_step']} | {row['compose_ms']:.1f} | {row['max_error_rel']:.2%} | {row['variance_error_rel']:+.3%} |"
        )
    lines += [
        "",
        "## Bleeding",
        "",
        "Throughput: particles at rest spacing in a disk on a flat plane, no gravity, default parameters",
        "(2 substeps per step). The NumPy + scipy cKDTree version of the same step runs in the same process.",
        "",
        "| particles | Taichi steps/s | Taichi particle-steps/s | NumPy+cKDTree particle-steps/s | speed-up |",
        "|---|---|---|---|---|",
    ]
    for row in results["bleeding_throughput"]:
        numpy_rate = f"{row['numpy_particle_steps_per_s']:.3g}" if "numpy_particle_steps_per_s" in row else "not run"
        speedup = f"{row['speedup']:.1f}x" if "speedup" in row else "-"
        lines.append(f"| {row['particles']:,} | {row['taichi_steps_per_s']:.1f} | {row['taichi_particle_steps_per_s']:.3g} | {numpy_rate} | {speedup} |")
    lines += [
        "",
        "Density error: 80 particles released in the hollow of the patch, mean density against rest density after 3 s.",
        "",
        "| substeps | mean density error | bulk (inner 60 %) density error | ms per simulated s |",
        "|---|---|---|---|",
    ]
    for row in results["bleeding_density"]:
        lines.append(f"| {row['substeps']} | {row['density_error_rel']:+.1%} | {row['bulk_density_error_rel']:+.1%} | {row['ms_per_simulated_s']:.0f} |")
    return "\n".join(lines) + "\n"
