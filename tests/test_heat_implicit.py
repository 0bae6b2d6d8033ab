"""The implicit heat scheme (backward Euler, conjugate gradient): analytic Gaussian, conservation on a
mesh with many charts, boundedness at time steps far beyond the explicit limit and at the iteration
cap, NaN not hidden, byte-identical runs (reset, 1 or 2 threads), and the scene key."""
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from scipy import ndimage

from lab.reference import analytic
from lab.reference.meshes import plane_mesh
from sims.heat.cautery import CG_TOLERANCE, SCHEMES, Cautery
from sims.scene import config
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT, ConfigError, load_scene_config
from sims.scene.instruments import Instrument, InstrumentFields
from sims.surface.texels import build_surface, load_mesh
from testing.helpers import cautery_values, surface_only_values, tissue_values

BODY = 37.0


def implicit(surface, tools=(), **tissue_changes):
    return Cautery(surface, tissue_values(**tissue_changes), surface_only_values(), InstrumentFields(list(tools)), scheme="implicit")


def ball(temperature_c=400.0, radius_mm=2.0, position_mm=(0.0, 0.0, 1.5)) -> Instrument:
    return Instrument.from_config({
        "name": "ball", "shape": {"type": "ball", "radius_mm": radius_mm, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
        "position_mm": list(position_mm), "direction": [0, 0, -1], "roll_deg": 0.0, "energized": True,
        "tip_temperature_c": temperature_c, "path": [],
    })


# measured max |T - exact| / exact peak after 2 s on 256^2 texels (texel 0.16 mm): 0.0076 at dt 0.01 s,
# 0.0169 at 0.05 s (backward Euler is first order in time; the explicit scheme measures 0.0029 at 0.01 s)
@pytest.mark.parametrize("dt, bound", [(0.01, 0.012), (0.05, 0.025)])
def test_gaussian_on_plane_matches_analytic(dt, bound):
    surface = build_surface(plane_mesh(40.0, 40.0), 256)
    cautery = implicit(surface, perfusion_1_s=0.0)
    r2 = (surface.position_mm[..., :2] ** 2).sum(axis=2)
    amplitude, sigma, seconds = 50.0, 0.5, 2.0
    cautery.set_temperature(BODY + analytic.gaussian_on_plane(r2, amplitude, sigma, 0.0, 0.0))
    for _ in range(int(round(seconds / dt))):
        cautery.step(dt)
        assert 1 <= cautery.last_iterations < cautery.max_iterations * cautery.layer_count and cautery.last_residual <= CG_TOLERANCE
    exact = analytic.gaussian_on_plane(r2, amplitude, sigma, cautery.diffusivity_mm2_s, seconds)
    error = np.abs(cautery.temperature_c() - BODY - exact)[surface.mask].max() / exact.max()
    assert exact.max() < 0.35 * amplitude  # it did spread
    assert error < bound


@pytest.mark.parametrize("dt, steps", [(0.01, 300), (1.0, 5)])
def test_total_heat_is_conserved_on_a_mesh_with_many_charts(dt, steps):
    """Measured drift with a rough field on the 16 charts of the liver lobe: 1.4e-8 (300 steps of 0.01 s), 1.6e-7 (5 of 1 s)."""
    surface = build_surface(load_mesh(REPO_ROOT / "static/meshes/liver_lobe.obj"), 128)
    assert ndimage.label(surface.mask, structure=np.ones((3, 3)))[1] >= 5  # several charts, insulated borders
    cautery = implicit(surface, perfusion_1_s=0.0, conductivity_w_mk=5.0)
    field = BODY + 60.0 * np.random.default_rng(1).random(surface.mask.shape)
    cautery.set_temperature(field)
    area = surface.texel_area_mm2.astype(np.float64)
    before = (cautery.temperature_c() * area).sum()
    for _ in range(steps):
        cautery.step(dt)
        assert cautery.last_residual <= CG_TOLERANCE
    after = cautery.temperature_c()
    assert after[surface.mask].std() < 0.5 * field[surface.mask].std()  # heat really moved
    assert after[surface.mask].min() >= BODY - 1e-3 and after[surface.mask].max() <= BODY + 60.0 + 1e-3
    assert abs((after * area).sum() / before - 1) < 1e-6


def huge_step_case(max_iterations):
    """dt = 1 s, k = 5 W/(m K), 0.08 mm texels, a 400 C ball pressed in, a rough 20..60 C start."""
    surface = build_surface(plane_mesh(20.0, 20.0), 256)
    cautery = Cautery(surface, tissue_values(conductivity_w_mk=5.0), cautery_values(), InstrumentFields([ball()]),
                      scheme="implicit", max_iterations=max_iterations)
    cautery.set_temperature(20.0 + 40.0 * np.random.default_rng(2).random(surface.mask.shape))
    return surface, cautery


def test_bounded_at_a_time_step_hundreds_of_explicit_substeps_long():
    surface, cautery = huge_step_case(max_iterations=500)
    assert cautery.explicit_substeps(1.0) > 500 and cautery.substeps(1.0) == 1
    for _ in range(4):
        cautery.step(1.0)
        field = cautery.temperature_c()[surface.mask]
        assert np.isfinite(field).all()
        assert field.min() >= 20.0 - 1e-3 and field.max() <= 400.0 + 1e-3
        assert cautery.last_iterations < 500 * cautery.layer_count and cautery.last_residual <= CG_TOLERANCE  # per layer 82..203
    assert cautery.temperature_c()[128, 128] > 250.0  # the tool heated the tissue under it (268 C: heat also goes into depth)
    assert field.min() > 37.0  # perfusion and conduction pulled the cold texels up toward body temperature
    assert np.isfinite(cautery.damage_omega()).all() and cautery.damage_omega()[128, 128] > 1.0


def test_iteration_cap_keeps_the_step_finite_and_bounded():
    surface, cautery = huge_step_case(max_iterations=5)
    for _ in range(3):
        cautery.step(1.0)
        field = cautery.temperature_c()[surface.mask]
        assert cautery.last_iterations == 5 * cautery.layer_count and cautery.last_residual > CG_TOLERANCE  # the cap was hit
        assert np.isfinite(field).all()
        assert field.min() >= 20.0 - 1e-3 and field.max() <= 400.0 + 1e-3


def test_a_non_finite_temperature_is_not_hidden_by_the_clamp():
    surface = build_surface(plane_mesh(10.0, 10.0, cells=2), 16)
    cautery = implicit(surface)
    field = np.full(surface.mask.shape, 50.0)
    field[8, 8] = np.nan
    cautery.set_temperature(field)
    cautery.step(0.01)
    assert not np.isfinite(cautery.temperature_c()[surface.mask]).all()


def test_schemes_constant_and_bad_scheme():
    assert SCHEMES == config.CAUTERY_SCHEMES == ("explicit", "implicit")
    surface = build_surface(plane_mesh(10.0, 10.0, cells=2), 16)
    with pytest.raises(ValueError, match="explicit, implicit"):
        Cautery(surface, tissue_values(), cautery_values(), InstrumentFields([]), scheme="crank")


SCENE = {
    "name": "implicit", "mesh": "meshes/patch.obj", "texture_size": 64, "models": ["cautery"], "duration_s": 0.5,
    "cautery": {"scheme": "implicit"},
    "instruments": [{"name": "ball", "shape": {"type": "ball", "radius_mm": 2.0}, "tip_temperature_c": 250,
                     "position_mm": [0.0, 0.0, 1.5], "energized": True}],
}


def test_scene_key_selects_the_scheme(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(SCENE))
    maxima = {}
    for scheme in SCHEMES:
        scene = Scene.from_file(path, [f"cautery.scheme={scheme}"], arch="cpu")
        assert scene.cautery.scheme == scheme
        for _ in range(50):
            scene.step()
        metrics = scene.metrics()["cautery"]
        assert scene.non_finite_field() is None
        maxima[scheme] = metrics["max_temperature_c"]
    assert scene.cautery.last_iterations >= 1 and metrics["heat_substeps_per_step"] == 1
    assert maxima["implicit"] > 100.0
    assert maxima["implicit"] == pytest.approx(maxima["explicit"], rel=0.05)
    assert load_scene_config(path)["cautery"]["scheme"] == "implicit"
    path.write_text(yaml.safe_dump({key: value for key, value in SCENE.items() if key != "cautery"}))
    assert load_scene_config(path)["cautery"]["scheme"] == "explicit"  # the default


def test_same_state_after_reset_and_with_one_or_two_threads(tmp_path):
    """The CG sums are reduced in a fixed order and reset() forgets the warm start: byte-identical runs."""
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(SCENE))
    scene = Scene.from_file(path, arch="cpu")
    runs = []
    for _ in range(2):
        for _ in range(30):
            scene.step()
        runs.append(scene.state_arrays())
        scene.reset()
    for key in runs[0]:
        assert np.array_equal(runs[0][key], runs[1][key]), key
    outputs = []
    for threads in ("1", "2"):
        out = tmp_path / f"threads{threads}"
        command = [sys.executable, "-m", "lab", "run", str(path), "--out", str(out), "--duration", "0.3",
                   "--set", "texture_size=256", "--arch", "cpu", "--quiet"]
        result = subprocess.run(command, capture_output=True, text=True, cwd=REPO_ROOT, env={**os.environ, "TISSUE_LAB_THREADS": threads})
        assert result.returncode == 0, result.stderr
        outputs.append((out / "state.npz").read_bytes())
    assert outputs[0] == outputs[1]


@pytest.mark.parametrize("how", ["file", "--set"])
def test_unknown_scheme_names_file_and_key(tmp_path, how):
    path = tmp_path / "scene.yaml"
    scene = dict(SCENE, cautery={"scheme": "crank_nicolson" if how == "file" else "implicit"})
    path.write_text(yaml.safe_dump(scene))
    with pytest.raises(ConfigError) as error:
        load_scene_config(path, ["cautery.scheme=crank_nicolson"] if how == "--set" else [])
    assert error.value.file == str(path) and error.value.key == "cautery.scheme"
    assert str(error.value).startswith(f"{path}: cautery.scheme: ")
    assert "'crank_nicolson'" in error.value.message and "explicit, implicit" in error.value.message
