"""Damage: when does Omega reach 1, against the analytic Arrhenius integral, for time steps 1 ms to 50 ms."""

from lab.bench.common import BODY_C, build_plane, pyplot, save
from lab.reference import analytic

TIME_STEPS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05)


def _cautery(tip_c: float | None, start_c: float):
    """A 4 x 4 mm liver plane of one insulated 1 mm layer at start_c with no perfusion; with tip_c, a huge energized ball
    touches every texel (the layer then relaxes toward tip_c at Cautery.contact_rate_1_s)."""
    from sims.heat.cautery import SURFACE_ONLY, Cautery
    from sims.scene import params
    from sims.scene.instruments import Instrument, InstrumentFields

    surface = build_plane(4.0, 16)
    tissue = dict(params.TISSUE_PRESETS["liver"], perfusion_1_s=0.0, initial_temperature_c=start_c)
    tools = []
    if tip_c is not None:
        tools.append(Instrument.from_config({
            "name": "plate", "shape": {"type": "ball", "radius_mm": 100.0, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
            "position_mm": [0.0, 0.0, -99.0], "direction": [0, 0, -1], "roll_deg": 0.0, "energized": True,
            "tip_temperature_c": tip_c, "path": [],
        }))
    layer = {**{name: spec.default for name, spec in params.CAUTERY.items()}, **SURFACE_ONLY, "layers": 1, "depth_mm": 1.0}
    cautery = Cautery(surface, tissue, layer, InstrumentFields(tools))
    return cautery, tissue


def time_to_omega_one(tip_c: float | None, start_c: float, dt_s: float) -> float:
    """Simulated seconds until Omega at the centre texel reaches 1 (linear interpolation between steps)."""
    cautery, _ = _cautery(tip_c, start_c)
    previous, t = 0.0, 0.0
    while True:
        cautery.step(dt_s)
        t += dt_s
        omega = float(cautery.omega_depth[8 * 16 + 8, 0])
        if omega >= 1.0:
            return t - dt_s + dt_s * (1.0 - previous) / (omega - previous)
        previous = omega
        if t > 100.0:
            raise RuntimeError("Omega did not reach 1 within 100 s")


def exact_time(tip_c: float | None, start_c: float) -> float:
    cautery, tissue = _cautery(tip_c, start_c)
    ln_a, ea, threshold = tissue["arrhenius_ln_a"], tissue["activation_energy_j_mol"], tissue["damage_threshold_c"]
    if tip_c is None:
        return analytic.arrhenius_time_to_omega(1.0, start_c, ln_a, ea, threshold)
    return analytic.arrhenius_time_under_relaxation(1.0, start_c, tip_c, cautery.contact_rate_1_s, ln_a, ea, threshold)


CASES = (
    {"name": "constant 60 C", "tip_c": None, "start_c": 60.0},
    {"name": "contact heating 37 -> 75 C", "tip_c": 75.0, "start_c": BODY_C},
    {"name": "contact heating 37 -> 250 C", "tip_c": 250.0, "start_c": BODY_C},
)


def run(quick: bool) -> dict:
    steps = TIME_STEPS_S[3:] if quick else TIME_STEPS_S
    cases = []
    for case in CASES:
        exact = exact_time(case["tip_c"], case["start_c"])
        rows = []
        for dt in steps:
            measured = time_to_omega_one(case["tip_c"], case["start_c"], dt)
            rows.append({"dt_s": dt, "time_s": measured, "error_s": measured - exact, "error_rel": measured / exact - 1.0})
        cases.append({"name": case["name"], "exact_time_s": exact, "runs": rows})
    return {"cases": cases}


def render(results: dict) -> list[str]:
    lines = [
        "## Damage: Omega timing against time step",
        "",
        "Time until the Arrhenius integral Omega reaches 1 (liver, A = 7.39e39 1/s, Ea = 2.577e5 J/mol, counted above 43 C) on a",
        "uniform plane, against the exact integral (adaptive quadrature of the analytic temperature history). Contact heating: a tool",
        "touching every texel relaxes T exponentially toward the tip temperature (h = 5000 W/(m² K), 1 mm layer: time",
        "constant 0.76 s). The crossing is interpolated linearly between steps, so the error is that of the integration.",
        "",
        "| case | exact (s) | " + " | ".join(f"dt {row['dt_s']:g} s" for row in results["cases"][0]["runs"]) + " |",
        "|---|---|" + "---|" * len(results["cases"][0]["runs"]),
    ]
    for case in results["cases"]:
        cells = " | ".join(f"{row['error_rel'] * 100:+.2g} %" for row in case["runs"])
        lines.append(f"| {case['name']} | {case['exact_time_s']:.4g} | {cells} |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.6, 3.8))
    for case in results["cases"]:
        dts = [row["dt_s"] for row in case["runs"]]
        errors = [max(abs(row["error_rel"]) * 100, 1e-6) for row in case["runs"]]
        ax.loglog(dts, errors, "o-", label=f"{case['name']} (exact {case['exact_time_s']:.3g} s)")
    ax.set_xticks(dts, [f"{dt:g}" for dt in dts], minor=False)
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xlabel("time step (s)")
    ax.set_ylabel("|time to Omega = 1| error, %")
    ax.set_title("Damage: Arrhenius timing error against time step")
    ax.legend(fontsize=7)
    return [save(fig, out_dir, "damage_timing.png")]
