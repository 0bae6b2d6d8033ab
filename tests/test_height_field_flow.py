"""Height-field blood (sims.blood.height_field), accuracy and stability (issue 11): Nusselt's film on an incline, the same
film under a 2:1 UV stretch and at twice the resolution, exact volume across the liver lobe's UV seams, hard cases
(a vertical wall, a 1 ml/s jet into one texel, the largest time step, the parameter range ends, drying out) and a
lake at rest for 10,000 steps.

The film runs in a U channel (an inclined floor between two walls standing on it, one UV chart): the walls hold the
blood at the sides, the lower end is an open border (an outfall), so far from the feed and the outlet the film is
uniform and its depth is Nusselt's h = (3 nu q / (g sin theta))^(1/3) for the flux q per unit width fed at the top
(docs/model/blood.md "Reference solutions and data")."""
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from lab.reference.meshes import plane_mesh
from sims.blood.height_field import CAPACITY_MM, kinematic_viscosity_mm2_s
from sims.scene import params
from sims.surface.texels import build_surface, load_mesh, surface_at
from tests.test_height_field import (
    G,
    _forget_models,  # noqa: F401  (blood_on's models die with this module's Taichi runtime)
    assert_exact,
    blood_on,
    bowl_surface,
    level_pool,
)

REPO = Path(__file__).resolve().parents[1]
NO_LOSS = {"pinning_depth_mm": 0.0, "clotting_rate_1_s": 0.0, "lifetime_s": 36000.0}

# --- the film on an incline -------------------------------------------------------------------------------------------
SLOPE_DEG = 30.0
FLOOR_MM, WALL_MM, LENGTH_MM = 20.0, 5.0, 30.0  # across the floor, wall height, along the channel
FILM_VISCOSITY = 20.0   # mPa s: a thick film (0.49 mm) resolved by 0.47 mm texels
FLUX_MM2_S = 10.0       # q, volume flux per unit width fed across the floor
FEED_MM = 4.0           # the feed row, from the upper end
WINDOW_MM = (9.0, 17.0)  # measured between these distances from the upper end, over the middle half of the floor
FILM_DT, FILM_STEPS, FILM_AVERAGE = 0.02, 50, 8  # 1 s; the window is full and steady from about 0.85 s (64^2 and
                                                 # 128^2); the depth is averaged over the last 8 steps


def channel_frame(slope_deg=SLOPE_DEG):
    """Unit vectors: across the channel (x), down the floor (s), the floor's normal (n, up)."""
    t = math.radians(slope_deg)
    return np.array([1.0, 0.0, 0.0]), np.array([0.0, -math.cos(t), -math.sin(t)]), np.array([0.0, -math.sin(t), math.cos(t)])


def channel_mesh(v_top=1.0, slope_deg=SLOPE_DEG, cell_mm=1.0):
    """A U channel: a floor FLOOR_MM wide, LENGTH_MM long, inclined at slope_deg, with walls WALL_MM high standing on
    its sides (perpendicular to it). One UV chart unfolded from the cross-section: u = arc length across / total,
    v = v_top at the upper end down to 0 at the lower end (v_top = 1: square texels on a square texture; 0.5: texels
    twice as long down the channel as across). Borders (the walls' tops and both ends) are open."""
    ex, es, en = channel_frame(slope_deg)
    half = FLOOR_MM / 2
    corners = [(-half, WALL_MM), (-half, 0.0), (half, 0.0), (half, WALL_MM)]
    section = []
    for (x0, n0), (x1, n1) in zip(corners[:-1], corners[1:]):
        cells = max(1, round(math.hypot(x1 - x0, n1 - n0) / cell_mm))
        section += [(x0 + (x1 - x0) * f, n0 + (n1 - n0) * f) for f in np.arange(cells) / cells]
    section = np.array(section + [corners[-1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(section, axis=0), axis=1))])
    along = np.linspace(0.0, LENGTH_MM, round(LENGTH_MM / cell_mm) + 1)
    a, s = np.meshgrid(np.arange(len(section)), along)
    a, s = a.ravel(), s.ravel()
    vertices = section[a, :1] * ex + s[:, None] * es + section[a, 1:] * en
    uv = np.stack([arc[a] / arc[-1], v_top * (1.0 - s / LENGTH_MM)], axis=1)
    width = len(section)
    faces = []
    for j in range(len(along) - 1):
        for i in range(width - 1):
            k = j * width + i
            faces += [[k, k + width + 1, k + 1], [k, k + width, k + width + 1]]
    return trimesh.Trimesh(vertices, np.array(faces), process=False, visual=trimesh.visual.TextureVisuals(uv=uv))


def nusselt_depth(q_mm2_s, nu_mm2_s, slope_deg=SLOPE_DEG):
    return (3.0 * nu_mm2_s * q_mm2_s / (G * math.sin(math.radians(slope_deg)))) ** (1.0 / 3.0)


_FILMS = {}


def film_run(name):
    """Feed FLUX_MM2_S per unit width across the floor at FEED_MM (a spawn_rate of radius 0 into every floor texel
    of that row, q times the texel's width across) and run to steady state; then the mean depth, pipe velocity down
    the channel and flux u h over the window. Cached per surface name, so the stretch and resolution tests reuse the
    64^2 run."""
    if name in _FILMS:
        return _FILMS[name]
    surface = film_surface(name)
    blood = blood_on(surface, blood_viscosity_mpa_s=FILM_VISCOSITY, **NO_LOSS)
    ex, es, en = channel_frame()
    position = surface.position_mm.astype(np.float64)
    x, s = position @ ex, position @ es
    floor = surface.mask & (surface.normal.astype(np.float64) @ en > 0.999)
    height = position @ en  # above the floor's plane: the walls
    feed_row = int(np.argmin(np.abs(np.where(floor, s, np.inf) - FEED_MM).min(axis=1)))
    feed_cols = np.flatnonzero(floor[feed_row])
    across = np.linalg.norm(surface.tangent_u[feed_row, feed_cols].astype(np.float64), axis=1)
    rates = FLUX_MM2_S * across / 1000.0  # ml/s
    window = floor & (s > WINDOW_MM[0]) & (s < WINDOW_MM[1]) & (np.abs(x) < FLOOR_MM / 4)
    depths, speeds, fluxes = [], [], []
    for step in range(FILM_STEPS):
        for col, rate in zip(feed_cols, rates):
            blood.spawn_rate(("feed", int(col)), (feed_row, int(col)), float(rate), FILM_DT, 0.0)
        blood.step(FILM_DT)
        if step >= FILM_STEPS - FILM_AVERAGE:
            depth, u = blood.depth_mm(), blood.u.to_numpy()[0][..., 2]  # NEIGHBOURS[2] = (1, 0): one row down
            depths.append(depth[window].mean())
            speeds.append(u[window].mean())
            fluxes.append((u * depth)[window].mean())  # per unit width: u W h / W (the donor is the upper texel)
    a = assert_exact(blood)
    wetted = blood.stain.to_numpy() > 0
    half = FILM_AVERAGE // 2
    result = {
        "depth_mm": float(np.mean(depths)),
        "drift": float(np.mean(depths[half:]) / np.mean(depths[:half]) - 1.0),  # steady: the two halves agree
        "velocity_mm_s": float(np.mean(speeds)),
        "flux_mm2_s": float(np.mean(fluxes)),
        "fed_width_mm": float(across.sum()),
        "texel_mm": (float(np.linalg.norm(surface.tangent_u[window][0])), float(np.linalg.norm(surface.tangent_v[window][0]))),
        "substeps": blood.last_substeps,
        "climbed_mm": float(height[wetted].max()),  # how far up the walls blood went (their tops are outfalls)
        "spawned_ml": a["spawned"],
        "nu": kinematic_viscosity_mm2_s(blood.params),
    }
    _FILMS[name] = result
    return result


_SURFACES = {}


def film_surface(name):
    """The channel on 64^2 texels ('64'), with texels twice as long down the channel ('stretched'), or the same
    triangles and UVs as '64' on 128^2 texels ('128')."""
    if name not in _SURFACES:
        if name in ("32", "128"):
            _SURFACES[name] = surface_at(film_surface("64"), int(name))
        else:
            _SURFACES[name] = build_surface(channel_mesh(v_top=0.5 if name == "stretched" else 1.0), 64)
    return _SURFACES[name]


@pytest.fixture(scope="module", autouse=True)
def _forget_films():
    yield
    _FILMS.clear()
    _SURFACES.clear()


def test_film_on_an_incline_has_nusselts_depth():
    """q = 10 mm^2/s of blood at 20 mPa s (nu = 19.0 mm^2/s) on 30 degrees: h = (3 nu q / (g sin theta))^(1/3) =
    0.488 mm and the mean velocity g sin theta h^2 / (3 nu) = q / h = 20.5 mm/s (docs/model/blood.md "Reference solutions and data").

    In a uniform film the scheme's balance is exactly Nusselt's (bed slope against the drag 3 nu u / h^2, flux u h), so
    what is left is the channel: the feed's standing ripple (gone 5 mm below it), the outlet's draw-down (the last
    3 mm) and the fold at the walls (blood climbs one texel, the floor beside it is 15-20 % shallower and that dip spreads
    inward down the channel). Measured over the window: -0.4 % (the centre line alone: -0.02 %). Tolerance 3 %: a drag
    off by 20 % (or using another depth than the donor's) would shift h by 6 %."""
    r = film_run("64")
    h = nusselt_depth(FLUX_MM2_S, r["nu"])
    mean_velocity = FLUX_MM2_S / h
    print(f"Nusselt film 64^2 (texels {r['texel_mm'][0]:.3f} x {r['texel_mm'][1]:.3f} mm): depth {r['depth_mm']:.4f} mm "
          f"(Nusselt {h:.4f}, {r['depth_mm'] / h - 1:+.2%}), mean velocity {r['velocity_mm_s']:.2f} mm/s (Nusselt "
          f"{mean_velocity:.2f}, {r['velocity_mm_s'] / mean_velocity - 1:+.2%}), flux u h {r['flux_mm2_s']:.3f} mm^2/s "
          f"(fed {FLUX_MM2_S}), drift over the last {FILM_AVERAGE} steps {r['drift']:+.1e}, blood up the walls to "
          f"{r['climbed_mm']:.2f} mm (of {WALL_MM}), substeps {r['substeps']}")
    # measured: depth 0.4864 mm against 0.4884 (-0.40 %), velocity 20.33 against 20.48 mm/s (-0.7 %), flux 9.89 mm^2/s,
    # drift 1e-4, blood on the walls' first texel only (its centre 0.08 mm above the floor), 18 substeps per 0.02 s step
    assert abs(r["drift"]) < 2e-3  # steady
    assert r["climbed_mm"] < 0.5 * WALL_MM  # the walls held it: no loss over their tops
    assert r["depth_mm"] == pytest.approx(h, rel=0.03)
    assert r["velocity_mm_s"] == pytest.approx(mean_velocity, rel=0.05)
    assert r["flux_mm2_s"] == pytest.approx(FLUX_MM2_S, rel=0.03)  # the fed flux passes the window


def test_film_depth_does_not_depend_on_the_uv_stretch():
    """The same channel with its UVs on half the texture's height: texels 0.47 mm across and 0.94 mm down the
    channel. Depth and velocity within 5 % of the square texels' (measured -0.12 %)."""
    plain, stretched = film_run("64"), film_run("stretched")
    h = nusselt_depth(FLUX_MM2_S, stretched["nu"])
    print(f"UV stretch: texels {stretched['texel_mm'][0]:.3f} x {stretched['texel_mm'][1]:.3f} mm: depth "
          f"{stretched['depth_mm']:.4f} mm against {plain['depth_mm']:.4f} on square texels "
          f"({stretched['depth_mm'] / plain['depth_mm'] - 1:+.2%}; Nusselt {h:.4f}), velocity "
          f"{stretched['velocity_mm_s']:.2f} against {plain['velocity_mm_s']:.2f} mm/s, drift {stretched['drift']:+.1e}")
    # measured: depth 0.4858 against 0.4864 mm (-0.12 %), velocity 20.28 against 20.33 mm/s
    assert stretched["texel_mm"][1] == pytest.approx(2 * stretched["texel_mm"][0], rel=0.02)
    assert abs(stretched["drift"]) < 2e-3
    assert stretched["depth_mm"] == pytest.approx(plain["depth_mm"], rel=0.05)
    assert stretched["velocity_mm_s"] == pytest.approx(plain["velocity_mm_s"], rel=0.05)
    assert stretched["depth_mm"] == pytest.approx(h, rel=0.03)


def test_film_depth_converges_with_resolution():
    """The same triangles and UVs on 128^2 texels (0.23 mm) against 64^2 (0.47 mm): within 10 % of each other
    (measured +0.17 %) and within 3 % of Nusselt."""
    coarse, fine = film_run("64"), film_run("128")
    h = nusselt_depth(FLUX_MM2_S, fine["nu"])
    print(f"resolution: depth {coarse['depth_mm']:.4f} mm at 64^2, {fine['depth_mm']:.4f} at 128^2 "
          f"({fine['depth_mm'] / coarse['depth_mm'] - 1:+.2%}; Nusselt {h:.4f}, {fine['depth_mm'] / h - 1:+.2%}), velocity "
          f"{coarse['velocity_mm_s']:.2f} and {fine['velocity_mm_s']:.2f} mm/s, drift {fine['drift']:+.1e}, substeps "
          f"{coarse['substeps']} and {fine['substeps']}")
    # measured: 0.4864 and 0.4872 mm (+0.17 %; Nusselt 0.4884: -0.24 % at 128^2), 18 and 53 substeps per step
    assert abs(fine["drift"]) < 2e-3
    assert fine["depth_mm"] == pytest.approx(coarse["depth_mm"], rel=0.1)
    assert fine["depth_mm"] == pytest.approx(h, rel=0.03)


# --- volume across the liver lobe's seams ------------------------------------------------------------------------------
def test_volume_is_exact_across_the_liver_lobes_seams():
    """Blood poured on the multi-chart liver lobe (xatlas charts, 919 seam links at 64^2) with suction and drying:
    spawned = on_surface + suctioned + left_surface + dried exactly in units at every step, the volume read from the
    depth field agrees with the accounting, and blood crossed seams into charts where none was poured."""
    surface = build_surface(load_mesh(REPO / "static/meshes/liver_lobe.obj"), 64)
    blood = blood_on(surface, lifetime_s=5.0, clotting_rate_1_s=0.0)
    assert blood.seam_links > 100
    charts, count = ndimage.label(surface.mask, structure=np.ones((3, 3)))
    linked = (np.diff(blood.link_start.to_numpy()) > 0).reshape(surface.mask.shape)
    z, nz = surface.position_mm[..., 2], surface.normal[..., 2]
    rows, cols = np.nonzero(linked & (nz > 0.5))
    top = np.argmax(z[rows, cols])
    sources = [(int(rows[top]), int(cols[top]))]  # the highest seam texel facing up: its blood runs down across charts
    for chart in np.argsort(np.bincount(charts.ravel())[1:])[::-1][:2] + 1:  # near the middle of the two largest charts
        r, c = np.nonzero(charts == chart)
        middle = np.argmin((r - r.mean()) ** 2 + (c - c.mean()) ** 2)
        sources.append((int(r[middle]), int(c[middle])))
    tool = surface.position_mm[sources[2]].astype(np.float64)
    areas = surface.texel_area_mm2.astype(np.float64)
    worst = 0.0
    for step in range(60):
        if step < 30:
            for index, source in enumerate(sources):
                blood.spawn_rate(("liver", index), source, 0.1, 0.02, 1.0)
        blood.step(0.02, [(tool, 4.0, 0.05)] if step >= 20 else [])
        a = assert_exact(blood)
        field_ml = float((blood.depth_mm() * areas)[surface.mask].sum()) / 1000.0
        balance_ml = a["spawned"] - a["suctioned"] - a["left_surface"] - a["dried"]
        worst = max(worst, abs(field_ml - balance_ml) / a["spawned"])
        assert blood.volume.to_numpy().min() >= 0
    wet = blood.stain.to_numpy() > 0
    fed = {int(charts[source]) for source in sources}
    reached = set(np.unique(charts[wet]).tolist()) - {0}
    link_speed = float(np.abs(blood.link_u.to_numpy()[0]).max())
    print(f"liver lobe ({count} charts, {blood.seam_links} seam links): spawned {a['spawned']:.4f} ml = on surface "
          f"{a['on_surface']:.4f} + suctioned {a['suctioned']:.4f} + left {a['left_surface']:.4f} + dried {a['dried']:.4f} "
          f"(exact in units); depth field against the accounting: largest relative error {worst:.1e}; charts fed "
          f"{sorted(fed)}, wetted {sorted(reached)}; fastest seam link {link_speed:.1f} mm/s")
    # measured: 0.18 ml spawned = 0.1258 on the surface + 0.0157 suctioned + 0.0115 left (through the outfalls where a
    # chart border found no seam partner: 93 pipes) + 0.0270 dried; depth field against the accounting 2e-16 (the depth is integer units times unit /
    # area); poured on charts 4 and 6, blood reached 7 and 8; seam links up to 36 mm/s
    assert worst <= 1e-6
    assert a["suctioned"] > 0 and a["dried"] > 0
    assert reached - fed, "no blood crossed a seam into a chart it was not poured on"
    assert link_speed > 0


# --- hard cases -----------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def wall():
    """A vertical 30 x 30 mm wall (rows grow downward), open borders: blood falls off the lower edge."""
    surface = build_surface(plane_mesh(30.0, 30.0, slope_deg=90.0), 32)
    assert np.abs(surface.normal[surface.mask][:, 2]).max() < 1e-6  # no hydrostatic pressure: g.n = 0
    return surface


LARGEST_STEP = params.SIMULATION["time_step_s"].max
PINNING = params.HEIGHT_FIELD["pinning_depth_mm"]
VISCOSITY = params.HEIGHT_FIELD["blood_viscosity_mpa_s"]


def check_state(blood):
    depth = blood.depth_mm()
    speeds = blood.pipe_speeds()
    assert np.isfinite(depth).all() and depth.min() >= 0.0
    assert np.isfinite(speeds).all()
    assert blood.volume.to_numpy().min() >= 0
    return assert_exact(blood), depth, speeds


@pytest.mark.parametrize("viscosity", [VISCOSITY.min, VISCOSITY.max])
@pytest.mark.parametrize("pinning", [PINNING.min, PINNING.max])
def test_a_jet_down_a_vertical_wall_at_the_largest_step_stays_finite_and_exact(wall, viscosity, pinning):
    """1 ml/s into one texel (radius 0) near the top of a vertical wall (g.n = 0: no hydrostatic pressure, only the bed
    slope moves it) at the largest time step the slider allows: 57 mm of depth per step in that texel (CAPACITY_MM is
    64), blood falling at hundreds of mm/s. Finite, non-negative, exact at every step; the source adds exactly what
    was asked (less any refused at capacity, counted)."""
    blood = blood_on(wall, blood_viscosity_mpa_s=viscosity, pinning_depth_mm=pinning, clotting_rate_1_s=0.0, lifetime_s=36000.0)
    source = (3, wall.size // 2)
    steps, rate = 20, 1.0
    deepest = 0.0
    for _ in range(steps):
        blood.spawn_rate("jet", source, rate, LARGEST_STEP, 0.0)
        blood.step(LARGEST_STEP)
        a, depth, speeds = check_state(blood)
        deepest = max(deepest, depth.max())
    units = a["units"]
    asked = rate * LARGEST_STEP * steps * 1000.0 / blood.unit_mm3
    print(f"jet on a wall (viscosity {viscosity}, pinning {pinning}): spawned {a['spawned']:.3f} ml, refused "
          f"{a['dropped_too_deep']:.3f}, left {a['left_surface']:.3f}, on surface {a['on_surface']:.4f}; deepest "
          f"{deepest:.1f} mm, fastest pipe {speeds.max():.0f} mm/s, substeps {blood.last_substeps}")
    # measured (viscosity/pinning 0/0, 50/0, 0/1, 50/1), the source spread over the step's substeps: 0.94 ml spawned,
    # 0.06 ml refused (the jet's texel still holds part of the last step's 57 mm when the next comes: 64 mm is its
    # capacity), 0.86-0.88 ml off the lower edge, 0.061-0.080 ml on the wall; deepest 56.9 mm, fastest pipe 420-855
    # mm/s, 64 substeps (max_substeps). With the whole step's source added at once: none refused, 420-750 mm/s
    assert units["spawned"] + units["dropped_too_deep"] == pytest.approx(asked, abs=1.0)  # the source is exact too
    assert deepest <= CAPACITY_MM * 1.01
    assert a["left_surface"] > 0  # it reached the lower edge


def test_blood_dries_out_to_nothing(wall):
    """lifetime_s at its smallest (0.1 s), the largest pinning depth (a film stays on the wall to dry), suction below
    the source: after the source stops, the surface dries to exactly zero units, and every unit spawned is dried,
    run off or suctioned."""
    blood = blood_on(wall, lifetime_s=params.HEIGHT_FIELD["lifetime_s"].min, pinning_depth_mm=PINNING.max,
                     clotting_rate_1_s=0.0)
    tool = wall.position_mm[12, wall.size // 2].astype(np.float64)
    for step in range(400):
        if step < 5:
            blood.spawn_rate("jet", (3, wall.size // 2), 1.0, LARGEST_STEP, 0.0)
        blood.step(LARGEST_STEP, [(tool, 2.0, 1.0)])
        a, _, _ = check_state(blood)
        if step >= 5 and a["units"]["on_surface"] == 0:
            break
    units = a["units"]
    print(f"drying out: empty after {step + 1} steps of {LARGEST_STEP} s; spawned {units['spawned']} units = dried "
          f"{units['dried']} + left {units['left_surface']} + suctioned {units['suctioned']}; on surface {units['on_surface']}")
    # measured: empty after 36 steps (1.8 s); 74,565,405 units = 32,837,923 dried + 16,072,637 run off + 25,654,845
    # suctioned
    assert units["on_surface"] == 0
    assert units["dried"] == units["spawned"] - units["left_surface"] - units["suctioned"]
    assert min(units["dried"], units["left_surface"], units["suctioned"]) > 0


# --- a lake at rest, long ---------------------------------------------------------------------------------------------------
def level_of(surface, volume_mm3):
    """The level (mm) of a level pool in the hollow holding this volume (bisection)."""
    areas = surface.texel_area_mm2.astype(np.float64)
    low, high = 0.0, 10.0
    for _ in range(60):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if (level_pool(surface, middle) * areas).sum() < volume_mm3 else (low, middle)
    return 0.5 * (low + high)


def test_a_lake_stays_at_rest_for_ten_thousand_steps():
    """A level pool 1 mm deep at the centre of the hollow z = r^2 / 100 (32^2 texels of 1.25 mm), blood's viscosity,
    10,000 steps (40 s). The volume is integer units (about 4e-6 mm of depth) moved with stochastic rounding, so rest
    is exact only to that noise. Drying (lifetime 36000 s, the slider's end) takes h t / lifetime, about 1e-3 mm at the
    centre, and the pool levels itself again; only the thinnest texels at the rim lag (their drag 3 nu / h^2 holds
    them), so the level is checked where the blood is deeper than 0.05 mm."""
    surface = bowl_surface("plain", 32)
    blood = blood_on(surface, blood_viscosity_mpa_s=3.5, **NO_LOSS)
    blood.set_depth(level_pool(surface, 1.0))
    start = blood.depth_mm()
    dt, steps = 0.004, 10_000  # one substep per step (CFL at sqrt(g h) = 99 mm/s and 1.25 mm texels)
    fastest = 0.0
    for step in range(steps):
        blood.step(dt)
        if step % 500 == 499:
            fastest = max(fastest, float(blood.pipe_speeds().max()))
    a = assert_exact(blood)
    depth = blood.depth_mm()
    level = level_of(surface, a["on_surface"] * 1000.0)
    deep = depth > 0.05
    error = np.abs(depth - level_pool(surface, level))
    free_surface = surface.position_mm[..., 2] + depth * surface.normal[..., 2]
    change = np.abs(depth - start).max()
    print(f"lake at rest, {steps} steps of {dt} s: level {level:.5f} mm (from 1; dried {a['dried'] * 1000:.4f} mm^3); "
          f"where deeper than 0.05 mm: |h - level pool| <= {error[deep].max():.2e} mm, free surface within "
          f"{np.ptp(free_surface[deep]):.2e} mm; at the rim |h - level pool| <= {error[~deep].max():.2e}; largest change "
          f"{change:.2e} mm; fastest pipe {fastest:.2e} mm/s (sqrt(g h) = {math.sqrt(G):.0f}); wet texels "
          f"{int((start > 0).sum())} -> {int((depth > 0).sum())}")
    # measured: level 0.99947 mm (0.175 mm^3 dried); where deeper than 0.05 mm |h - level pool| <= 8.1e-5 mm and the
    # free surface within 1.3e-4 mm (tens of units of noise); the rim 4.5e-4 mm above the lowered level; largest change
    # 6.1e-4 mm (mostly the drying); fastest pipe 3.7e-3 mm/s (sampled every 500 steps); the shore did not move.
    assert error[deep].max() < 2e-4 and np.ptp(free_surface[deep]) < 3e-4
    assert change < 1e-3
    assert fastest < 0.01
    assert ((depth > 0) == (start > 0)).all()
