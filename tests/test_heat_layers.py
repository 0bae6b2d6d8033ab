"""Heat in depth: the column solve, Carslaw and Jaeger's slab, the 3D reference, sleeping tiles and the hard cases."""
import math

import numpy as np
import pytest
from scipy.special import erf

from lab.reference.meshes import plane_mesh
from sims.heat import layers
from sims.heat.cautery import Cautery
from sims.scene import params
from sims.scene.instruments import Instrument, InstrumentFields
from sims.surface.texels import build_surface
from testing.helpers import cautery_values, tissue_values

BODY = 37.0


def test_column_elimination_solves_the_backward_euler_system():
    """The tabulated bottom-up elimination gives numpy's solution of the same tridiagonal system, for every solved
    depth n (the layer below held) and both bottoms."""
    faces = layers.layer_faces(10, 6.0)
    rng = np.random.default_rng(4)
    for bottom in layers.BOTTOMS:
        up, down, pivot, carry = layers.elimination_tables(faces, bottom, 0.05, 0.14, 3.4e-3)
        for n in (1, 4, 10):
            matrix = np.diag(1.0 + up[:n] + down[:n] + 0.05 * 3.4e-3)
            for layer in range(n - 1):
                matrix[layer, layer + 1], matrix[layer + 1, layer] = -down[layer], -up[layer + 1]
            rhs = rng.uniform(30, 90, n)
            exact = np.linalg.solve(matrix, rhs)
            reduced = rhs.copy()
            for layer in range(n - 2, -1, -1):
                reduced[layer] += carry[n, layer] * reduced[layer + 1]
            solved, above = np.zeros(n), 0.0
            for layer in range(n):
                solved[layer] = above = (reduced[layer] + up[layer] * above) / pivot[n, layer]
            assert solved == pytest.approx(exact, rel=1e-12)


def test_layers_grow_from_a_thin_top_to_the_depth():
    faces = layers.layer_faces(8, 6.0)
    widths = np.diff(faces)
    assert faces[0] == 0.0 and faces[-1] == pytest.approx(6.0)
    assert np.allclose(widths[1:] / widths[:-1], layers.LAYER_GROWTH)
    assert widths[0] < 0.2  # the default top layer is thin (0.174 mm)
    assert layers.layer_faces(1, 2.0).tolist() == [0.0, 2.0]


def test_rest_profile_balances_air_loss_against_perfusion_and_the_bottom():
    faces = layers.layer_faces(8, 6.0)
    rest = layers.rest_profile(faces, "body", 0.136, 3.4e-3, 37.0, 0.05, 22.0)
    assert 22.0 < rest[0] < rest[-1] < 37.0  # the air cools the top most
    assert np.all(np.diff(rest) > 0)
    assert layers.rest_profile(faces, "insulated", 0.136, 0.0, 37.0, 0.0, 22.0).tolist() == [37.0] * 8


def slab_case(layer_count=24, depth_mm=20.0):
    surface = build_surface(plane_mesh(4.0, 4.0, cells=2), 16)
    tissue = tissue_values(perfusion_1_s=0.0)
    cautery = Cautery(surface, tissue, cautery_values(layers=layer_count, depth_mm=depth_mm, surface_loss_w_m2k=0.0),
                      InstrumentFields([]))
    return surface, cautery


def test_a_heated_top_slab_cools_into_the_half_space_as_carslaw_and_jaeger_say():
    """Carslaw & Jaeger (1959) section 2.9: 0 < z < L at T_body + dT, below at T_body, top insulated, no perfusion:
    T(0, t) = T_body + dT erf(L / sqrt(4 alpha t)). Here L is the layer face nearest 0.5 mm, the half-space 20 mm deep
    (heat reaches 2 mm in 5 s). Measured: within 0.4 % of dT."""
    surface, cautery = slab_case()
    faces = cautery.faces_mm
    slab = int(np.argmin(np.abs(faces - 0.5)))
    thickness = faces[slab]
    rise = 20.0
    start = np.full((cautery.layer_count,) + surface.mask.shape, BODY)
    start[:slab] += rise
    cautery.set_temperature(start)
    alpha, dt, t = cautery.diffusivity_mm2_s, 0.01, 0.0
    checked = 0
    for mark in (0.2, 0.5, 1.0, 2.0, 5.0):
        while t < mark - 1e-9:
            cautery.step(dt)
            t += dt
        measured = cautery.temperature_c()[8, 8] - BODY
        exact = rise * erf(thickness / math.sqrt(4 * alpha * t))
        assert abs(measured - exact) < 0.02 * rise, (t, measured, exact)
        checked += 1
    assert checked == 5 and cautery.temperature_c()[8, 8] < BODY + 0.75 * rise  # it did cool


@pytest.fixture(scope="module")
def contact_runs():
    """Issue 10's contact (ball 1.5 mm, 250 C, pressed 0.2 mm, 2 s, then lifted) up to 12 s: the 3D reference on its
    0.05 mm grid, the layered model at its defaults on 0.094 mm texels."""
    from lab.bench.heat_layers import ball_contact_layered
    from lab.bench.heat_reference import ball_contact_reference

    times = (2.0, 7.0, 12.0)
    return ball_contact_reference(grid_mm=0.05, end_s=12.0, sample_times_s=times), ball_contact_layered(end_s=12.0, sample_times_s=times)


def test_the_burn_cools_and_stops_growing_as_in_the_3d_reference(contact_runs):
    """Defaults within 3 C of the 3D reference at the surface after lift-off and within 10 % on area and depth
    (measured: 0.5 C, -1.4 %, +4.2 %); the coagulated zone stops growing within 5 s of lift-off."""
    reference, layered = contact_runs
    for ref, mine in zip(reference["samples"], layered["samples"]):
        assert ref["t_s"] == mine["t_s"]
        if ref["t_s"] > 2.0:
            assert abs(mine["surface_center_c"] - ref["surface_center_c"]) < 3.0
        assert mine["coagulated_area_mm2"] == pytest.approx(ref["coagulated_area_mm2"], rel=0.1)
        assert mine["coagulation_depth_mm"] == pytest.approx(ref["coagulation_depth_mm"], rel=0.1)
    seven, twelve = layered["samples"][1], layered["samples"][2]
    assert twelve["coagulated_area_mm2"] < 1.02 * seven["coagulated_area_mm2"]
    assert seven["surface_center_c"] < 70.0  # the surface cooled from 224 C within 5 s


def ball(tip_c=250.0, position=(0.0, 0.0, 1.3), energized=True):
    return Instrument.from_config({
        "name": "ball", "shape": {"type": "ball", "radius_mm": 1.5, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
        "position_mm": list(position), "direction": [0, 0, -1], "roll_deg": 0.0, "energized": energized,
        "tip_temperature_c": tip_c, "path": []})


def burn(tolerance_c, seconds=3.0):
    surface = build_surface(plane_mesh(24.0, 24.0), 128)
    tool = ball()
    fields = InstrumentFields([tool])
    cautery = Cautery(surface, tissue_values(), cautery_values(sleep_tolerance_c=tolerance_c), fields)
    awake = []
    for step in range(int(round(seconds / 0.01))):
        if step == 100:
            tool.energized_by_hand = False
            fields.set_time(1.0)
        cautery.step(0.01)
        awake.append(cautery.awake_fraction())
    return cautery, awake


def test_sleeping_tiles_change_the_burn_by_less_than_their_tolerance():
    """A 1 s burn on a 24 mm plane, then 2 s of cooling: with the default tolerance (0.05 C) most tiles sleep and the
    temperatures differ from a run in which none sleeps (tolerance 0) by less than the tolerance; damage alike."""
    awake_run, _ = burn(0.0)
    sleepy, awake = burn(params.CAUTERY["sleep_tolerance_c"].default)
    assert awake[0] == 1.0 and max(awake[1:]) <= 0.5  # a fresh state looks at every tile; then far tiles sleep (of 8 x 8)
    difference = np.abs(sleepy.temperature_depth_c() - awake_run.temperature_depth_c()).max()
    assert difference < params.CAUTERY["sleep_tolerance_c"].default
    assert sleepy.metrics()["coagulated_area_mm2"] == pytest.approx(awake_run.metrics()["coagulated_area_mm2"], rel=1e-3)


def test_an_idle_lab_steps_no_tile_and_a_tool_wakes_its_tiles():
    surface = build_surface(plane_mesh(24.0, 24.0), 128)
    tool = ball(energized=False)
    fields = InstrumentFields([tool])
    cautery = Cautery(surface, tissue_values(), cautery_values(), fields)
    cautery.step(0.01)  # the first step looks at every tile (a fresh state)
    cautery.step(0.01)
    assert cautery.awake_fraction() == 0.0
    before = cautery.temperature_depth_c()
    for _ in range(50):
        cautery.step(0.01)
    assert np.array_equal(cautery.temperature_depth_c(), before)  # at rest and not stepped
    tool.energized_by_hand = True
    fields.set_time(0.0)
    cautery.step(0.01)
    assert 0.0 < cautery.awake_fraction() < 0.2
    assert cautery.temperature_c()[64, 64] > before[0, 64, 64] + 1.0


def test_outputs_in_depth(contact_runs):
    """State arrays per layer, the depth map and the metrics after a short burn."""
    surface = build_surface(plane_mesh(12.0, 12.0), 64)
    cautery = Cautery(surface, tissue_values(), cautery_values(), InstrumentFields([ball()]))
    for _ in range(150):
        cautery.step(0.01)
    count = cautery.layer_count
    assert cautery.temperature_depth_c().shape == (count, 64, 64) and cautery.damage_omega_depth().shape == (count, 64, 64)
    assert cautery.layer_depth_mm.shape == (count,) and np.all(np.diff(cautery.layer_depth_mm) > 0)
    depth = cautery.coagulation_depth_mm()
    metrics = cautery.metrics()
    assert metrics["coagulation_depth_mm"] == pytest.approx(depth.max()) and 0.3 < depth.max() < 2.0
    assert depth[0, 0] == 0.0 and metrics["coagulated_volume_mm3"] > 0.0
    omega = cautery.damage_omega_depth()[:, 32, 32]
    assert omega[0] >= 1.0 and np.all(np.diff(omega) <= 0)  # damage falls with depth under the tool
    # the depth map is where log Omega crosses 0 between the layer centres
    below = int(np.argmax(omega < 1.0))
    assert cautery.layer_depth_mm[below - 1] <= depth[32, 32] <= cautery.layer_depth_mm[below]


@pytest.mark.parametrize("layer_count, depth_mm", [(1, 0.5), (1, 30.0), (32, 0.5), (32, 30.0)])
def test_hard_cases_stay_finite_and_bounded(layer_count, depth_mm):
    """One layer and the most layers, the thinnest top layer (32 layers in 0.5 mm: 0.05 um), the hottest tool, the
    largest time step and the highest conductivity and contact conductance."""
    surface = build_surface(plane_mesh(12.0, 12.0), 32)
    tip = params.INSTRUMENT["tip_temperature_c"].max
    tissue = tissue_values(conductivity_w_mk=params.TISSUE["conductivity_w_mk"].max)
    values = cautery_values(layers=layer_count, depth_mm=depth_mm, contact_conductance_w_m2k=params.CAUTERY["contact_conductance_w_m2k"].max)
    cautery = Cautery(surface, tissue, values, InstrumentFields([ball(tip_c=tip)]))
    dt = params.SIMULATION["time_step_s"].max
    low = min(BODY, values["air_temperature_c"])
    for _ in range(200):
        cautery.step(dt)
    field = cautery.temperature_depth_c()[:, surface.mask]
    assert np.isfinite(field).all() and field.min() >= low - 1e-3 and field.max() <= tip + 1e-3
    assert np.isfinite(cautery.damage_omega_depth()).all() and cautery.temperature_c().max() > 100.0


def test_an_old_scene_with_a_heated_layer_loads_with_a_note(tmp_path):
    """cautery.heated_layer_mm is gone (the heat goes into layers): an old scene still loads, and says so."""
    from sims.scene.config import REPO_ROOT, load_scene_config

    text = (REPO_ROOT / "scenes/default.yaml").read_text().replace("cautery:\n", "cautery:\n  heated_layer_mm: 1.0\n", 1)
    path = tmp_path / "old.yaml"
    path.write_text(text.replace("mesh: meshes/patch.obj", f"mesh: {REPO_ROOT / 'static/meshes/patch.obj'}"))
    config = load_scene_config(path)
    assert "heated_layer_mm" not in config["cautery"] and config["cautery"]["layers"] == params.CAUTERY["layers"].default
    assert len(config["notes"]) == 1 and config["notes"][0].startswith("cautery.heated_layer_mm: ")
    assert "cautery.layers" in config["notes"][0]
    assert load_scene_config(REPO_ROOT / "scenes/default.yaml")["notes"] == []


def test_the_cross_section_shows_the_burn_under_the_last_energized_tool():
    """Scene.burn_section cuts across the ball's stroke where it is; the picture outlines the coagulated zone in white
    and is as deep as the burn (the browser's Burn cross-section folder shows this picture)."""
    from lab.web.section_view import MARGIN_LEFT, MARGIN_TOP, PIXELS_PER_MM, section_image
    from sims.scene.assembly import Scene
    from sims.scene.config import REPO_ROOT

    scene = Scene.from_file(REPO_ROOT / "scenes/default.yaml", ["texture_size=128"])
    assert scene.burn_section() is None  # no tool energized yet
    while scene.time_s < 2.0:
        scene.step()
    section = scene.burn_section()
    assert section.tool == "ball_electrode"
    ball = np.asarray(scene.instrument("ball_electrode").pose_at(scene.time_s).position_mm)
    assert np.linalg.norm(section.centre_mm - ball) < 2.0  # under the tool
    assert abs(section.direction @ np.array([1.0, 0.0, 0.0])) < 0.3  # across the stroke (it moves along +x)
    middle = len(section.distance_mm) // 2
    assert section.coagulation_depth_mm[middle] > 0.2 and section.coagulation_depth_mm[0] == 0.0
    image = section_image(section)
    column = MARGIN_LEFT + int(round(float(section.distance_mm[-1]) * PIXELS_PER_MM))  # distance 0
    white = np.nonzero((image[MARGIN_TOP:, column] > 240).all(axis=1))[0]
    deepest_white_mm = (white.max() + 0.5) / PIXELS_PER_MM
    assert abs(deepest_white_mm - section.coagulation_depth_mm[middle]) < 0.1  # the outline sits at the burn's depth
    scene.reset()
    assert scene.burn_section() is None


def test_layers_that_would_not_fit_in_memory_are_refused_with_the_key_named():
    """16 layers under a 2048^2 heat grid would take 1.07 GB of layered fields: the scene is refused before anything is
    built (the default heat grid, half as fine, would fit)."""
    from sims.scene.assembly import Scene
    from sims.scene.config import REPO_ROOT, ConfigError

    with pytest.raises(ConfigError) as error:
        Scene.from_file(REPO_ROOT / "scenes/default.yaml", ["texture_size=2048", "cautery.layers=16", "cautery.heat_grid_divisor=1"])
    assert "cautery.layers" in str(error.value) and "1.07 GB" in str(error.value) and "fewer cautery.layers" in str(error.value)
