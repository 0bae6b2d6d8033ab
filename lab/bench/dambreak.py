"""Dam break: our blood SPH (sims.blood.particles.Bleeding, Clavet double density relaxation in texture space) against
Martin & Moyce 1952, with the error next to the cost.

Set-up (all choices here, none tuned to the data):
- A flat vertical plane (x horizontal, z up, UV = (x, z) / (texture side)), so gravity (0, 0, -9810) mm/s^2
  lies fully in it and texture space is an ordinary 2D domain. The plane covers a 10a x 2.5a rectangle of
  the square texture (texels of h/2, edges on texel borders); `Bleeding(walls=True)` keeps the particles
  on it: free-slip walls at the texture's left and bottom edges and at the chart's right and top borders.
- Column a = 25 mm wide and 2a high (hexagonal lattice at the particle spacing), its left side on the
  left wall. It first settles behind a dam (the same set-up on a chart 1a wide, velocities damped by
  inertia 0.95 per substep) so the release starts from hydrostatic rest, not from the lattice: 40 ms,
  then the particles above the lattice's top row are removed (the relaxed fluid is less dense than the
  lattice, so the column rises by settle_rise_a, 3-7 % of its height; left in, the taller column would
  run faster), then 20 ms more. Its height is reported (column_height_a, top particle + half a row).
  Released at t = 0.
- Water-like: no film drag (blood_viscosity_mpa_s = 0, so the Nusselt drag 3 nu / e^2 is exactly 0), no
  Clavet viscosity (sigma = beta = 0), no clotting, no pinning, speed clamp 1e5 mm/s.
- Interaction radius h = 3 x spacing. Stiffness from a nominal sound speed c = 2.2 m/s (2.2 x the speed
  of a fall from the column top, sqrt(2 g 2a) = 0.99 m/s; the front runs at about 0.9 m/s): for a small
  density gradient the relaxation accelerates a particle by -(h rho0 / 4) grad P, so with
  P = k (rho - rho0), c^2 = k h rho0^2 / 4 and k = 4 c^2 / (h rho0^2) (rho0 the lattice density sum);
  the near stiffness equals k. The measured hydrostatic compression of
  the settled column (bottom against top, compression_rel) is reported. Fixing c instead of k keeps the
  Mach number the same at every resolution; k then grows as 1/h.
- Known bias of the model: Clavet's pressure is negative where rho < rho0, which holds a free surface
  together (surface tension). Its strength grows with k h^2 (so as c^2 h), so at coarse spacings the
  fluid is cohesive (rounded front, fluid clinging to walls), and a stiffer fluid is slower, not faster.
  Refining at a fixed c weakens it and the front moves ahead of Martin & Moyce, toward the peer's.
- Known artefact of the clamp walls: they have no boundary particles, so fluid next to a wall misses half
  its neighbours and is in tension; at the finest spacing a cavity opens along the left wall near T = 2 and
  its collapse throws a thin jet up the wall (it does not reach the front).
- Front: particle x (mm from the left wall, over a) of rank floor(0.002 N) from the largest, the largest x
  of all but the 0.2 % most advanced particles (drops thrown ahead do not count); every frame (1 ms).
  T = t sqrt(2 g / a), Z = front / a, as Martin & Moyce.
- Cost: wall time of the release run only (not the settling, the surface, or the kernel compile); a
  particle-step is one particle through one substep (a full relaxation step); `substeps` per 1 ms frame.

The shallow-water (Ritter) front Z = 1 + 2T, an inviscid upper bound that Martin & Moyce's front stays well
behind, is drawn for scale.
"""
import math
import time

import numpy as np

from lab.bench.common import json_finite
from lab.reference.dambreak import FRONT_QUANTILE, MARTIN_MOYCE, front_error, front_position, martin_moyce_front

A_MM = 25.0                      # column width a
G_MM_S2 = 9810.0
TANK_LENGTH_A, TANK_HEIGHT_A = 10.0, 2.5
T_END = 5.5                      # last T simulated (Martin & Moyce's last point: 5.316)
FRAME_S = 1.0e-3                 # one Bleeding.step; the front is sampled after each
RADIUS_RATIO = 3.0               # interaction radius / particle spacing
SOUND_SPEED_MM_S = 2200.0
SETTLE_S, SETTLE_INERTIA = 0.06, 0.95
SNAPSHOT_T = (1.0, 2.0, 3.5, 5.0)
SNAPSHOT_POINTS = 1500

QUICK_RUNS = ((1.0, 2), (1.0, 4), (0.7, 4))
FULL_RUNS = ((1.0, 2), (1.0, 4), (1.0, 8), (0.7, 4), (0.5, 4), (0.5, 8), (0.35, 8))
FULL_SOUND_SPEEDS = (1500.0, 3000.0)   # extra runs at spacing 0.5 mm, 8 substeps


def time_scale_1_s() -> float:
    """sqrt(2 g / a): T = t times this."""
    return math.sqrt(2.0 * G_MM_S2 / A_MM)


def tank_surface(texel_mm: float, chart_length_a: float = TANK_LENGTH_A):
    """Vertical plane chart chart_length_a x TANK_HEIGHT_A (in a) in the bottom-left corner of a square texture.

    Returns (surface, texel_mm, size): texels are a / ceil(a / texel_mm) wide so a, the chart's length and its
    height are whole numbers of texels; the chart's left and bottom edges are the texture's (grid x = 0,
    grid y = size), its right and top edges are mask borders.
    """
    import trimesh

    from sims.surface.texels import build_surface

    per_a = int(math.ceil(A_MM / texel_mm - 1e-9))
    texel = A_MM / per_a
    size = 2 ** int(math.ceil(math.log2(max(TANK_LENGTH_A, TANK_HEIGHT_A) * per_a)))
    length, height = chart_length_a * A_MM, math.ceil(TANK_HEIGHT_A * per_a) * texel
    n = 9
    xs, zs = np.meshgrid(np.linspace(0.0, length, n), np.linspace(0.0, height, n))
    vertices = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)
    uv = np.stack([xs.ravel(), zs.ravel()], axis=1) / (size * texel)
    faces = [[j * n + i, j * n + i + 1, j * n + i + n + 1] for j in range(n - 1) for i in range(n - 1)]
    faces += [[j * n + i, j * n + i + n + 1, j * n + i + n] for j in range(n - 1) for i in range(n - 1)]
    mesh = trimesh.Trimesh(vertices, np.array(faces), visual=trimesh.visual.TextureVisuals(uv=uv), process=False)
    return build_surface(mesh, size), texel, size


def column_positions(spacing_mm: float) -> np.ndarray:
    """Hexagonal lattice (N, 2) of (x, z) in mm filling the column [0, a] x [0, 2a]."""
    row_height = spacing_mm * math.sqrt(3.0) / 2.0
    rows = int(round(2.0 * A_MM / row_height))
    points = []
    for j in range(rows):
        offset = 0.25 * spacing_mm if j % 2 == 0 else 0.75 * spacing_mm
        count = int(math.floor((A_MM - offset) / spacing_mm)) + 1
        points += [(offset + i * spacing_mm, (j + 0.5) * row_height) for i in range(count) if offset + i * spacing_mm < A_MM]
    return np.asarray(points, np.float64)


def fluid_params(spacing_mm: float, substeps: int, sound_speed_mm_s: float = SOUND_SPEED_MM_S) -> dict:
    """Bleeding parameters of the dam break (see the module docstring)."""
    from sims.blood.particles import lattice_density
    from sims.scene import params

    radius = RADIUS_RATIO * spacing_mm
    rho0 = lattice_density(spacing_mm, radius)
    stiffness = 4.0 * sound_speed_mm_s**2 / (radius * rho0**2)
    values = {name: spec.default for name, spec in params.BLEEDING.items()}
    values.update(
        particle_spacing_mm=spacing_mm, interaction_radius_mm=radius, rest_density=1.0,
        stiffness_mm_s2=stiffness, near_stiffness_mm_s2=stiffness,
        viscosity_sigma_1_s=0.0, viscosity_beta_s_mm=0.0, blood_viscosity_mpa_s=0.0,
        inertia=1.0, max_speed_mm_s=1.0e5, pinning_density=0.0, clotting_rate_1_s=0.0,
        lifetime_s=1.0e4, substeps=int(substeps),
    )
    return values


def _grid(xz_mm: np.ndarray, texel: float, size: int) -> np.ndarray:
    return np.stack([xz_mm[:, 0] / texel, size - xz_mm[:, 1] / texel], axis=1)


def _xz_a(bleeding, texel: float, size: int) -> np.ndarray:
    pos = bleeding.pos.to_numpy()[: bleeding.count].astype(np.float64)
    return np.stack([pos[:, 0] * texel, (size - pos[:, 1]) * texel], axis=1) / A_MM


_RIGS = {}  # spacing -> (dam Bleeding, tank Bleeding, texel, size): runs at one spacing share them (one compile each)


def _rig(spacing_mm: float, values: dict):
    """The settling (chart 1a long: a dam at x = a) and release (whole tank) pools for this spacing, with `values`."""
    from sims.blood.particles import Bleeding

    if spacing_mm not in _RIGS:
        count = len(column_positions(spacing_mm))
        dam, texel, size = tank_surface(values["interaction_radius_mm"] / 2.0, chart_length_a=1.0)
        tank, _, _ = tank_surface(values["interaction_radius_mm"] / 2.0)
        gravity = (0.0, 0.0, -G_MM_S2)
        _RIGS[spacing_mm] = (Bleeding(dam, values, gravity, count, walls=True), Bleeding(tank, values, gravity, count, walls=True), texel, size)
    dam, tank, texel, size = _RIGS[spacing_mm]
    dam.params, tank.params = dict(values, inertia=SETTLE_INERTIA), dict(values)  # read by every step
    return dam, tank, texel, size


def _settle(bleeding, texel: float, size: int, spacing_mm: float, settle_s: float):
    """The column behind the dam, damped to rest for 2/3 of settle_s, cut back to the lattice's height (the fluid's
    rest density is below the lattice's, so it rises) and damped for the rest. Returns (grid positions, column
    height / a (top particle + half a lattice row), rise before the cut / a, compression, rms speed / sqrt(g a))."""
    lattice = column_positions(spacing_mm)
    top = lattice[:, 1].max() / A_MM                  # the lattice's highest row: 2a less half a row
    bleeding.place(_grid(lattice, texel, size))
    frames = int(round(settle_s / FRAME_S))
    for _ in range(2 * frames // 3):
        bleeding.step(FRAME_S)
    xz_a = _xz_a(bleeding, texel, size)
    rise = float(np.quantile(xz_a[:, 1], 0.995)) - top
    bleeding.place(bleeding.pos.to_numpy()[: bleeding.count][xz_a[:, 1] <= top])
    for _ in range(frames - 2 * frames // 3):
        bleeding.step(FRAME_S)
    xz_a = _xz_a(bleeding, texel, size)
    height = float(np.quantile(xz_a[:, 1], 0.995)) + 2.0 - top
    rho = bleeding.density.to_numpy()[: bleeding.count, 0].astype(np.float64)
    inner = (xz_a[:, 0] > 0.2) & (xz_a[:, 0] < 0.8)
    low, high = inner & (xz_a[:, 1] > 0.15) & (xz_a[:, 1] < 0.5), inner & (xz_a[:, 1] > height - 0.5) & (xz_a[:, 1] < height - 0.15)
    compression = float(rho[low].mean() / rho[high].mean() - 1.0) if low.any() and high.any() else math.nan
    vel = bleeding.vel.to_numpy()[: bleeding.count].astype(np.float64) * texel
    rms = float(np.sqrt((vel**2).sum(axis=1).mean()) / math.sqrt(G_MM_S2 * A_MM))
    return bleeding.pos.to_numpy()[: bleeding.count].copy(), height, rise, compression, rms


def simulate(spacing_mm: float, substeps: int, sound_speed_mm_s: float = SOUND_SPEED_MM_S, t_end: float = T_END,
             settle_s: float = SETTLE_S, snapshots=()) -> dict:
    """One dam break: settle the column, release it, follow the front until T = t_end (or the far wall).

    Returns spacing_mm, substeps, sound_speed_mm_s, stiffness_mm_s2, interaction_radius_mm, particles,
    column_height_a, settle_rise_a, compression_rel, settle_rms_speed (over sqrt(g a)), T and Z (front history, T = 0 first),
    error (front_error), wall_s, ms_per_simulated_s, particle_steps_per_s, setup_s (surfaces, compile,
    settling), snapshots ([{T, x, z}] in a at the first frames past the requested T, at most 1500 particles).
    """
    setup_start = time.perf_counter()
    values = fluid_params(spacing_mm, substeps, sound_speed_mm_s)
    dam, bleeding, texel, size = _rig(spacing_mm, values)
    if settle_s > 0:
        grid, height, rise, compression, rms = _settle(dam, texel, size, spacing_mm, settle_s)
    else:
        grid, height, rise, compression, rms = _grid(column_positions(spacing_mm), texel, size), 2.0, 0.0, math.nan, 0.0
    bleeding.place(grid)
    bleeding.step(FRAME_S)  # compiles the kernels (first run at this spacing); then back to the start
    bleeding.place(grid)
    setup_s = time.perf_counter() - setup_start
    count = len(grid)
    scale = time_scale_1_s()
    times, fronts, shots = [0.0], [front_position(_xz_a(bleeding, texel, size)[:, 0])], []
    frames, wall = 0, 0.0
    while times[-1] < t_end and fronts[-1] < TANK_LENGTH_A - 0.5:
        start = time.perf_counter()
        bleeding.step(FRAME_S)
        wall += time.perf_counter() - start
        frames += 1
        xz_a = _xz_a(bleeding, texel, size)
        times.append(frames * FRAME_S * scale)
        fronts.append(front_position(xz_a[:, 0]))
        if len(shots) < len(snapshots) and times[-1] >= snapshots[len(shots)]:
            keep = np.linspace(0, len(xz_a) - 1, min(SNAPSHOT_POINTS, len(xz_a))).astype(int)
            shots.append({"T": times[-1], "x": np.round(xz_a[keep, 0], 3).tolist(), "z": np.round(xz_a[keep, 1], 3).tolist()})
    if bleeding.count != count or not np.isfinite(bleeding.pos.to_numpy()[:count]).all():
        raise RuntimeError(f"dam break at spacing {spacing_mm} mm lost particles or became non-finite")
    simulated = frames * FRAME_S
    return {
        "spacing_mm": spacing_mm,
        "substeps": int(substeps),
        "sound_speed_mm_s": sound_speed_mm_s,
        "stiffness_mm_s2": values["stiffness_mm_s2"],
        "interaction_radius_mm": values["interaction_radius_mm"],
        "particles": count,
        "column_height_a": height,
        "settle_rise_a": rise,
        "compression_rel": compression,
        "settle_rms_speed": rms,
        "T": [round(v, 5) for v in times],
        "Z": [round(v, 5) for v in fronts],
        "error": front_error(times, fronts),
        "wall_s": wall,
        "ms_per_simulated_s": 1000.0 * wall / max(simulated, 1e-12),
        "particle_steps_per_s": count * substeps * frames / max(wall, 1e-12),
        "setup_s": setup_s,
        "snapshots": shots,
    }


def run(quick: bool) -> dict:
    """Dam breaks at a few spacings and substep counts (and, in full, sound speeds): JSON-able results."""
    plan = [(spacing, substeps, SOUND_SPEED_MM_S) for spacing, substeps in (QUICK_RUNS if quick else FULL_RUNS)]
    if not quick:
        plan += [(0.5, 8, c) for c in FULL_SOUND_SPEEDS]
    finest = min(plan, key=lambda item: (item[0], -item[1]))
    runs = []
    for spacing, substeps, speed in plan:
        wanted = SNAPSHOT_T if (spacing, substeps, speed) == finest else ()
        runs.append(json_finite(simulate(spacing, substeps, sound_speed_mm_s=speed, snapshots=wanted)))
    _RIGS.clear()
    from lab.bench import peer

    return {
        "peer": peer.run(quick),
        "setup": {
            "a_mm": A_MM, "tank_a": [TANK_LENGTH_A, TANK_HEIGHT_A], "radius_ratio": RADIUS_RATIO, "sound_speed_mm_s": SOUND_SPEED_MM_S,
            "frame_s": FRAME_S, "settle_s": SETTLE_S, "front_quantile": FRONT_QUANTILE, "walls": "free slip",
        },
        "martin_moyce": [list(pair) for pair in MARTIN_MOYCE],
        "runs": runs,
    }


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def render(results: dict) -> list[str]:
    setup = results["setup"]
    lines = [
        "## Dam break against Martin & Moyce (1952)",
        "",
        f"A water column a = {setup['a_mm']:.0f} mm wide and 2a high collapses in a {setup['tank_a'][0]:g}a x {setup['tank_a'][1]:g}a "
        "tank with free-slip walls, simulated by the blood model (`sims.blood.particles`, `walls=True`) on a vertical plane in texture space, "
        f"without film drag, viscosity or clotting; interaction radius {setup['radius_ratio']:g} x spacing, stiffness from a nominal sound "
        f"speed of {setup['sound_speed_mm_s'] / 1000:g} m/s; the column settled behind a dam and was cut back to 2a before release "
        "(column compression: bulk density at its bottom over that at its top, minus 1). Front: the largest x of all "
        f"but the {setup['front_quantile']:.1%} most advanced particles. Error: |Z - Z_MM| at Martin & Moyce's 10 points "
        "(T = t sqrt(2g/a) from 0.85 to 5.3), in units of a; signed > 0 is ahead of them. Cost: wall time of the release only; "
        "a particle-step is one particle through one substep.",
        "",
        "| spacing (mm) | particles | substeps per ms | sound speed (m/s) | mean abs error (a) | max abs error (a) | mean signed (a) | "
        "column height (a) | column compression | release wall (s) | ms per simulated s | particle-steps/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in results["runs"]:
        error = row["error"]
        lines.append(
            f"| {row['spacing_mm']:g} | {row['particles']:,} | {row['substeps']} | {row['sound_speed_mm_s'] / 1000:g} | "
            f"{_fmt(error['mean_abs_a'], '.3f')} | {_fmt(error['max_abs_a'], '.3f')} | {_fmt(error['mean_signed_a'], '+.3f')} | "
            f"{_fmt(row['column_height_a'], '.3f')} | {_fmt(row['compression_rel'], '.1%')} | {row['wall_s']:.1f} | "
            f"{row['ms_per_simulated_s']:,.0f} | {row['particle_steps_per_s']:.3g} |"
        )
    lines += ["", _summary(results["runs"]), ""]
    from lab.bench import peer

    return lines + peer.render(results["peer"])


def _summary(runs: list) -> str:
    """Where the front is relative to Martin & Moyce (finest run), and how refinement moves it."""
    main = [r for r in runs if r["sound_speed_mm_s"] == SOUND_SPEED_MM_S and r["error"]["signed_a"]]
    if not main:
        return "No Martin & Moyce point lies inside the simulated time."
    row = min(main, key=lambda r: (r["spacing_mm"], -r["substeps"]))
    coarse = max(main, key=lambda r: (r["spacing_mm"], -r["substeps"]))
    signed = row["error"]["signed_a"]
    ahead, behind = sum(v > 0 for v in signed), sum(v < 0 for v in signed)
    half = len(signed) // 2
    text = (
        f"Finest run ({row['spacing_mm']:g} mm, {row['particles']:,} particles, {row['substeps']} substeps): the front is ahead of "
        f"Martin & Moyce at {ahead} and behind at {behind} of {len(signed)} points"
    )
    if half:
        text += (f", by {np.mean(signed[:half]):+.2f} a on average up to T = {row['error']['T'][half - 1]:.2f} and "
                 f"{np.mean(signed[half:]):+.2f} a after")
    text += f" (largest {max(signed, key=abs):+.2f} a)."
    if coarse is not row:
        text += (
            f" The coarsest ({coarse['spacing_mm']:g} mm, {coarse['substeps']} substeps) is {coarse['error']['mean_signed_a']:+.2f} a "
            f"on average against {row['error']['mean_signed_a']:+.2f} a: Clavet's pressure holds the free surface together (an "
            "artificial surface tension growing as stiffness x spacing²), which slows coarse and stiff runs; refining weakens it."
        )
    return text


def plot(results: dict, out_dir) -> list[str]:
    """dambreak_front.png (Z against T, with the peer where it ran), dambreak_error_cost.png (error against the
    release's wall time) and, when stored, dambreak_snapshots.png."""
    from pathlib import Path

    from lab.bench.common import pyplot, save

    plt = pyplot()
    out = Path(out_dir)
    peer = results.get("peer")
    peer_runs = peer["runs"] if peer and peer.get("available") else []
    data = np.asarray(results["martin_moyce"], np.float64)
    written = []

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    T = np.linspace(0.0, T_END, 50)
    ax.plot(T, 1.0 + 2.0 * T, ":", color="0.5", label="shallow water (Ritter), Z = 1 + 2T")
    cmap = plt.get_cmap("viridis")
    main = [r for r in results["runs"] if r["sound_speed_mm_s"] == SOUND_SPEED_MM_S]
    for index, row in enumerate(sorted(main, key=lambda r: (-r["spacing_mm"], r["substeps"]))):
        ax.plot(row["T"], row["Z"], color=cmap(index / max(len(main) - 1, 1)), lw=1.2,
                label=f"ours {row['spacing_mm']:g} mm, {row['substeps']} substeps ({row['particles']:,})")
    for row in peer_runs:
        ax.plot(row["T"], row["Z"], "--", lw=1.2, label=f"SPlisHSPlasH DFSPH ({row['particles']:,})")
    ax.plot(data[:, 0], data[:, 1], "ko", ms=5, label="Martin & Moyce 1952")
    ax.set(xlabel="T = t sqrt(2g/a)", ylabel="front Z = z / a", xlim=(0, T_END), ylim=(0.8, TANK_LENGTH_A))
    ax.legend(fontsize=7, loc="upper left")
    written.append(save(fig, out, "dambreak_front.png"))

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for speed in sorted({r["sound_speed_mm_s"] for r in results["runs"]}):
        rows = [r for r in results["runs"] if r["sound_speed_mm_s"] == speed and r["error"]["mean_abs_a"] is not None]
        marker = "o" if speed == SOUND_SPEED_MM_S else "s"
        ax.scatter([r["wall_s"] for r in rows], [r["error"]["mean_abs_a"] for r in rows], marker=marker,
                   label=f"ours, c = {speed / 1000:g} m/s")
        for r in rows:
            ax.annotate(f"{r['spacing_mm']:g} mm x{r['substeps']}", (r["wall_s"], r["error"]["mean_abs_a"]),
                        fontsize=6, xytext=(3, 3), textcoords="offset points")
    for row in peer_runs:
        if row["error"]["mean_abs_a"] is not None:
            ax.scatter([row["wall_s"]], [row["error"]["mean_abs_a"]], marker="^", color="k")
            ax.annotate(f"SPlisHSPlasH {row['particles_per_a']}/a", (row["wall_s"], row["error"]["mean_abs_a"]),
                        fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set(xscale="log", xlabel="wall time of the release, T = 0 to 5.5 (s)", ylabel="mean |Z - Z_MM| (a)")
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.margins(x=0.2, y=0.1)
    ax.legend(fontsize=7)
    written.append(save(fig, out, "dambreak_error_cost.png"))

    shots = next((r for r in results["runs"] if r.get("snapshots")), None)
    if shots:
        snaps = shots["snapshots"]
        fig, axes = plt.subplots(len(snaps), 1, figsize=(6.4, 1.25 * len(snaps) + 0.4), sharex=True)
        for ax, snap in zip(np.atleast_1d(axes), snaps):
            ax.scatter(snap["x"], snap["z"], s=0.4, color="tab:red")
            ax.axvline(martin_moyce_front(snap["T"]), color="k", lw=0.8, ls="--")
            ax.set(xlim=(0, TANK_LENGTH_A), ylim=(0, TANK_HEIGHT_A), aspect="equal", ylabel="z / a")
            ax.set_title(f"T = {snap['T']:.2f} (dashed: Martin & Moyce front)", fontsize=8)
        np.atleast_1d(axes)[-1].set_xlabel(f"x / a (ours, {shots['spacing_mm']:g} mm spacing)")
        written.append(save(fig, out, "dambreak_snapshots.png"))
    return written
