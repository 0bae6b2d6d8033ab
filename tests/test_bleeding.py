"""Blood: gravity through the metric, resolution independence, accounting, settling, hard cases,
determinism, cautery stopping bleeding and suction."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from lab.reference.meshes import plane_mesh
from sims.blood.particles import Bleeding
from sims.scene import params
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT, load_scene_config
from sims.surface.texels import build_surface, load_mesh

DEFAULTS = {name: spec.default for name, spec in params.BLEEDING.items()}
GRAVITY = [0.0, 0.0, -9810.0]
HOLLOW_MM = (-7.0, 10.0)  # the dimple of static/meshes/patch.obj (tools/make_static.py)


def bleeding_on(surface, capacity=20_000, **changes):
    return Bleeding(surface, {**DEFAULTS, **changes}, GRAVITY, capacity)


def sorted_pool(bleeding) -> dict:
    """The alive particles' sort order, positions, velocities and ids, to compare two pools bytewise."""
    return {name: getattr(bleeding, name).to_numpy()[:bleeding.count] for name in ("sorted", "pos", "vel", "uid")}


def assert_accounting(bleeding):
    counts = bleeding.accounting()
    assert counts["spawned"] == counts["alive"] + counts["suctioned"] + counts["left_surface"] + counts["expired"], counts
    return counts


@pytest.mark.parametrize("width_mm, length_mm", [(60.0, 60.0), (30.0, 60.0)])
def test_lone_particle_accelerates_at_g_sin_theta(width_mm, length_mm):
    """30 degree incline; the 30 x 60 mm plane maps onto square UVs: stretched 2:1 along the slope."""
    surface = build_surface(plane_mesh(width_mm, length_mm, slope_deg=30.0), 128)
    bleeding = bleeding_on(surface, viscosity_sigma_1_s=0.0, viscosity_beta_s_mm=0.0, blood_viscosity_mpa_s=0.0,
                           inertia=1.0, max_speed_mm_s=1.0e5)
    bleeding.spawn((8, 64), 1, 0.0)  # near the top (+y, uphill)
    start = bleeding.particle_arrays()["particle_position_mm"][0].copy()
    dt, steps = 0.01, 10
    for _ in range(steps):
        bleeding.step(dt)
    state = bleeding.particle_arrays()
    speed = np.linalg.norm(state["particle_velocity_mm_s"][0])
    expected = 9810.0 * math.sin(math.radians(30.0))
    assert speed / (steps * dt) == pytest.approx(expected, rel=0.02)
    travelled = np.linalg.norm(state["particle_position_mm"][0] - start)
    assert travelled == pytest.approx(0.5 * expected * (steps * dt) ** 2, rel=0.06)  # symplectic Euler: (n+1)/n
    direction = (state["particle_position_mm"][0] - start) / travelled
    assert direction @ [0.0, -math.cos(math.radians(30.0)), -0.5] == pytest.approx(1.0, abs=1e-3)  # straight downhill


@pytest.mark.parametrize("width_mm, length_mm", [(24.0, 24.0), (24.0, 48.0)])
@pytest.mark.parametrize("approaching", [True, False])
def test_viscosity_impulse_of_a_pair_is_clavets(width_mm, length_mm, approaching):
    """Two particles 0.5 h apart moving along their line, nothing else acting (no pressure, gravity, drag or clotting):
    after one substep an approaching pair has each lost half of Clavet's impulse dt q (sigma u + beta u^2) (u the
    approach speed, q at their advanced distance), a receding pair keeps its speed. Also with 2:1 stretched texels."""
    surface = build_surface(plane_mesh(width_mm, length_mm), 128)
    sigma, beta, dt, speed = 5.0, 0.05, 0.01, 20.0  # 1/s, s/mm, s, mm/s of each particle
    bleeding = bleeding_on(surface, viscosity_sigma_1_s=sigma, viscosity_beta_s_mm=beta, blood_viscosity_mpa_s=0.0,
                           stiffness_mm_s2=0.0, near_stiffness_mm_s2=0.0, inertia=1.0, clotting_rate_1_s=0.0,
                           max_speed_mm_s=1.0e5, substeps=1)
    h, texel_mm = DEFAULTS["interaction_radius_mm"], width_mm / 128
    apart_mm = 0.5 * h
    bleeding.place(np.array([[64.0 - apart_mm / 2 / texel_mm, 64.0], [64.0 + apart_mm / 2 / texel_mm, 64.0]]))
    toward = 1.0 if approaching else -1.0
    velocity = np.zeros((bleeding.pool_size, 2), np.float32)
    velocity[:2, 0] = [toward * speed / texel_mm, -toward * speed / texel_mm]  # grid units / s
    bleeding.vel.from_numpy(velocity)
    bleeding.step(dt)
    after = bleeding.particle_arrays()["particle_velocity_mm_s"]
    expected = speed
    if approaching:
        u = 2.0 * speed
        q = 1.0 - (apart_mm - u * dt) / h
        expected = speed - 0.5 * min(dt * q * (sigma * u + beta * u * u), u)
    assert expected < speed or not approaching
    for index, sign in ((0, toward), (1, -toward)):
        assert after[index] == pytest.approx([sign * expected, 0.0, 0.0], rel=1e-4, abs=1e-3)


def scene_config(changes: dict):
    """The bleeding scene with the particle method (the method these tests are about) and these changes."""
    changes = {"bleeding.method": "particles", **changes}
    return load_scene_config(REPO_ROOT / "scenes" / "bleeding.yaml", [f"{k}={json.dumps(v)}" for k, v in changes.items()])


def test_blood_area_is_independent_of_texture_size():
    areas = []
    for size in (256, 512):
        scene = Scene(scene_config({"texture_size": size}))
        while scene.time_s < 1.0 - 1e-9:
            scene.step()
        areas.append(scene.metrics()["bleeding"]["blood_area_mm2"])
    assert areas[0] > 20.0
    assert abs(areas[0] / areas[1] - 1) < 0.15, areas


def test_reading_the_blood_area_keeps_the_fading_trails_on_display():
    scene = Scene(scene_config({"texture_size": 128, "look.blood_trail_s": 5.0}))
    for _ in range(60):
        scene.step()
    shown = scene.film.trail.to_numpy()
    assert shown.max() > 0.0
    assert scene.metrics()["bleeding"]["blood_area_mm2"] > 0.0
    scene.composite()
    assert np.array_equal(scene.film.trail.to_numpy(), shown)  # metrics and pictures (the lab's stats) keep the trails


def test_accounting_holds_at_every_step():
    changes = {
        "texture_size": 128,
        "bleeding.lifetime_s": 0.6,
        "bleed_points": [
            {"name": "top", "position_mm": [8.0, 14.0, 4.0], "rate_ml_s": 0.05},
            {"name": "edge", "position_mm": [0.0, -19.5, -5.5], "rate_ml_s": 0.05},  # at the lower border: leaves
        ],
        "instruments": [{
            "name": "sucker", "shape": {"type": "capsule", "radius_mm": 1.5}, "position_mm": [8.0, 10.0, 5.0],
            "energized": True, "suction": {"radius_mm": 6.0, "rate_ml_s": 0.02},
        }],
    }
    scene = Scene(scene_config(changes))
    for _ in range(150):
        scene.step()
        counts = assert_accounting(scene.bleeding)
    assert all(counts[key] > 0 for key in ("alive", "suctioned", "left_surface", "expired")), counts


def settle(substeps: int, seconds: float = 3.0, particles: int = 80):
    """A blob smaller than the hollow, released in it: (bleeding, mean density error, speeds, centroid drift in the last second)."""
    surface = build_surface(load_mesh(REPO_ROOT / "static/meshes/patch.obj"), 256)
    bleeding = bleeding_on(surface, substeps=substeps)
    positions = surface.position_mm
    distance = np.linalg.norm(positions[..., :2] - HOLLOW_MM, axis=-1) + np.where(surface.mask, 0, np.inf)
    texel = np.unravel_index(np.argmin(distance), distance.shape)
    bleeding.spawn(texel, particles, 1.0)
    steps = int(round(seconds / 0.01))
    for step in range(steps):
        bleeding.step(0.01)
        if step == steps - 101:
            centroid = bleeding.particle_arrays()["particle_position_mm"].mean(axis=0)
    rho = bleeding.density.to_numpy()[: bleeding.count, 0]
    state = bleeding.particle_arrays()
    drift = np.linalg.norm(state["particle_position_mm"].mean(axis=0) - centroid)
    return bleeding, rho.mean() / bleeding.rest_density - 1.0, np.linalg.norm(state["particle_velocity_mm_s"], axis=1), drift


def test_blob_settles_in_the_hollow_near_rest_density():
    bleeding, density_error, speed, drift = settle(substeps=int(DEFAULTS["substeps"]))
    assert bleeding.count == 80  # nothing ran out of the hollow
    assert drift < 0.1  # mm in the last second: at rest
    assert abs(density_error) < 0.10


def run_steps(bleeding, steps, dt):
    for _ in range(steps):
        bleeding.step(dt)
        assert_accounting(bleeding)


def assert_bounded(bleeding, max_speed, label=""):
    state = bleeding.particle_arrays()
    for name, values in state.items():
        assert np.isfinite(values).all(), (label, name)
    speed = np.linalg.norm(state["particle_velocity_mm_s"], axis=1)
    assert (speed <= max_speed * 1.001 + 1e-3).all(), (label, speed.max())
    assert ((state["particle_uv"] >= 0) & (state["particle_uv"] <= 1)).all()


@pytest.fixture(scope="module")
def patch_256():
    return build_surface(load_mesh(REPO_ROOT / "static/meshes/patch.obj"), 256)


@pytest.mark.parametrize("case", ["rest_density_50", "time_step_x10", "border"])
def test_hard_cases_stay_finite_and_bounded(patch_256, case):
    changes = {"rest_density": 50.0} if case == "rest_density_50" else {}
    bleeding = bleeding_on(patch_256, **changes)
    texel = (128, 128) if case != "border" else (255, 3)
    bleeding.spawn(texel, 2000, 2.0)
    run_steps(bleeding, 50, 0.1 if case == "time_step_x10" else 0.01)
    assert_bounded(bleeding, DEFAULTS["max_speed_mm_s"])
    if case == "border":
        assert bleeding.accounting()["left_surface"] > 0


def texel_gravity(surface, gravity_mm_s2, rows, cols):
    """G^-1 J^T g (grid units / s^2) at these texels, in float64: the tangential part of gravity in texel steps."""
    ex, ey = surface.tangent_u[rows, cols].astype(np.float64), -surface.tangent_v[rows, cols].astype(np.float64)
    metric = surface.metric[rows, cols].astype(np.float64)
    rhs = np.stack([ex @ gravity_mm_s2, ey @ gravity_mm_s2], axis=1)
    return np.linalg.solve(metric, rhs[..., None])[..., 0]


def test_particles_carry_the_metric_and_gravity_of_the_texel_they_are_in(patch_256):
    """Flowing blood on the curved patch: after each step every particle's metric and gravity (which it carries and
    reads again only after it moves) are those of the texel under it, also after gravity turns."""
    bleeding = bleeding_on(patch_256, capacity=2000)
    bleeding.spawn((60, 200), 1500, 2.0)  # on the slope of the dimple: the blood runs down across many texels
    for gravity in (GRAVITY, [6000.0, 0.0, -6000.0]):
        bleeding.set_gravity(gravity)
        for _ in range(15):
            bleeding.step(0.01)
            n = bleeding.count
            assert n > 1000
            pos = bleeding.pos.to_numpy()[:n]
            rows, cols = np.floor(pos[:, 1]).astype(int), np.floor(pos[:, 0]).astype(int)
            metric = patch_256.metric[rows, cols]
            np.testing.assert_allclose(bleeding.metric.to_numpy()[:n], np.stack([metric[:, 0, 0], metric[:, 0, 1], metric[:, 1, 1]], axis=1), rtol=1e-6)
            np.testing.assert_allclose(bleeding.gravity.to_numpy()[:n], texel_gravity(patch_256, np.asarray(gravity, np.float64), rows, cols), rtol=1e-4, atol=1e-3)
    moved = np.linalg.norm(bleeding.particle_arrays()["particle_velocity_mm_s"], axis=1)
    assert np.median(moved) > 1.0  # still flowing: the texels changed under the particles


def test_particles_at_rest_off_the_surface_leave_it_at_the_first_step(patch_256):
    """A particle reads its texel again only when it enters another one; one placed (or spawned) at rest where there is
    no surface must still leave at its first step, not stay because it did not move."""
    bleeding = Bleeding(patch_256, DEFAULTS, (0.0, 0.0, 0.0), 10)
    bleeding.place(np.array([[-0.5, 100.5], [100.5, -0.5], [300.5, 50.5], [60.5, 60.5], [190.5, 190.5]], np.float32))
    bleeding.step(0.01)
    counts = assert_accounting(bleeding)
    assert counts["left_surface"] == 3 and counts["alive"] == 2, counts


def test_density_sums_every_pair_in_range_once(patch_256):
    """The density pass against all pairs in NumPy on a corner of the curved patch (the metric varies per texel):
    the candidate runs (three rows of cells h/4 wide, walked in whole vectors) hold every neighbour once."""
    rows, cols = np.nonzero(patch_256.mask[:96, :96])  # a corner of the patch, where the metric changes most
    rng = np.random.default_rng(5)
    texels = rng.choice(len(rows), 2500, replace=False)
    grid = np.stack([cols[texels], rows[texels]], axis=1) + rng.uniform(0.0, 1.0, (len(texels), 2))
    bleeding = bleeding_on(patch_256, capacity=len(grid))
    bleeding.place(grid.astype(np.float32))
    bleeding.step(1e-7)  # sorts and sums the density; moves nothing measurable (gravity x dt^2 ~ 1e-10 mm)
    n = bleeding.count
    assert n == len(grid)
    pos, metric = bleeding.pos.to_numpy()[:n].astype(np.float64), bleeding.metric.to_numpy()[:n].astype(np.float64)
    h = DEFAULTS["interaction_radius_mm"]
    expected = np.zeros(n)
    for i in range(n):
        d = pos - pos[i]
        m = 0.5 * (metric + metric[i])
        r = np.sqrt(np.maximum(m[:, 0] * d[:, 0] ** 2 + 2 * m[:, 1] * d[:, 0] * d[:, 1] + m[:, 2] * d[:, 1] ** 2, 0.0))
        q = np.where((r < h) & (np.arange(n) != i), 1.0 - r / h, 0.0)
        expected[i] = (q**2).sum()
    assert expected.mean() > 5.0  # neighbours enough to miss some
    np.testing.assert_allclose(bleeding.density.to_numpy()[:n, 0], expected, rtol=1e-4, atol=1e-4)


def test_dense_clump_of_100k_particles_in_one_cell(patch_256):
    bleeding = bleeding_on(patch_256, capacity=100_000)
    assert bleeding.spawn((128, 128), 100_000, 0.0) == 100_000  # all on one point
    run_steps(bleeding, 3, 0.01)
    assert_bounded(bleeding, DEFAULTS["max_speed_mm_s"])
    assert bleeding.accounting()["spawned"] == 100_000


@pytest.mark.parametrize("end", ["min", "max"])
def test_every_slider_at_each_end(patch_256, end):
    bleeding = bleeding_on(patch_256, capacity=3000)
    for name, spec in params.BLEEDING.items():
        if name == "capacity":
            continue
        bleeding.params.update(DEFAULTS, **{name: spec.min if end == "min" else spec.max})
        bleeding.reset()
        bleeding.spawn((128, 128), 400, 1.0)
        run_steps(bleeding, 5, 0.01)
        assert_bounded(bleeding, bleeding.params["max_speed_mm_s"], name)


def test_a_parameter_changed_between_steps_acts_at_the_next_step(patch_256):
    """The step's scalars sit on the device and are written only when they change (sims.blood.particles.STEP_VALUES): a slider
    moved between two steps acts at the next one."""
    same, changed = (bleeding_on(patch_256, capacity=1000) for _ in range(2))
    for pool in (same, changed):
        pool.spawn((128, 128), 400, 1.0)
        run_steps(pool, 10, 0.01)
    assert np.array_equal(same.pos.to_numpy(), changed.pos.to_numpy())
    changed.params["stiffness_mm_s2"] = params.BLEEDING["stiffness_mm_s2"].max
    for pool in (same, changed):
        pool.step(0.01)
    assert not np.array_equal(same.pos.to_numpy()[:400], changed.pos.to_numpy()[:400])
    changed.params["lifetime_s"] = params.BLEEDING["lifetime_s"].min  # 0.1 s: the blood is 0.11 s old
    changed.step(0.01)
    counts = assert_accounting(changed)
    assert counts["alive"] == 0 and counts["expired"] > 0, counts


def test_the_step_whose_pool_outgrows_the_launching_thread_compiles_nothing(patch_256):
    """A pool that can outgrow the launching thread's share (sims.core.backend.serial) has the thread pool's kernels
    compiled with it: the step on which the pool crosses the share compiles no kernel (compiled on that step, they
    stalled the lab 1.9 s), and the step runs on."""
    from sims.blood.particles import PARTICLE_LOOP_ITEMS
    from sims.core import backend

    bleeding = Bleeding(patch_256, dict(DEFAULTS), (0.0, 0.0, 0.0), 12_000)
    bleeding.spawn((128, 128), 200, 2.0)
    bleeding.step(0.01)  # a small pool: the launching thread's kernel
    compiled = len(Bleeding._passes._primal.compiled_kernels)
    bleeding.spawn((128, 128), 11_000, 4.0)
    assert not backend.serial(PARTICLE_LOOP_ITEMS * bleeding.count), bleeding.count
    bleeding.step(0.01)
    assert len(Bleeding._passes._primal.compiled_kernels) == compiled
    assert_bounded(bleeding, DEFAULTS["max_speed_mm_s"])


def test_a_pool_of_a_million_particles_takes_under_300_mb(patch_256):
    """The fields sized by the pool grow linearly: bytes per particle x 1M (issue 13)."""
    per_particle = bleeding_on(patch_256, capacity=1000).memory_bytes()["particles"] / 1000
    assert per_particle * 1_000_000 < 300e6


def test_pool_full_is_counted_not_silent(patch_256):
    bleeding = bleeding_on(patch_256, capacity=100)
    assert bleeding.spawn((128, 128), 150, 1.0) == 100
    counts = bleeding.accounting()
    assert counts["spawned"] == 100 and counts["dropped_pool_full"] == 50


def test_same_scene_twice_gives_identical_state():
    states = []
    for _ in range(2):
        scene = Scene(scene_config({"texture_size": 128}))
        for _ in range(60):
            scene.step()
        states.append(scene.state_arrays())
    for key in states[0]:
        assert np.array_equal(states[0][key], states[1][key]), key


def test_the_gpu_sort_orders_the_pool_as_the_serial_sort(monkeypatch):
    """The counting sort a GPU runs (prefix sum by blocks of keys, each particle into any free slot of its key, then
    each cell's slots in index order) puts the pool in the serial sort's order: the same bytes after 10 steps of
    30,000 particles flowing down the bench's disk (21,000 cells: 21 blocks of keys), every loop parallel."""
    from lab.bench.bleeding import _defaults, build_plane
    from lab.reference.sph import disk_positions
    from sims.core import backend

    monkeypatch.setattr(backend, "SERIAL_BELOW_ITEMS", 0)
    values = _defaults()
    positions = disk_positions(30_000, values["particle_spacing_mm"])
    side = 2.4 * float(np.abs(positions).max())
    grid = (positions / side + 0.5) * 1024
    grid[:, 1] = 1024 - grid[:, 1]
    states = []
    for parallel_sort in (False, True):
        bleeding = Bleeding(build_plane(side, 1024), values, (0.0, -3000.0, 0.0), 30_000, parallel_sort=parallel_sort)
        bleeding.place(grid)
        for _ in range(10):
            bleeding.step(0.01)
        assert bleeding.cells_x * bleeding.cells_y > 20 * 1024 and 0 < bleeding.count
        assert_accounting(bleeding)
        states.append(sorted_pool(bleeding))
    for name in states[0]:
        assert np.array_equal(states[0][name], states[1][name]), name


@pytest.mark.parametrize("count, levels", [(700, 1), (20_000, 2)])
def test_the_gpu_sort_orders_a_dense_clump_as_the_serial_sort(patch_256, monkeypatch, count, levels):
    """A clump on one point, one cell: the GPU sort's runs of 32 ranked, then merged 32 at a time (one level, its
    result copied back from the scratch, for a pool under 1,024; two, runs of 1,024 then the cell, above) give the
    serial sort's order, every loop parallel, as the clump bursts."""
    from sims.core import backend

    monkeypatch.setattr(backend, "SERIAL_BELOW_ITEMS", 0)
    states = []
    for parallel_sort in (False, True):
        bleeding = Bleeding(patch_256, dict(DEFAULTS), GRAVITY, count, parallel_sort=parallel_sort)
        assert bleeding._merge_levels == levels
        assert bleeding.spawn((128, 128), count, 0.0) == count
        bleeding.step(0.01)
        largest = np.diff(bleeding.cell_start.to_numpy()[:bleeding.cells_x * bleeding.cells_y + 1]).max()
        assert largest > 32 ** levels, largest  # still a clump at the step's last sort: every level merged
        run_steps(bleeding, 2, 0.01)
        states.append(sorted_pool(bleeding))
    for name in states[0]:
        assert np.array_equal(states[0][name], states[1][name]), name


@pytest.mark.parametrize("method, scene, duration", [("particles", "bleeding.yaml", "0.5"), ("height_field", "bleeding.yaml", "0.5"),
                                                     ("height_field", "hemostasis.yaml", "2.6")])  # the last: with suction
def test_identical_state_with_one_and_two_threads_and_with_small_loops_serial(tmp_path, method, scene, duration):
    """The same bytes on 1 and 2 threads with every loop parallel (TISSUE_LAB_SERIAL_BELOW=0), and with small loops on
    the launching thread (the default, sims.core.backend.serial)."""
    outputs = []
    for threads, serial_below in (("1", "0"), ("2", "0"), ("2", None)):
        out = tmp_path / f"threads{threads}_{serial_below}"
        env = {**__import__("os").environ, "TISSUE_LAB_THREADS": threads}
        if method == "particles":  # compiled as the lab does: without Taichi's advanced optimisation the serial and
            env["TISSUE_LAB_QUICK_COMPILE"] = "0"  # parallel particle steps round differently (tests/conftest.py)
        env.pop("TISSUE_LAB_SERIAL_BELOW", None)
        if serial_below is not None:
            env["TISSUE_LAB_SERIAL_BELOW"] = serial_below
        result = subprocess.run([sys.executable, "-m", "lab", "run", str(REPO_ROOT / "scenes" / scene), "--out", str(out),
                                 "--duration", duration, "--set", "texture_size=128", "--set", f"bleeding.method={method}",
                                 "--arch", "cpu", "--quiet"],
                                capture_output=True, text=True, cwd=REPO_ROOT, env=env)
        assert result.returncode == 0, result.stderr
        outputs.append((out / "state.npz").read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]


def surface_height(x_mm: float, y_mm: float) -> float:
    vertices = load_mesh(REPO_ROOT / "static/meshes/patch.obj").vertices
    return float(vertices[np.argmin(((vertices[:, :2] - [x_mm, y_mm]) ** 2).sum(axis=1)), 2])


def test_cautery_stops_bleeding():
    """A hot ball pressed on the vessel coagulates the tissue under it; the bleed rate falls to zero."""
    x, y = 8.0, 14.0
    z = surface_height(x, y)
    scene = Scene(scene_config({
        "texture_size": 128,
        "models": ["cautery", "bleeding"],
        "bleed_points": [{"name": "vessel", "position_mm": [x, y, z], "rate_ml_s": 0.05}],
        "instruments": [{"name": "ball", "shape": {"type": "ball", "radius_mm": 2.0}, "position_mm": [x, y, z + 5.0],
                         "path": [{"t_s": 0.3, "position_mm": [x, y, z + 5.0]},
                                  {"t_s": 0.4, "position_mm": [x, y, z + 1.5], "energized": True}]}],
    }))
    for _ in range(30):
        scene.step()
    assert scene.bleed_rates()["vessel"] == pytest.approx(0.05, rel=1e-3)  # 37 C tissue coagulates negligibly
    bled = scene.bleeding.accounting()["spawned"]
    assert bled > 0
    for _ in range(100):
        scene.step()
    assert scene.bleed_rates()["vessel"] < 1e-6
    spawned = scene.bleeding.accounting()["spawned"]
    for _ in range(20):
        scene.step()
    assert scene.bleeding.accounting()["spawned"] == spawned


def test_suction_removes_blood_inside_its_radius_only(patch_256):
    bleeding = bleeding_on(patch_256, clotting_rate_1_s=10.0, rest_speed_mm_s=50.0)
    centre = patch_256.position_mm[128, 128]
    far = patch_256.position_mm[128, 200]
    bleeding.spawn((128, 128), 200, 1.0)
    bleeding.spawn((128, 200), 200, 1.0)
    for _ in range(20):  # let it clot in place
        bleeding.step(0.01)
    before = bleeding.particle_arrays()["particle_position_mm"]
    inside_before = np.linalg.norm(before - centre, axis=1) < 4.0
    bleeding.step(0.01, suction=[(centre, 4.0, 100.0)])
    after = bleeding.particle_arrays()["particle_position_mm"]
    assert bleeding.accounting()["suctioned"] == inside_before.sum() > 100
    assert (np.linalg.norm(after - centre, axis=1) >= 4.0).all()
    assert (np.linalg.norm(after - far, axis=1) < 4.0).sum() == (np.linalg.norm(before - far, axis=1) < 4.0).sum()
