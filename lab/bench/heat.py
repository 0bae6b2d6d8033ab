"""Heat: error against the analytic Gaussian (flat and 3:1 stretched plane) and the l = 1 mode on a sphere of many UV
charts (seams) against cost, per texture size, time step and time-stepping scheme; a Pareto plot."""
import numpy as np

from lab.bench import common
from lab.bench.common import BODY_C, pyplot, save, synced_seconds
from lab.reference import analytic
from lab.reference.meshes import plane_mesh

SIDE_MM = 40.0
SIGMA_MM = 0.5
AMPLITUDE_C = 50.0
SPHERE_RADIUS_MM = 5.0
SPHERE_CONDUCTIVITY_W_MK = 5.0  # the slider's top: the mode decays 10 % per second on a 5 mm sphere


def schemes() -> tuple:
    from sims.heat import cautery

    return tuple(getattr(cautery, "SCHEMES", ("explicit",)))


def gaussian_run(size: int, dt_s: float, seconds: float, scheme: str = "explicit", u_scale: float = 1.0) -> dict:
    """A Gaussian (sigma 0.5 mm, 50 C above body) on a 40 x 40 mm liver plane, no perfusion, no tool, diffused for
    `seconds` and compared with the analytic solution. u_scale < 1 stretches texels 1/u_scale : 1 along x."""
    from sims.heat.cautery import SURFACE_ONLY, Cautery
    from sims.scene import params
    from sims.scene.instruments import InstrumentFields
    from sims.surface.texels import build_surface

    surface = build_surface(plane_mesh(SIDE_MM, SIDE_MM, u_scale=u_scale), size)
    tissue = dict(params.TISSUE_PRESETS["liver"], perfusion_1_s=0.0)
    cautery_params = {**{name: spec.default for name, spec in params.CAUTERY.items()}, **SURFACE_ONLY}
    kwargs = {} if scheme == "explicit" else {"scheme": scheme}
    cautery = Cautery(surface, tissue, cautery_params, InstrumentFields([]), **kwargs)
    r2 = (surface.position_mm[..., :2] ** 2).sum(axis=2)
    cautery.set_temperature(BODY_C + analytic.gaussian_on_plane(r2, AMPLITUDE_C, SIGMA_MM, 0.0, 0.0))
    steps = max(2, int(round(seconds / dt_s)))
    cautery.step(dt_s)  # compiles the kernels; not timed
    wall = synced_seconds(lambda: cautery.step(dt_s), steps - 1)
    alpha = cautery.diffusivity_mm2_s
    exact = analytic.gaussian_on_plane(r2, AMPLITUDE_C, SIGMA_MM, alpha, steps * dt_s)
    mask = surface.mask
    excess = cautery.temperature_c() - BODY_C
    row = {
        "scheme": scheme,
        "texture_size": size,
        "dt_s": dt_s,
        "simulated_s": steps * dt_s,
        "texel_mm": SIDE_MM / size / u_scale,
        "stretch": 1.0 / u_scale,
        "max_error_rel": float(np.abs(excess - exact)[mask].max() / AMPLITUDE_C),
        "ms_per_simulated_s": 1000.0 * wall / ((steps - 1) * dt_s),
        "work_per_step": _work_per_step(cautery, dt_s),
    }
    return row


def sphere_surface(size: int):
    """An icosphere of radius SPHERE_RADIUS_MM unwrapped by xatlas (a few dozen charts: seams everywhere)."""
    import trimesh

    from sims.surface.texels import build_surface

    return build_surface(trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_RADIUS_MM), size)


def sphere_run(size: int, dt_s: float, seconds: float, scheme: str = "explicit") -> dict:
    """T = body + 10 cos(theta) on sphere_surface(size) (k 5 W/(m K), no perfusion) against the analytic decay of the
    l = 1 mode: the amplitude ratio measured and exact, and the relative error of the decay rate."""
    from sims.heat.cautery import SURFACE_ONLY, Cautery
    from sims.scene import params
    from sims.scene.instruments import InstrumentFields

    surface = sphere_surface(size)
    tissue = dict(params.TISSUE_PRESETS["liver"], perfusion_1_s=0.0, conductivity_w_mk=SPHERE_CONDUCTIVITY_W_MK)
    cautery_params = {**{name: spec.default for name, spec in params.CAUTERY.items()}, **SURFACE_ONLY}
    cautery = Cautery(surface, tissue, cautery_params, InstrumentFields([]), scheme=scheme)
    position = surface.position_mm.astype(np.float64)
    cos_theta = position[..., 2] / np.maximum(np.linalg.norm(position, axis=-1), 1e-9)
    weight = np.where(surface.mask, cos_theta * surface.texel_area_mm2, 0.0)

    def amplitude():
        return ((cautery.temperature_c() - BODY_C) * weight).sum() / (cos_theta * weight).sum()

    cautery.set_temperature(BODY_C + 10.0 * cos_theta)
    start = amplitude()
    steps = max(2, int(round(seconds / dt_s)))
    cautery.step(dt_s)  # compiles the kernels; not timed
    wall = synced_seconds(lambda: cautery.step(dt_s), steps - 1)
    measured = amplitude() / start
    exact = analytic.sphere_l1_amplitude(cautery.diffusivity_mm2_s, SPHERE_RADIUS_MM, steps * dt_s)
    return {"scheme": scheme, "texture_size": size, "dt_s": dt_s, "simulated_s": steps * dt_s, "seam_links": cautery.seam_links,
            "amplitude_ratio": float(measured), "exact_ratio": exact, "rate_error_rel": float(np.log(measured) / np.log(exact) - 1.0),
            "ms_per_simulated_s": 1000.0 * wall / ((steps - 1) * dt_s)}


def _work_per_step(cautery, dt_s: float) -> float:
    """Explicit substeps, or solver iterations, spent on the last step."""
    iterations = getattr(cautery, "last_iterations", None)
    return float(iterations if iterations is not None else cautery.substeps(dt_s))


def run(quick: bool) -> dict:
    sizes = (128, 256) if quick else (128, 256, 512, 1024)
    steps = (0.01,) if quick else (0.005, 0.01, 0.02, 0.05)
    seconds = 0.5 if quick else 2.0
    rows = [gaussian_run(size, dt, seconds, scheme) for scheme in schemes() for size in sizes for dt in steps]
    stretched_sizes = sizes[:1] if quick else sizes  # quick: one size (each run compiles a heat model anew)
    stretched = [gaussian_run(size, 0.01, seconds, scheme, u_scale=1 / 3) for scheme in schemes() for size in stretched_sizes]
    sphere_sizes = (128,) if quick else (128, 256, 512)
    sphere = [sphere_run(size, 0.01, seconds, scheme) for scheme in schemes() for size in sphere_sizes]
    return {"sigma_mm": SIGMA_MM, "side_mm": SIDE_MM, "seconds": seconds, "plane": rows, "stretched": stretched,
            "sphere_radius_mm": SPHERE_RADIUS_MM, "sphere": sphere}


def pareto(rows: list[dict]) -> list[dict]:
    """The runs no other run beats in both cost (ms per simulated s) and error (largest, relative), cheapest first."""
    return common.pareto(rows, lambda row: row["ms_per_simulated_s"], lambda row: row["max_error_rel"])


def render(results: dict) -> list[str]:
    lines = [
        "## Heat: error against cost",
        "",
        f"A Gaussian (sigma {results['sigma_mm']} mm, 50 C above body) on a {results['side_mm']:.0f} x {results['side_mm']:.0f} mm "
        f"liver plane, no perfusion, diffused for {results['seconds']} s against the analytic solution",
        "(variance sigma² + 2 alpha t). Error: max |T - T_exact| over the surface relative to the initial 50 C peak.",
        "Cost: wall milliseconds per simulated second (kernels only, device synchronised). Work: explicit substeps or",
        "solver iterations in one step. Pareto front (no other run is both cheaper and more accurate) in bold.",
        "",
        "| scheme | texels | texel (mm) | dt (s) | max error | ms per simulated s | work per step |",
        "|---|---|---|---|---|---|---|",
    ]
    front = {id(row) for row in pareto(results["plane"])}
    for row in results["plane"]:
        bold = "**" if id(row) in front else ""
        lines.append(f"| {bold}{row['scheme']}{bold} | {row['texture_size']}² | {row['texel_mm']:.3f} | {row['dt_s']} | "
                     f"{bold}{row['max_error_rel']:.3%}{bold} | {bold}{row['ms_per_simulated_s']:.0f}{bold} | {row['work_per_step']:.0f} |")
    lines += ["", "Stretched plane: the same Gaussian with texels 3:1 (UV u covers a third of the texture), dt 0.01 s.", "",
              "| scheme | texels | texel along x (mm) | max error | ms per simulated s |", "|---|---|---|---|---|"]
    for row in results["stretched"]:
        lines.append(f"| {row['scheme']} | {row['texture_size']}² | {row['texel_mm']:.3f} | {row['max_error_rel']:.3%} | {row['ms_per_simulated_s']:.0f} |")
    if results.get("sphere"):
        lines += ["", f"Sphere (UV seams): the l = 1 mode cos(theta) on an xatlas-unwrapped icosphere of radius {results['sphere_radius_mm']:g} mm",
                  f"(k = {SPHERE_CONDUCTIVITY_W_MK:g} W/(m K)), dt 0.01 s for {results['seconds']} s, against the analytic decay rate",
                  "2 alpha / R² (heat crosses the seams through sims.surface.seams links).", "",
                  "| scheme | texels | seam links | decay rate error | ms per simulated s |", "|---|---|---|---|---|"]
        for row in results["sphere"]:
            lines.append(f"| {row['scheme']} | {row['texture_size']}² | {row['seam_links']} | {row['rate_error_rel']:+.3%} | "
                         f"{row['ms_per_simulated_s']:.0f} |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    markers = {"explicit": "o", "implicit": "s"}
    for scheme in sorted({row["scheme"] for row in results["plane"]}):
        rows = [row for row in results["plane"] if row["scheme"] == scheme]
        ax.scatter([r["ms_per_simulated_s"] for r in rows], [r["max_error_rel"] * 100 for r in rows],
                   marker=markers.get(scheme, "^"), label=scheme, alpha=0.8)
        for r in rows:
            ax.annotate(f"{r['texture_size']}, {r['dt_s']:g}s", (r["ms_per_simulated_s"], r["max_error_rel"] * 100),
                        fontsize=6, xytext=(3, 2), textcoords="offset points")
    front = pareto(results["plane"])
    ax.plot([r["ms_per_simulated_s"] for r in front], [r["max_error_rel"] * 100 for r in front], "k--", lw=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("cost: wall ms per simulated second")
    ax.set_ylabel("max error, % of the 50 C peak")
    ax.set_title("Heat: Gaussian on a plane, error against cost (label: texels, dt)")
    ax.legend()
    return [save(fig, out_dir, "heat_pareto.png")]
