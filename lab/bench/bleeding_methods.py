"""Bleeding methods side by side: particles (sims.blood.particles.Bleeding, a 2D Clavet film of fixed thickness) and the height
field (sims.blood.height_field.HeightFieldBleeding, depth per texel through virtual pipes) on the same cases, error next to
cost, each at a couple of resolutions (texel size for the height field, particle spacing for the particles).

Cases (all choices here, none tuned to the results):
- incline: a 30 x 30 mm plane at 30 degrees, open borders; blood fed along a 20 mm line across the slope, 2.5 mm below
  the top edge (21 bleed disks of radius 0.6 mm, 1 mm apart), at the flux per width q that gives a Nusselt film
  h = (3 nu q / (g sin theta))^(1/3) of `film_mm` (nu from the blood viscosity, 3.33 mm^2/s). Measured: the blood
  volume per area in a window 10 mm wide (|x| < 5 mm) from 10 to 20 mm down the slope, averaged over the last 0.3 s of
  1.2 s (steady by then: the film crosses the window in under 0.5 s). Height field: mean depth of the window's texels.
  Particles: particles in the window x particle volume / window area (their splat gives the same within 1-2 %); the
  particles' mean speed down the slope there is kept too (Nusselt's mean speed is g sin theta h^2 / (3 nu)).
- hollow: 0.3 ml poured at 0.3 ml/s for 1 s (disk of 1 mm) at the bottom of the paraboloid z = r^2 / 100 mm (40 x 40 mm,
  plane UVs), then 0.5 s to settle (the height field is level by then; the particles' film stops spreading by 1.5 s).
  A level pool of volume V there is H = sqrt(2 V / (100 pi)) deep at the centre (V = pi 100 H^2 / 2) and wets the cap
  r^2 < 100 H: projected area pi 100 H (434 mm^2 for 0.3 ml), surface area (2 pi / 3) 50^2 ((1 + 100 H / 50^2)^1.5 - 1)
  (441 mm^2). Measured from blood_thickness_mm (the particles' splat): the surface area of texels at least 0.01 mm deep
  (against the surface area) and the mean thickness within r < 1 mm (against H).
- dam break, Ritter: a horizontal strip 96 x 12 mm with walls (walls=True for both), h0 = 1 mm of blood at rest behind
  a dam 32 mm from the left end, released at t = 0 and followed for 0.15 s (the rarefaction reaches 15 mm back, the
  front 2 sqrt(g h0) t = 29.7 mm ahead), frictionless (no film drag, no Clavet viscosity, speed clamp off). Error:
  the front (height field: the last strip column whose mean depth is at least 1e-3 h0; particles: the x of rank
  0.2 % from the most advanced particle, as the dambreak section) against 2 sqrt(g h0) t, and the mean |h - h_Ritter| / h0
  over the wave (-sqrt(g h0) t < x - x0 < 2 sqrt(g h0) t, strip-averaged thickness). The particles, in two honest
  translations of the same reservoir: the default 0.3 mm film with a lattice that puts h0 of blood per area (3.3x their
  rest density), and a 1 mm film (= h0) at rest density. Their pressure is Clavet's equation of state (stiffness k, set
  for a film of fixed thickness), not g h, and on a level bed their gravity has no tangential part, so how far they
  spread says how their pressure acts, not that it models shallow water. A front at the strip's far wall is a lower
  bound (flagged in the table).
- dam break, Martin & Moyce (full run only): the particles on the formulation they are validated on, the dambreak
  section's vertical-plane water column (lab.bench.dambreak.simulate, its own water-like parameters), rerun here at
  two spacings. The height field has no counterpart there: on a vertical plane its hydrostatic term g_n h is 0, and a
  column as high as it is wide is not shallow water (Ritter's Z = 1 + 2T is that limit). Relative front error: the mean
  of |Z - Z_MM| / (Z_MM - 1) over Martin & Moyce's points (the front's distance from the dam).
- cost as the bled volume grows: one bleed point (the scene bleeding.yaml's vessel, radius 0.6 mm) at 1 ml/s on
  static/meshes/patch.obj (60 x 40 mm, blood runs off its lower edge), product defaults for both methods; wall ms per
  simulated second after 0.1, 0.3, 1 (and, full run, 3) ml bled, with the blood still on the surface, the particles alive
  (pool from sims.blood.particles.auto_capacity) or the height field's awake tiles and substeps.

Physics cases (incline, hollow): blood's viscosity, clotting, drying and pinning off (they stop a film on purpose);
everything else the product defaults (sims.scene.params.BLEEDING / HEIGHT_FIELD, so new keys come along). Particle runs use
an interaction radius of 3 x spacing, as the default 1.5 mm for 0.5 mm.

Cost: wall time of the run's steps (and feeding) after the kernels compiled, Taichi synchronised at both ends, over the
simulated time (ms per simulated second); measurements in between are not timed. The cost-growth case times 20 steps at
each mark, the fastest tenth scaled (common.synced_seconds), so the state is the one at the mark.
"""
import math
import time

import numpy as np

from lab.bench.common import json_finite, pyplot, save, synced_seconds
from lab.reference.dambreak import MARTIN_MOYCE, front_position
from lab.reference.meshes import grid_faces
from sims.blood.height_field import TILE as HEIGHT_FIELD_TILE
from sims.scene.config import REPO_ROOT

G_MM_S2 = 9810.0
GRAVITY = (0.0, 0.0, -G_MM_S2)
DT_S = 0.01
RADIUS_RATIO = 3.0                 # particles: interaction radius / spacing

INCLINE_DEG, INCLINE_SIDE_MM = 30.0, 30.0
FEED_WIDTH_MM, FEED_FROM_TOP_MM, FEED_PITCH_MM, FEED_RADIUS_MM = 20.0, 2.5, 1.0, 0.6
WINDOW_HALF_WIDTH_MM, WINDOW_DOWN_MM = 5.0, (10.0, 20.0)
INCLINE_S, INCLINE_AVERAGE_S, INCLINE_SAMPLE_EVERY = 1.2, 0.3, 5

HOLLOW_HALF_MM, HOLLOW_VOLUME_ML, HOLLOW_POUR_S, HOLLOW_SETTLE_S = 20.0, 0.3, 1.0, 0.5
HOLLOW_WET_MM, HOLLOW_CENTRE_MM = 0.01, 1.0

STRIP_MM, DAM_MM, H0_MM, RITTER_S, RITTER_DT_S = (96.0, 12.0), 32.0, 1.0, 0.15, 0.005
FRONT_DEPTH_FRACTION = 1e-3

BLEED_RATE_ML_S, BLEED_RADIUS_MM, BLEED_AT_MM = 1.0, 0.6, (8.0, 14.0, 4.2)
COST_STEPS, COST_CHUNKS = 20, 10     # steps timed after each mark, in chunks (the fastest counts)

QUICK = {
    "incline_films_mm": (0.3,), "height_field_sizes": {"incline": (64,), "hollow": (64,), "ritter": (1.0,), "cost": (8,)},
    "spacings_mm": (0.5,), "marks_ml": (0.1, 0.3, 1.0), "martin_moyce": (),
}
FULL = {
    "incline_films_mm": (0.3, 0.5), "height_field_sizes": {"incline": (64, 128), "hollow": (64, 128), "ritter": (1.0, 0.5), "cost": (8, 4)},
    "spacings_mm": (0.5, 0.35), "marks_ml": (0.1, 0.3, 1.0, 3.0), "martin_moyce": ((1.0, 2), (0.7, 4)),
}
PARTICLE_TEXTURE = {"incline": {0.5: 64, 0.35: 128}, "hollow": {0.5: 128, 0.35: 128}, "ritter_texel_mm": 0.25}
COST_TEXTURE = 512                 # the display texture of the cost-growth case, as the lab's default preset


# --- parameters and meshes -------------------------------------------------------------------------------------------
def height_field_params(**changes) -> dict:
    from sims.scene import params

    return {**{name: spec.default for name, spec in params.HEIGHT_FIELD.items()}, **changes}


def particle_params(spacing_mm: float, **changes) -> dict:
    from sims.scene import params

    values = {name: spec.default for name, spec in params.BLEEDING.items()}
    values.update(particle_spacing_mm=spacing_mm, interaction_radius_mm=RADIUS_RATIO * spacing_mm)
    return {**values, **changes}


PHYSICS_HF = {"clotting_rate_1_s": 0.0, "pinning_depth_mm": 0.0, "lifetime_s": 36000.0}
PHYSICS_PARTICLES = {"clotting_rate_1_s": 0.0, "pinning_density": 0.0, "lifetime_s": 36000.0}


def _mesh(vertices, faces, uv):
    import trimesh

    return trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv), process=False)


def incline_mesh(side_mm: float = INCLINE_SIDE_MM, slope_deg: float = INCLINE_DEG, cells: int = 8):
    """A side x side square tilted about x (rising toward +y, so texture rows grow downhill), UVs onto [0, 1]^2."""
    xs, ys = np.meshgrid(np.linspace(-side_mm / 2, side_mm / 2, cells + 1), np.linspace(-side_mm / 2, side_mm / 2, cells + 1))
    slope = math.radians(slope_deg)
    vertices = np.stack([xs.ravel(), ys.ravel() * math.cos(slope), ys.ravel() * math.sin(slope)], axis=1)
    uv = np.stack([xs.ravel() / side_mm + 0.5, ys.ravel() / side_mm + 0.5], axis=1)
    return _mesh(vertices, grid_faces(cells, cells), uv)


def hollow_mesh(half_mm: float = HOLLOW_HALF_MM, cells: int = 40):
    """The paraboloid hollow z = r^2 / 100 (mm) over a 2 half x 2 half square, plane UVs (x, y) onto [0, 1]^2."""
    xs, ys = np.meshgrid(np.linspace(-half_mm, half_mm, cells + 1), np.linspace(-half_mm, half_mm, cells + 1))
    vertices = np.stack([xs.ravel(), ys.ravel(), (xs.ravel() ** 2 + ys.ravel() ** 2) / 100.0], axis=1)
    uv = np.stack([(xs.ravel() + half_mm) / (2 * half_mm), (ys.ravel() + half_mm) / (2 * half_mm)], axis=1)
    return _mesh(vertices, grid_faces(cells, cells), uv)


def strip_surface(texel_mm: float):
    """Horizontal strip STRIP_MM in the bottom-left corner of a square texture of texel_mm texels (edges on texel
    borders): (surface, size)."""
    from sims.surface.texels import build_surface

    length, width = STRIP_MM
    size = 2 ** int(math.ceil(math.log2(length / texel_mm - 1e-9)))
    xs, ys = np.meshgrid(np.linspace(0.0, length, 9), np.linspace(0.0, width, 9))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    uv = np.stack([xs.ravel(), ys.ravel()], axis=1) / (size * texel_mm)
    return build_surface(_mesh(vertices, grid_faces(8, 8), uv), size), size


def level_pool(volume_ml: float) -> dict:
    """Level pool of volume_ml in z = r^2 / 100: centre depth, projected and surface area of the wetted cap."""
    depth = math.sqrt(2.0 * volume_ml * 1000.0 / (100.0 * math.pi))
    surface = 2.0 * math.pi / 3.0 * 2500.0 * ((1.0 + 100.0 * depth / 2500.0) ** 1.5 - 1.0)
    return {"depth_mm": depth, "projected_area_mm2": 100.0 * math.pi * depth, "surface_area_mm2": surface}


def ritter_depth(x_mm, t_s: float, h0_mm: float = H0_MM):
    """Ritter's depth at x (mm from the dam) at t."""
    c = math.sqrt(G_MM_S2 * h0_mm)
    x = np.asarray(x_mm, np.float64)
    return np.where(x <= -c * t_s, h0_mm, np.where(x >= 2 * c * t_s, 0.0, (2 * c - x / t_s) ** 2 / (9 * G_MM_S2)))


def _model(method: str, surface, values: dict, capacity: int = 0, walls: bool = False, display=None):
    if method == "height_field":
        from sims.blood.height_field import HeightFieldBleeding

        return HeightFieldBleeding(surface, values, GRAVITY, walls=walls, display=display)
    from sims.blood.particles import Bleeding

    return Bleeding(surface, values, GRAVITY, capacity, walls=walls)


def _nearest_texel(surface, point_mm) -> tuple:
    distance = np.linalg.norm(surface.position_mm - np.asarray(point_mm), axis=-1) + np.where(surface.mask, 0.0, np.inf)
    return tuple(int(v) for v in np.unravel_index(np.argmin(distance), distance.shape))


def _resolution(method: str, texel_mm: float, spacing_mm: float | None) -> str:
    return f"{texel_mm:.2g} mm texels" if method == "height_field" else f"{spacing_mm:g} mm spacing"


class _Clock:
    """Wall seconds of the timed parts, Taichi synchronised at both ends of each."""

    def __init__(self):
        self.seconds = 0.0

    def __enter__(self):
        import taichi as ti

        ti.sync()
        self._start = time.perf_counter()

    def __exit__(self, *exc):
        import taichi as ti

        ti.sync()
        self.seconds += time.perf_counter() - self._start


# --- incline ----------------------------------------------------------------------------------------------------------
def incline(method: str, film_mm: float, size: int = 64, spacing_mm: float | None = None) -> dict:
    """A film fed across an incline against Nusselt's depth (module docstring)."""
    from sims.blood.height_field import kinematic_viscosity_mm2_s
    from sims.surface.texels import build_surface

    surface = build_surface(incline_mesh(), size)
    values = height_field_params(**PHYSICS_HF) if method == "height_field" else particle_params(spacing_mm, **PHYSICS_PARTICLES)
    nu = kinematic_viscosity_mm2_s(values)
    slope = math.radians(INCLINE_DEG)
    q = G_MM_S2 * math.sin(slope) * film_mm**3 / (3.0 * nu)       # mm^2/s: the flux per width for a film_mm film
    rate = q * FEED_WIDTH_MM / 1000.0                              # ml/s over the feed line
    xs = np.linspace(-FEED_WIDTH_MM / 2, FEED_WIDTH_MM / 2, int(round(FEED_WIDTH_MM / FEED_PITCH_MM)) + 1)
    top = INCLINE_SIDE_MM / 2
    down_top = top - FEED_FROM_TOP_MM
    feeds = [_nearest_texel(surface, (x, down_top * math.cos(slope), down_top * math.sin(slope))) for x in xs]
    capacity = 0
    if method == "particles":
        from sims.blood.particles import particle_volume_ml

        capacity = int(1.2 * rate * INCLINE_S / particle_volume_ml(values)) + 2048
    blood = _model(method, surface, values, capacity)

    def feed_and_step():
        for index, texel in enumerate(feeds):
            blood.spawn_rate(index, texel, rate / len(feeds), DT_S, FEED_RADIUS_MM)
        blood.step(DT_S)

    feed_and_step()  # compiles the kernels
    blood.reset()
    position = surface.position_mm.astype(np.float64)
    down = top - position[..., 1] / math.cos(slope)   # mm down the slope from the top edge
    window = surface.mask & (np.abs(position[..., 0]) < WINDOW_HALF_WIDTH_MM) & (down > WINDOW_DOWN_MM[0]) & (down < WINDOW_DOWN_MM[1])
    window_area = 2 * WINDOW_HALF_WIDTH_MM * (WINDOW_DOWN_MM[1] - WINDOW_DOWN_MM[0])
    steps = int(round(INCLINE_S / DT_S))
    first_sample = steps - int(round(INCLINE_AVERAGE_S / DT_S))
    clock, depths, speeds, done = _Clock(), [], [], 0
    while done < steps:
        chunk = INCLINE_SAMPLE_EVERY if done >= first_sample else first_sample - done
        with clock:
            for _ in range(chunk):
                feed_and_step()
        done += chunk
        if done <= first_sample:
            continue
        if method == "height_field":
            depth = blood.depth_mm()
            area = surface.texel_area_mm2
            depths.append(float((depth * area)[window].sum() / area[window].sum()))
        else:
            arrays = blood.particle_arrays()
            p, v = arrays["particle_position_mm"].astype(np.float64), arrays["particle_velocity_mm_s"].astype(np.float64)
            p_down = top - p[:, 1] / math.cos(slope)
            inside = (np.abs(p[:, 0]) < WINDOW_HALF_WIDTH_MM) & (p_down > WINDOW_DOWN_MM[0]) & (p_down < WINDOW_DOWN_MM[1])
            depths.append(float(inside.sum() * blood.particle_volume_ml * 1000.0 / window_area))
            downhill = np.array([0.0, -math.cos(slope), -math.sin(slope)])
            speeds.append(float((v[inside] @ downhill).mean()) if inside.any() else 0.0)
    measured = float(np.mean(depths))
    half = len(depths) // 2
    row = {
        "case": "incline", "method": method, "resolution": _resolution(method, INCLINE_SIDE_MM / size, spacing_mm),
        "texel_mm": INCLINE_SIDE_MM / size, "spacing_mm": spacing_mm, "film_mm": film_mm,
        "flux_per_width_mm2_s": q, "feed_ml_s": rate,
        "measures": [{"quantity": f"steady depth, Nusselt {film_mm:g} mm", "unit": "mm", "reference": film_mm,
                      "measured": measured, "error_rel": measured / film_mm - 1.0}],
        "unsteadiness_rel": float(np.mean(depths[half:]) / max(np.mean(depths[:half]), 1e-30) - 1.0) if half else 0.0,
        "simulated_s": steps * DT_S, "wall_s": clock.seconds, "ms_per_simulated_s": 1000.0 * clock.seconds / (steps * DT_S),
    }
    if method == "particles":
        speed = float(np.mean(speeds))
        row.update(particles_at_end=int(blood.count), mean_speed_mm_s=speed,
                   nusselt_speed_at_measured_mm_s=G_MM_S2 * math.sin(slope) * measured**2 / (3.0 * nu),
                   window_flux_mm2_s=speed * measured)
    else:
        row["substeps_last_step"] = int(blood.last_substeps)
    return row


# --- hollow -----------------------------------------------------------------------------------------------------------
def hollow(method: str, size: int = 64, spacing_mm: float | None = None) -> dict:
    """0.3 ml poured into the paraboloid hollow against the level pool (module docstring)."""
    from sims.surface.texels import build_surface

    surface = build_surface(hollow_mesh(), size)
    values = height_field_params(**PHYSICS_HF) if method == "height_field" else particle_params(spacing_mm, **PHYSICS_PARTICLES)
    capacity = 0
    if method == "particles":
        from sims.blood.particles import particle_volume_ml

        capacity = int(math.ceil(HOLLOW_VOLUME_ML / particle_volume_ml(values))) + 256
    blood = _model(method, surface, values, capacity)
    centre = _nearest_texel(surface, (0.0, 0.0, 0.0))
    rate = HOLLOW_VOLUME_ML / HOLLOW_POUR_S
    blood.spawn_rate("pour", centre, rate, DT_S, 1.0)
    blood.step(DT_S)  # compiles the kernels
    blood.reset()
    pour, steps = int(round(HOLLOW_POUR_S / DT_S)), int(round((HOLLOW_POUR_S + HOLLOW_SETTLE_S) / DT_S))
    clock = _Clock()
    with clock:
        for index in range(steps):
            if index < pour:
                blood.spawn_rate("pour", centre, rate, DT_S, 1.0)
            blood.step(DT_S)
    thickness = blood.state_arrays()["blood_thickness_mm"].astype(np.float64)
    r = np.hypot(surface.position_mm[..., 0], surface.position_mm[..., 1])
    depth = float(thickness[surface.mask & (r < HOLLOW_CENTRE_MM)].mean())
    area = float(surface.texel_area_mm2[surface.mask & (thickness >= HOLLOW_WET_MM)].sum(dtype=np.float64))
    pool = level_pool(HOLLOW_VOLUME_ML)
    metrics = blood.metrics()
    return {
        "case": "hollow", "method": method, "resolution": _resolution(method, 2 * HOLLOW_HALF_MM / size, spacing_mm),
        "texel_mm": 2 * HOLLOW_HALF_MM / size, "spacing_mm": spacing_mm, "level_pool": pool,
        "measures": [
            {"quantity": "centre depth (r < 1 mm)", "unit": "mm", "reference": pool["depth_mm"], "measured": depth,
             "error_rel": depth / pool["depth_mm"] - 1.0},
            {"quantity": "wetted area (>= 0.01 mm)", "unit": "mm²", "reference": pool["surface_area_mm2"], "measured": area,
             "error_rel": area / pool["surface_area_mm2"] - 1.0},
        ],
        "on_surface_ml": metrics["on_surface_ml"], "left_surface_ml": metrics["left_surface_ml"],
        "own_blood_area_mm2": metrics["blood_area_mm2"], "max_thickness_mm": metrics["max_thickness_mm"],
        "simulated_s": steps * DT_S, "wall_s": clock.seconds, "ms_per_simulated_s": 1000.0 * clock.seconds / (steps * DT_S),
    }


# --- dam break ----------------------------------------------------------------------------------------------------------
def _ritter_lattice(spacing_mm: float, film_mm: float) -> np.ndarray:
    """(x, y) mm of a hexagonal lattice filling the reservoir [0, DAM_MM] x [0, width] with H0_MM of blood per area."""
    spacing = spacing_mm * math.sqrt(film_mm / H0_MM)   # particle volume = hexagon(spacing_mm) x film
    row_height = spacing * math.sqrt(3.0) / 2.0
    points = []
    for j in range(int(STRIP_MM[1] / row_height)):
        offset = (0.25 if j % 2 == 0 else 0.75) * spacing
        points += [(offset + i * spacing, (j + 0.5) * row_height) for i in range(int((DAM_MM - offset) / spacing) + 1)]
    return np.asarray(points, np.float64)


def ritter(method: str, texel_mm: float = 1.0, spacing_mm: float | None = None, film_mm: float | None = None) -> dict:
    """Release of h0 of blood on a level strip against Ritter's solution (module docstring). Particles: film_mm is their
    film thickness (None: the default 0.3 mm, so the reservoir starts compressed to h0 / film; H0_MM: at rest density)."""
    if method == "height_field":
        surface, size = strip_surface(texel_mm)
        values = height_field_params(**PHYSICS_HF, blood_viscosity_mpa_s=0.0)
        blood = _model(method, surface, values, walls=True)
        x = surface.position_mm[..., 0].astype(np.float64)
        start = np.where(surface.mask & (x < DAM_MM), H0_MM, 0.0)

        def begin():
            blood.set_depth(start)
    else:
        texel_mm = PARTICLE_TEXTURE["ritter_texel_mm"]
        surface, size = strip_surface(texel_mm)
        values = particle_params(spacing_mm, **PHYSICS_PARTICLES, blood_viscosity_mpa_s=0.0, viscosity_sigma_1_s=0.0,
                                 viscosity_beta_s_mm=0.0, max_speed_mm_s=1.0e5)
        if film_mm is not None:
            values["film_thickness_mm"] = film_mm
        lattice = _ritter_lattice(spacing_mm, values["film_thickness_mm"])
        grid = np.stack([lattice[:, 0] / texel_mm, size - lattice[:, 1] / texel_mm], axis=1)
        blood = _model(method, surface, values, capacity=len(lattice), walls=True)

        def begin():
            blood.place(grid)
    begin()
    blood.step(RITTER_DT_S)  # compiles the kernels
    begin()
    steps = int(round(RITTER_S / RITTER_DT_S))
    clock = _Clock()
    with clock:
        for _ in range(steps):
            blood.step(RITTER_DT_S)
    t = steps * RITTER_DT_S
    thickness = blood.state_arrays()["blood_thickness_mm"].astype(np.float64)
    columns = surface.mask.any(axis=0)
    rows = surface.mask.any(axis=1)
    profile = thickness[rows][:, columns].mean(axis=0)
    xs = surface.position_mm[..., 0][rows][:, columns].mean(axis=0).astype(np.float64) - DAM_MM
    c = math.sqrt(G_MM_S2 * H0_MM)
    exact_front = 2.0 * c * t
    if method == "height_field":
        wet = xs[profile >= FRONT_DEPTH_FRACTION * H0_MM]
        front = float(wet.max()) if len(wet) else -DAM_MM
    else:
        x = np.sort(blood.particle_arrays()["particle_position_mm"][:, 0].astype(np.float64)) - DAM_MM
        front = front_position(x)
        median = float(np.median(x))
    wave = (xs > -c * t) & (xs < exact_front)
    profile_error = float(np.abs(profile - ritter_depth(xs, t))[wave].mean() / H0_MM)
    at_dam = float(profile[np.argmin(np.abs(xs))])
    resolution = _resolution(method, texel_mm, spacing_mm)
    if method == "particles":
        resolution += f", {values['film_thickness_mm']:g} mm film"
    at_end = front > STRIP_MM[0] - DAM_MM - 1.0   # at the strip's far wall: the front would be further on a longer strip
    row = {
        "case": "dam break (Ritter)", "method": method, "resolution": resolution,
        "texel_mm": texel_mm, "spacing_mm": spacing_mm,
        "measures": [
            {"quantity": f"front at {t:g} s", "unit": "mm", "reference": exact_front, "measured": front,
             "error_rel": front / exact_front - 1.0, "at_end_wall": bool(at_end)},
            {"quantity": "mean |h - h_Ritter| / h0 over the wave", "unit": "h0", "reference": 0.0, "measured": profile_error,
             "error_rel": profile_error},
        ],
        "depth_at_dam_mm": at_dam, "depth_at_dam_exact_mm": 4.0 * H0_MM / 9.0,
        "simulated_s": t, "wall_s": clock.seconds, "ms_per_simulated_s": 1000.0 * clock.seconds / t,
    }
    if method == "particles":
        row.update(particles=len(grid), film_mm=values["film_thickness_mm"], start_density_over_rest=H0_MM / values["film_thickness_mm"],
                   median_x_mm=median)
    else:
        row["substeps_last_step"] = int(blood.last_substeps)
    return row


def martin_moyce(spacing_mm: float, substeps: int) -> dict:
    """The particles on the dambreak section's vertical-plane water column (lab.bench.dambreak.simulate)."""
    from lab.bench import dambreak

    result = dambreak.simulate(spacing_mm, substeps)
    dambreak._RIGS.clear()
    error = result["error"]
    reference = np.interp(error["T"], *np.asarray(MARTIN_MOYCE).T) if error["points"] else np.array([])
    relative = float(np.mean(np.abs(error["signed_a"]) / (reference - 1.0))) if error["points"] else math.nan
    return {
        "case": "dam break (Martin & Moyce)", "method": "particles", "resolution": f"{spacing_mm:g} mm spacing, {substeps} substeps/ms",
        "texel_mm": result["interaction_radius_mm"] / 2.0, "spacing_mm": spacing_mm,
        "measures": [
            {"quantity": "front, mean |Z - Z_MM| / (Z_MM - 1)", "unit": "", "reference": 0.0, "measured": relative, "error_rel": relative},
            {"quantity": "front, mean |Z - Z_MM|", "unit": "a", "reference": 0.0, "measured": error["mean_abs_a"],
             "error_rel": None, "signed_a": error["mean_signed_a"]},
        ],
        "particles": result["particles"], "simulated_s": result["T"][-1] / dambreak.time_scale_1_s(),
        "wall_s": result["wall_s"], "ms_per_simulated_s": result["ms_per_simulated_s"],
    }


# --- cost as the bled volume grows ----------------------------------------------------------------------------------------
def cost_growth(method: str, marks_ml, divisor: int = 8, spacing_mm: float | None = None) -> dict:
    """Cost per simulated second after each bled volume in marks_ml at BLEED_RATE_ML_S on the patch at the lab's
    COST_TEXTURE display (product defaults; the height field on a grid `divisor` times coarser, as bleeding.grid_divisor)."""
    from sims.surface.resample import model_grid
    from sims.surface.texels import build_surface, load_mesh

    display = build_surface(load_mesh(REPO_ROOT / "static/meshes/patch.obj"), COST_TEXTURE)
    values = height_field_params(grid_divisor=divisor) if method == "height_field" else particle_params(spacing_mm)
    surface, resampler = model_grid(display, divisor) if method == "height_field" else (display, None)
    size = surface.size
    texel = float(np.median(np.linalg.norm(surface.tangent_u[surface.mask], axis=1)))
    capacity = 0
    if method == "particles":
        from sims.blood.particles import auto_capacity

        duration = max(marks_ml) / BLEED_RATE_ML_S + COST_STEPS * DT_S
        capacity = auto_capacity([{"rate_ml_s": BLEED_RATE_ML_S, "path": []}], values, duration)
    blood = _model(method, surface, values, capacity, display=resampler)
    vessel = _nearest_texel(display, BLEED_AT_MM)

    def one():
        blood.spawn_rate("vessel", vessel, BLEED_RATE_ML_S, DT_S, BLEED_RADIUS_MM)
        blood.step(DT_S)

    one()  # compiles the kernels
    blood.reset()
    points, clock, done = [], _Clock(), 0
    for mark in marks_ml:
        steps = int(math.ceil(mark / (BLEED_RATE_ML_S * DT_S) - 1e-9)) - done  # to the mark (counted: metrics() would splat)
        with clock:
            for _ in range(steps):
                one()
        metrics = blood.metrics()  # at the mark (its last step); the cost is that of the next COST_STEPS steps
        point = {"mark_ml": mark, "bled_ml": metrics["spawned_ml"], "on_surface_ml": metrics["on_surface_ml"],
                 "left_surface_ml": metrics["left_surface_ml"], "max_thickness_mm": metrics["max_thickness_mm"]}
        if method == "particles":
            point.update(particles=int(metrics["alive"]), dropped_pool_full=int(metrics["dropped_pool_full"]))
        else:
            point.update(awake_tiles=int(blood.tiles.awake), substeps=int(blood.last_substeps))
        wall = synced_seconds(one, COST_STEPS, COST_CHUNKS)
        clock.seconds += wall
        done += steps + COST_STEPS
        point.update(ms_per_simulated_s=1000.0 * wall / (COST_STEPS * DT_S), wall_so_far_s=clock.seconds)
        points.append(point)
    resolution = _resolution(method, texel, spacing_mm) + (f" (display {COST_TEXTURE}², 1/{divisor})" if method == "height_field" else "")
    return {"method": method, "resolution": resolution, "texel_mm": texel,
            "spacing_mm": spacing_mm, "texture_size": size, "capacity": capacity, "points": points}


# --- the section ------------------------------------------------------------------------------------------------------------
def run(quick: bool) -> dict:
    plan = QUICK if quick else FULL
    sizes, spacings = plan["height_field_sizes"], plan["spacings_mm"]
    cases = []
    for film in plan["incline_films_mm"]:
        cases += [incline("height_field", film, size=size) for size in sizes["incline"]]
        cases += [incline("particles", film, size=PARTICLE_TEXTURE["incline"][s], spacing_mm=s) for s in spacings]
    cases += [hollow("height_field", size=size) for size in sizes["hollow"]]
    cases += [hollow("particles", size=PARTICLE_TEXTURE["hollow"][s], spacing_mm=s) for s in spacings]
    cases += [ritter("height_field", texel_mm=texel) for texel in sizes["ritter"]]
    cases += [ritter("particles", spacing_mm=s, film_mm=film) for film in (None, H0_MM) for s in spacings]
    cases += [martin_moyce(s, n) for s, n in plan["martin_moyce"]]
    growth = [cost_growth("height_field", plan["marks_ml"], divisor=d) for d in sizes["cost"]]
    growth += [cost_growth("particles", plan["marks_ml"], spacing_mm=s) for s in spacings]
    return json_finite({
        "setup": {"dt_s": DT_S, "radius_ratio": RADIUS_RATIO, "incline_deg": INCLINE_DEG, "bleed_rate_ml_s": BLEED_RATE_ML_S,
                  "hollow_volume_ml": HOLLOW_VOLUME_ML, "h0_mm": H0_MM, "ritter_s": RITTER_S},
        "cases": cases, "growth": growth,
    })


def _number(value, unit: str = "") -> str:
    if value is None:
        return "-"
    text = f"{value:.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    return f"{text} {unit}".strip() if unit and unit != "h0" else text


def render(results: dict) -> list[str]:
    lines = [
        "## Bleeding methods: particles against the height field",
        "",
        "The same cases for both bleeding methods (`sims.blood.particles`, a Clavet film of fixed thickness, 0.3 mm at rest density; "
        "`sims.blood.height_field`, depth per texel through virtual pipes), each at a couple of resolutions. Incline: a film fed "
        "across a 30° plane at the flux per width of a Nusselt film of the stated depth, volume per area in a window down "
        "the slope after 1.2 s. Hollow: 0.3 ml poured into z = r²/100 mm, 1.5 s later, against the level pool (centre "
        "depth 1.38 mm; the wetted cap's surface area 441 mm², projected 434). Dam break (Ritter): 1 mm of blood released "
        "on a level walled strip, frictionless, 0.15 s. Dam break (Martin & Moyce, full run): the particles on the dambreak "
        "section's vertical water column. Incline and hollow without clotting, drying or pinning; the rest product "
        "defaults. Cost: wall ms per simulated second of the run (kernels compiled beforehand). Set-up in "
        "lab/bench/bleeding_methods.py.",
        "",
        "| case | method | resolution | quantity | reference | measured | error | ms per simulated s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in results["cases"]:
        for index, measure in enumerate(row["measures"]):
            error = measure["error_rel"]
            if measure["reference"] == 0.0 or error is None:  # an error already: no reference value to show
                reference, shown = "0", "-" if error is None else f"{error:.3f}"
                if "signed_a" in measure and measure["signed_a"] is not None:
                    shown = f"(signed {measure['signed_a']:+.3f} a)"
            else:
                reference, shown = _number(measure["reference"], measure["unit"]), f"{error:+.1%}"
            measured = _number(measure["measured"], measure["unit"])
            if measure.get("at_end_wall"):  # the far wall stopped it: a lower bound
                measured, shown = f"≥ {measured} (far wall)", f"≥ {shown}"
            cost = f"{row['ms_per_simulated_s']:,.0f}" if index == 0 else "″"
            lines.append(f"| {row['case']} | {row['method']} | {row['resolution']} | {measure['quantity']} | {reference} | "
                         f"{measured} | {shown} | {cost} |")
    lines += ["", *_notes(results["cases"]), ""]
    lines += [
        f"### Cost as the bled volume grows (one bleed point at {results['setup']['bleed_rate_ml_s']:g} ml/s on the patch, product defaults)",
        "",
        "Wall ms per simulated second over the 20 steps right after each bled volume (the fastest of 10 runs of 2 steps, scaled: "
        "a burst of other load does not count); the state (on surface, particles, tiles) is at the mark. Blood runs off "
        "the patch's lower edge, so what is on the surface is given too, with the particles alive or the height field's "
        f"awake {HEIGHT_FIELD_TILE}² tiles and substeps per 0.01 s step. Wall so far: the whole run to that point (compiled kernels).",
        "",
        "| method | resolution | bled (ml) | on surface (ml) | particles / awake tiles (substeps) | max thickness (mm) | ms per simulated s | wall so far (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run_ in results["growth"]:
        for point in run_["points"]:
            size = (f"{point['particles']:,}" if run_["method"] == "particles"
                    else f"{point['awake_tiles']:,} ({point['substeps']})")
            lines.append(f"| {run_['method']} | {run_['resolution']} | {point['bled_ml']:.2f} | {point['on_surface_ml']:.3f} | {size} | "
                         f"{point['max_thickness_mm']:.2f} | {point['ms_per_simulated_s']:,.0f} | {point['wall_so_far_s']:.1f} |")
    lines += ["", *_growth_notes(results["growth"])]
    return lines


def _growth_notes(growth: list) -> list[str]:
    """Particle runs whose blood piles up at the bleed point (splat far above the film), against the height field."""
    from sims.blood.particles import MAX_CANDIDATES
    from sims.scene import params

    film = params.BLEEDING["film_thickness_mm"].default
    field = [r for r in growth if r["method"] == "height_field"]
    notes = []
    for run_ in growth:
        last = run_["points"][-1]
        if run_["method"] == "particles" and last["max_thickness_mm"] > 10 * film:
            kept = ", ".join(f"{r['points'][-1]['on_surface_ml']:.2f} ml ({r['resolution']})" for r in field)
            notes.append(
                f"- Particles at {run_['resolution']}: the blood piles up at the bleed point (splat up to {last['max_thickness_mm']:.0f} mm "
                f"against a {film:g} mm film after {last['mark_ml']:g} ml): the density sum reads at most MAX_CANDIDATES = {MAX_CANDIDATES} "
                "candidates (about 70 at rest for a radius of 3 spacings), so a clump does not feel all of its own pressure; "
                f"{last['on_surface_ml']:.2f} ml stays on the patch ({last['particles']:,} particles) where the height field keeps {kept}.")
    return notes


def _notes(cases: list) -> list[str]:
    """What the table says, from the numbers."""
    notes = []
    for case in ("incline", "hollow", "dam break (Ritter)"):
        for method in ("height_field", "particles"):
            rows = [r for r in cases if r["case"] == case and r["method"] == method]
            if not rows:
                continue
            worst = max(rows, key=lambda r: abs(r["measures"][0]["error_rel"] or 0.0))
            m = worst["measures"][0]
            notes.append(f"- {case}, {method}: worst {m['quantity']} error {m['error_rel']:+.1%} ({worst['resolution']}); "
                         f"cost {min(r['ms_per_simulated_s'] for r in rows):,.0f}-{max(r['ms_per_simulated_s'] for r in rows):,.0f} ms per simulated s.")
    particles = [r for r in cases if r["case"] == "incline" and r["method"] == "particles"]
    if particles:
        notes.append("- The particle film keeps about its rest thickness whatever the flux (the Clavet pressure pulls it back to "
                     "0.3 mm), so it carries the flux at another speed: " + "; ".join(
                         f"{r['resolution']}, Nusselt {r['film_mm']:g} mm: {r['measures'][0]['measured']:.3f} mm at "
                         f"{r['mean_speed_mm_s']:.0f} mm/s (q {r['window_flux_mm2_s']:.1f} against {r['flux_per_width_mm2_s']:.1f} mm²/s fed)"
                         for r in particles) + ".")
    ritter_particles = [r for r in cases if r["case"] == "dam break (Ritter)" and r["method"] == "particles"]
    if ritter_particles:
        notes.append("- Ritter with particles: their pressure is Clavet's equation of state (stiffness and film thickness, not "
                     "g h) and gravity has no part along a level bed, so nothing in the model follows sqrt(g h0): the rows show "
                     "what it does, not a shallow-water solution it is meant to give. With the default 0.3 mm film the 1 mm "
                     f"reservoir starts {ritter_particles[0]['start_density_over_rest']:.1f}x compressed and bursts (not spray: the median "
                     "particle is at " + ", ".join(f"{r['median_x_mm']:+.0f} mm" for r in ritter_particles if r["film_mm"] != H0_MM)
                     + " from the dam at the end); with a 1 mm film it starts at rest density and barely moves (median particle at "
                     + ", ".join(f"{r['median_x_mm']:+.1f} mm" for r in ritter_particles if r["film_mm"] == H0_MM) + ").")
    return notes


def plot(results: dict, out_dir) -> list[str]:
    """bleeding_methods_error_cost.png (error against cost per case) and bleeding_methods_growth.png (cost and blood on
    the surface against the bled volume)."""
    plt = pyplot()
    colours = {"height_field": "tab:blue", "particles": "tab:red", "particles, 1 mm film": "tab:orange"}
    cases = ["incline", "hollow", "dam break (Ritter)", "dam break (Martin & Moyce)"]
    cases = [case for case in cases if any(r["case"] == case for r in results["cases"])]
    fig, axes = plt.subplots(1, len(cases), figsize=(3.7 * len(cases), 3.9), squeeze=False)
    for ax, case in zip(axes[0], cases):
        rows = [r for r in results["cases"] if r["case"] == case]
        quantities, kinds = [], []
        for row in rows:
            kind = "particles, 1 mm film" if row["method"] == "particles" and row.get("film_mm") == H0_MM and "Ritter" in case else row["method"]
            if kind not in kinds:
                kinds.append(kind)
            for measure in row["measures"]:
                if measure["error_rel"] is None:
                    continue
                if measure["quantity"] not in quantities:
                    quantities.append(measure["quantity"])
                which = quantities.index(measure["quantity"])
                error = max(abs(measure["error_rel"]), 1e-4)
                ax.scatter(row["ms_per_simulated_s"], 100 * error, marker="osD^"[which % 4], color=colours[kind],
                           facecolors="none" if which else colours[kind])
                label = row["resolution"].split(",")[0].replace(" mm texels", "").replace(" mm spacing", "")
                if case == "incline":
                    label += f" (h {row['film_mm']:g})"
                if measure.get("at_end_wall"):
                    label = "≥ " + label
                ax.annotate(label, (row["ms_per_simulated_s"], 100 * error), fontsize=6, xytext=(3, 2), textcoords="offset points")
        for kind in kinds:
            ax.scatter([], [], color=colours[kind], label=kind)
        for index, quantity in enumerate(quantities):
            ax.scatter([], [], marker="osD^"[index % 4], color="0.4", facecolors="0.4" if index == 0 else "none", label=quantity)
        ax.set(xscale="log", yscale="log", xlabel="cost: wall ms per simulated second", ylabel="|error|, %", title=case)
        _plain_log_ticks(ax)
        ax.margins(x=0.3, y=0.3)
        ax.legend(fontsize=6)
    fig.suptitle("Error against cost (labels: texel size or particle spacing, mm; ≥: front stopped by the far wall)", fontsize=9)
    written = [save(fig, out_dir, "bleeding_methods_error_cost.png")]

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    for index, run_ in enumerate(results["growth"]):
        points = run_["points"]
        style = "-" if index % 2 == 0 else "--"
        label = f"{run_['method']}, {run_['resolution']}"
        bled = [p["mark_ml"] for p in points]
        left.loglog(bled, [p["ms_per_simulated_s"] for p in points], "o" + style, color=colours[run_["method"]], label=label)
        right.plot(bled, [p["on_surface_ml"] for p in points], "o" + style, color=colours[run_["method"]], label=label)
    left.axhline(1000.0, color="k", lw=0.8, ls=":", label="real time")
    left.set(xlabel="bled volume (ml)", ylabel="wall ms per simulated second", title="Cost against bled volume (1 ml/s, patch)")
    right.set(xscale="log", xlabel="bled volume (ml)", ylabel="blood on the surface (ml)", title="Blood kept on the patch")
    for ax in (left, right):
        _plain_log_ticks(ax, y=ax is left)
        ax.legend(fontsize=7)
    written.append(save(fig, out_dir, "bleeding_methods_growth.png"))
    return written


def _plain_log_ticks(ax, y: bool = True) -> None:
    """Log axes labelled 0.1, 1, 10, 1000 (no minor labels, which overlap)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axes = (ax.xaxis, ax.yaxis) if y else (ax.xaxis,)
    for axis in axes:
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        axis.set_minor_formatter(NullFormatter())
