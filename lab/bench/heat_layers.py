"""Heat in depth: the layered model against the 3D axisymmetric reference (lab.bench.heat_reference), its cost, and
what the sleeping tiles save.

The case is issue 10's: a ball electrode (radius 1.5 mm, 250 C) pressed 0.2 mm into a flat liver plane for 2 s, then
lifted; both models with the same contact law (h w(d), in series with the top half cell), no loss to air, 62 s.
"""
import time

import numpy as np

from lab.bench import common
from lab.bench.common import build_plane, pyplot, save
from sims.surface.sleep_tiles import TILE

SAMPLE_TIMES_S = (2.0, 7.0, 12.0, 32.0, 62.0)


def _ball(tip_c: float, radius_mm: float, press_mm: float, energized: bool = True, centre=(0.0, 0.0)):
    from sims.scene.instruments import Instrument

    return Instrument.from_config({
        "name": "ball", "shape": {"type": "ball", "radius_mm": radius_mm, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
        "position_mm": [centre[0], centre[1], radius_mm - press_mm], "direction": [0, 0, -1], "roll_deg": 0.0,
        "energized": energized, "tip_temperature_c": tip_c, "path": []})


def _cautery(size: int, side_mm: float, tools: list, **cautery_changes):
    from sims.heat.cautery import Cautery
    from sims.scene import params
    from sims.scene.instruments import InstrumentFields

    surface = build_plane(side_mm, size)
    values = {name: spec.default for name, spec in params.CAUTERY.items()}
    values.update(bottom="body", surface_loss_w_m2k=0.0)
    values.update(cautery_changes)
    fields = InstrumentFields(tools)
    return surface, Cautery(surface, dict(params.TISSUE_PRESETS["liver"]), values, fields), fields


def ball_contact_layered(size: int = 128, side_mm: float = 12.0, tip_c: float = 250.0, contact_s: float = 2.0,
                         end_s: float = 62.0, sample_times_s=SAMPLE_TIMES_S, dt_s: float = 0.01, radius_mm: float = 1.5,
                         press_mm: float = 0.2, **cautery_changes) -> dict:
    """The reference's contact on the layered model (sims.heat.cautery) on a side_mm plane of size^2 texels; cautery_changes
    override sims.scene.params CAUTERY defaults (layers, depth_mm, sleep_tolerance_c, ...). Returns samples (t_s,
    surface_center_c at the texel next to the axis, coagulated_area_mm2, coagulation_depth_mm (largest),
    coagulated_volume_mm3), ms_per_step (stepping only), mean awake share of the tiles, texel_mm, top_layer_mm."""
    tool = _ball(tip_c, radius_mm, press_mm)
    surface, cautery, fields = _cautery(size, side_mm, [tool], **cautery_changes)
    centre = np.unravel_index(np.argmin((surface.position_mm[..., :2] ** 2).sum(axis=2)), surface.mask.shape)
    cautery.step(dt_s)  # compiles the kernels; the run starts again from rest
    cautery.reset()
    samples, t, steps, wall, awake = [], 0.0, 0, 0.0, 0.0
    marks = sorted({*sample_times_s, contact_s, end_s})
    for mark in marks:
        count = int(round((mark - t) / dt_s))
        start = time.perf_counter()
        for _ in range(count):
            cautery.step(dt_s)
            awake += cautery.awake_fraction()
        cautery.temperature_c()  # waits for the device
        wall += time.perf_counter() - start
        steps += count
        t = mark
        if abs(t - contact_s) < 1e-9:
            tool.energized_by_hand = False
            fields.set_time(t)
        if any(abs(t - s) < 1e-9 for s in sample_times_s):
            metrics = cautery.metrics()
            samples.append({"t_s": t, "surface_center_c": float(cautery.temperature_c()[centre]),
                            **{key: metrics[key] for key in ("coagulated_area_mm2", "coagulation_depth_mm", "coagulated_volume_mm3")}})
    return {"size": size, "side_mm": side_mm, "texel_mm": side_mm / size, "layers": cautery.layer_count,
            "depth_mm": float(cautery.faces_mm[-1]), "top_layer_mm": cautery.top_layer_mm,
            "sleep_tolerance_c": cautery.cautery["sleep_tolerance_c"], "tip_c": tip_c, "contact_s": contact_s,
            "samples": samples, "steps": steps, "ms_per_step": 1e3 * wall / max(steps, 1), "awake_share": awake / max(steps, 1)}


def errors(run: dict, reference: dict) -> dict:
    """Against the reference at the same sample times: largest |surface T - reference| after lift-off (C), and the
    relative errors of the final coagulated area and depth."""
    ref = {s["t_s"]: s for s in reference["samples"]}
    after = [s for s in run["samples"] if s["t_s"] > run["contact_s"] + 1e-9 and s["t_s"] in ref]
    last, last_ref = run["samples"][-1], ref[run["samples"][-1]["t_s"]]
    return {
        "surface_c": max((abs(s["surface_center_c"] - ref[s["t_s"]]["surface_center_c"]) for s in after), default=0.0),
        "area": last["coagulated_area_mm2"] / last_ref["coagulated_area_mm2"] - 1.0,
        "depth": last["coagulation_depth_mm"] / last_ref["coagulation_depth_mm"] - 1.0,
    }


def pareto(rows: list[dict]) -> list[dict]:
    """The runs no other run beats in both cost (ms_per_step) and error (worst of the area and depth errors)."""
    return common.pareto(rows, lambda row: row["ms_per_step"], lambda row: max(abs(row["error"]["area"]), abs(row["error"]["depth"])))


def depth_against_contact(tips_c=(150.0, 250.0, 400.0), contacts_s=(0.5, 1.0, 2.0, 4.0), cool_s: float = 10.0,
                          size: int = 128) -> list[dict]:
    """Final coagulation depth and area (after cool_s of cooling) of the ball held for each contact time."""
    rows = []
    for tip in tips_c:
        for contact in contacts_s:
            run = ball_contact_layered(size=size, tip_c=tip, contact_s=contact, end_s=contact + cool_s,
                                       sample_times_s=(contact + cool_s,))
            last = run["samples"][-1]
            rows.append({"tip_c": tip, "contact_s": contact, "size": size, "depth_mm": last["coagulation_depth_mm"],
                         "area_mm2": last["coagulated_area_mm2"]})
    return rows


def cost_against_activity(sizes=(256, 512, 1024), side_mm: float = 24.0, steps: int = 100) -> list[dict]:
    """ms per 0.01 s step on a side_mm plane: idle (the ball parked off, nothing warm) and burning (the ball pressed
    and energized for 1 s first), per texture size."""
    rows = []
    for size in sizes:
        row = {"size": size}
        for state in ("idle", "burning"):
            tool = _ball(250.0, 1.5, 0.2, energized=state == "burning")
            surface, cautery, fields = _cautery(size, side_mm, [tool])
            for _ in range(100 if state == "burning" else 2):
                cautery.step(0.01)
            cautery.temperature_c()
            start = time.perf_counter()
            for _ in range(steps):
                cautery.step(0.01)
            cautery.temperature_c()
            row[f"{state}_ms"] = 1e3 * (time.perf_counter() - start) / steps
            row[f"{state}_awake"] = cautery.awake_fraction()
        row["ratio"] = row["burning_ms"] / max(row["idle_ms"], 1e-9)
        rows.append(row)
    return rows


def run(quick: bool) -> dict:
    from lab.bench.heat_reference import ball_contact_reference

    end = 7.0 if quick else 62.0  # quick: one sample after lift-off
    times = tuple(t for t in SAMPLE_TIMES_S if t <= end)
    reference = ball_contact_reference(grid_mm=0.05 if quick else 0.025, end_s=end, sample_times_s=times)
    reference.pop("history")
    layer_counts = (4, 8) if quick else (2, 4, 6, 8, 12, 16)
    sizes = (64, 128) if quick else (64, 128, 256)
    rows = []
    for layers in layer_counts:
        rows.append(ball_contact_layered(size=128, end_s=end, sample_times_s=times, layers=layers))
    for size in sizes:
        if size != 128:
            rows.append(ball_contact_layered(size=size, end_s=end, sample_times_s=times))
    tolerances = (0.0, 0.05, 0.5) if quick else (0.0, 0.01, 0.05, 0.2, 0.5, 1.0)
    sleeping = [ball_contact_layered(size=128, side_mm=24.0, end_s=end, sample_times_s=times, sleep_tolerance_c=tol)
                for tol in tolerances]
    for row in rows + sleeping:
        row["error"] = errors(row, reference)
    return {
        "reference": reference,
        "runs": rows,
        "pareto": [(r["layers"], r["size"]) for r in pareto(rows)],
        "sleeping": sleeping,
        "depth_against_contact": depth_against_contact(tips_c=(250.0,), contacts_s=(1.0, 2.0), size=64) if quick else depth_against_contact(),
        "cost": cost_against_activity(sizes=(256,) if quick else (256, 512, 1024), steps=20 if quick else 100),
    }


def render(results: dict) -> list[str]:
    from sims.scene import params

    ref = results["reference"]
    default_layers = int(params.CAUTERY["layers"].default)
    default = next(r for r in results["runs"] if r["layers"] == default_layers and r["size"] == 128)
    lines = ["## Heat in depth: the layered model against the 3D reference", "",
             f"Issue 10's contact (ball 1.5 mm at 250 C pressed 0.2 mm for 2 s, then lifted) on a 12 mm liver plane. The 3D "
             f"reference: axisymmetric finite volumes, {ref['model']['grid_mm']} mm grid (its convergence: the heat reference "
             "section). The layered model at its defaults: "
             f"{default_layers} layers to {default['depth_mm']:g} mm (top layer {default['top_layer_mm']:.3f} mm), "
             f"{default['texel_mm']:.3f} mm texels.", "",
             "| t (s) | surface T, 3D (C) | layered | coagulated area, 3D (mm²) | layered | depth, 3D (mm) | layered |",
             "|---|---|---|---|---|---|---|"]
    for a, b in zip(ref["samples"], default["samples"]):
        lines.append(f"| {a['t_s']:g} | {a['surface_center_c']:.1f} | {b['surface_center_c']:.1f} | {a['coagulated_area_mm2']:.2f} | "
                     f"{b['coagulated_area_mm2']:.2f} | {a['coagulation_depth_mm']:.3f} | {b['coagulation_depth_mm']:.3f} |")
    pareto_set = {tuple(p) for p in results["pareto"]}
    lines += ["", "Error against cost (errors: largest |ΔT| at the surface after lift-off; final area and depth, relative; "
              "cost: ms per 0.01 s step on the 12 mm plane, every tile awake; * on the Pareto front):", "",
              "| layers | texels | texel (mm) | top layer (mm) | ΔT after lift-off (C) | area | depth | ms/step | |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in results["runs"]:
        e = r["error"]
        lines.append(f"| {r['layers']} | {r['size']}² | {r['texel_mm']:.3f} | {r['top_layer_mm']:.3f} | {e['surface_c']:.2f} | "
                     f"{100 * e['area']:+.1f} % | {100 * e['depth']:+.1f} % | {r['ms_per_step']:.2f} | "
                     f"{'*' if (r['layers'], r['size']) in pareto_set else ''} |")
    lines += ["", f"Sleeping tiles: the same contact on a 24 mm plane (128², tiles of {TILE}² texels), by sleep tolerance:", "",
              "| tolerance (C) | tiles awake (mean) | ms/step | ΔT after lift-off (C) | area | depth |", "|---|---|---|---|---|---|"]
    for r in results["sleeping"]:
        e = r["error"]
        lines.append(f"| {r['sleep_tolerance_c']:g} | {100 * r['awake_share']:.0f} % | {r['ms_per_step']:.2f} | {e['surface_c']:.2f} | "
                     f"{100 * e['area']:+.1f} % | {100 * e['depth']:+.1f} % |")
    lines += ["", f"Burn depth against contact time (final depth after 10 s of cooling, mm; area in mm²; "
                  f"{results['depth_against_contact'][0]['size']}² texels):", "",
              "| tip (C) | " + " | ".join(f"{c:g} s" for c in sorted({r['contact_s'] for r in results['depth_against_contact']})) + " |",
              "|---|" + "---|" * len({r['contact_s'] for r in results['depth_against_contact']})]
    for tip in sorted({r["tip_c"] for r in results["depth_against_contact"]}):
        cells = [f"{r['depth_mm']:.2f} ({r['area_mm2']:.1f})" for r in results["depth_against_contact"] if r["tip_c"] == tip]
        lines.append(f"| {tip:g} | " + " | ".join(cells) + " |")
    lines += ["", "Cost against activity: ms per 0.01 s step on a 24 mm plane, idle (ball parked, off) and burning (the ball "
              "pressed in for 1 s):", "", "| texels | idle (ms) | tiles awake | burning (ms) | tiles awake | burning / idle |",
              "|---|---|---|---|---|---|"]
    for r in results["cost"]:
        lines.append(f"| {r['size']}² | {r['idle_ms']:.3f} | {100 * r['idle_awake']:.0f} % | {r['burning_ms']:.2f} | "
                     f"{100 * r['burning_awake']:.1f} % | {r['ratio']:.0f} |")
    return lines


def plot(results: dict, out_dir) -> list[str]:
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.6, 4.0))
    ref = results["reference"]
    t_ref = [s["t_s"] for s in ref["samples"]]
    left.plot(t_ref, [s["coagulated_area_mm2"] for s in ref["samples"]], "k-o", label="3D reference: area (mm²)")
    left.plot(t_ref, [10 * s["coagulation_depth_mm"] for s in ref["samples"]], "k--s", label="3D reference: depth x10 (mm)")
    for r in results["runs"]:
        if r["size"] != 128:
            continue
        t = [s["t_s"] for s in r["samples"]]
        line, = left.plot(t, [s["coagulated_area_mm2"] for s in r["samples"]], "-", alpha=0.7, label=f"{r['layers']} layers")
        left.plot(t, [10 * s["coagulation_depth_mm"] for s in r["samples"]], "--", color=line.get_color(), alpha=0.7)
    left.set_xlabel("t (s)")
    left.set_title("Burn after a 2 s contact at 250 C")
    left.legend(fontsize=7)
    front = {tuple(p) for p in results["pareto"]}
    for r in results["runs"]:
        worst = 100 * max(abs(r["error"]["area"]), abs(r["error"]["depth"]))
        right.scatter(r["ms_per_step"], worst, color="tab:red" if (r["layers"], r["size"]) in front else "tab:blue")
        right.annotate(f"{r['layers']}L {r['size']}²", (r["ms_per_step"], worst), fontsize=7)
    right.set_xscale("log")
    right.set_xlabel("ms per 0.01 s step")
    right.set_ylabel("worst of area and depth error (%)")
    right.set_title("Error against cost (red: Pareto front)")
    files = [save(fig, out_dir, "heat_layers.png")]
    fig, axis = plt.subplots(figsize=(5.0, 3.6))
    rows = results["depth_against_contact"]
    for tip in sorted({r["tip_c"] for r in rows}):
        mine = [r for r in rows if r["tip_c"] == tip]
        axis.plot([r["contact_s"] for r in mine], [r["depth_mm"] for r in mine], "-o", label=f"{tip:g} C")
    axis.set_xlabel("contact time (s)")
    axis.set_ylabel("coagulation depth (mm)")
    axis.set_title("Ball 1.5 mm pressed 0.2 mm")
    axis.legend()
    files.append(save(fig, out_dir, "burn_depth.png"))
    return files
