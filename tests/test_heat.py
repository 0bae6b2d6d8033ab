"""Heat along the surface against analytic solutions, conservation and the maximum principle (layers uniform in depth
over an insulated bottom, so the layered model must spread exactly as a surface field)."""
import numpy as np
import pytest

from lab.reference.meshes import plane_mesh
from sims.heat.cautery import Cautery
from sims.scene import params
from sims.scene.config import REPO_ROOT
from sims.scene.instruments import Instrument, InstrumentFields
from sims.surface.texels import build_surface, load_mesh
from testing.helpers import surface_only_values, tissue_values

DEFAULT_SIZE = int(params.SIMULATION["texture_size"].default)
BODY = 37.0


def gaussian_variances(width_mm, height_mm, seconds=3.0, sigma_mm=2.0, size=DEFAULT_SIZE):
    """Spread a Gaussian bump on a plane; return measured (var_x, var_y) and the analytic variance."""
    surface = build_surface(plane_mesh(width_mm, height_mm), size)
    cautery = Cautery(surface, tissue_values(perfusion_1_s=0.0, conductivity_w_mk=2.0), surface_only_values(), InstrumentFields([]))
    x, y = surface.position_mm[..., 0], surface.position_mm[..., 1]
    cautery.set_temperature(BODY + 20.0 * np.exp(-(x**2 + y**2) / (2 * sigma_mm**2)))
    dt = 0.01
    for _ in range(int(round(seconds / dt))):
        cautery.step(dt)
    excess = (cautery.temperature_c() - BODY) * surface.texel_area_mm2
    var_x = (excess * x**2).sum() / excess.sum()
    var_y = (excess * y**2).sum() / excess.sum()
    return var_x, var_y, sigma_mm**2 + 2 * cautery.diffusivity_mm2_s * seconds


def test_gaussian_spreads_with_variance_s2_plus_2_alpha_t():
    var_x, var_y, expected = gaussian_variances(40.0, 40.0)
    assert abs(var_x / expected - 1) < 0.02
    assert abs(var_y / expected - 1) < 0.02
    assert var_x > 4.0 * 1.2  # it did spread: s^2 = 4 mm^2


def test_spread_is_isotropic_in_mm_on_uvs_stretched_3_to_1():
    var_x, var_y, expected = gaussian_variances(60.0, 20.0)
    assert abs(var_x / var_y - 1) < 0.05
    assert abs(var_x / expected - 1) < 0.02


def total_heat_drift(surface, steps=300, dt=0.01):
    """Relative change of the integral of T over area with no perfusion and no tool."""
    cautery = Cautery(surface, tissue_values(perfusion_1_s=0.0, conductivity_w_mk=5.0), surface_only_values(), InstrumentFields([]))
    rng = np.random.default_rng(1)
    field = BODY + 60.0 * rng.random(surface.mask.shape)  # rough: every texel exchanges heat
    cautery.set_temperature(field)
    area = surface.texel_area_mm2.astype(np.float64)
    before = (cautery.temperature_c() * area).sum()
    for _ in range(steps):
        cautery.step(dt)
    after_field = cautery.temperature_c()
    assert after_field[surface.mask].std() < 0.5 * field[surface.mask].std()  # heat really moved
    assert np.abs(cautery.temperature_depth_c() - after_field[None]).max() < 1e-3  # and stayed uniform in depth
    return abs((after_field * area).sum() / before - 1)


@pytest.mark.parametrize("mesh_file", ["static/meshes/patch.obj", "static/meshes/liver_lobe.obj"])
def test_total_heat_is_conserved(mesh_file):
    surface = build_surface(load_mesh(REPO_ROOT / mesh_file), 128)
    assert total_heat_drift(surface) < 1e-3


@pytest.mark.parametrize("extreme", ["max", "min"])
def test_maximum_principle_at_parameter_extremes(extreme):
    """Every tissue/cautery parameter at one end of its range, dt at its top, a 400 C tool, 10,000 steps."""
    pick = (lambda spec: spec.max) if extreme == "max" else (lambda spec: spec.min)
    tissue = {name: pick(spec) for name, spec in params.TISSUE.items()}
    tissue.update(body_temperature_c=37.0, initial_temperature_c=20.0, conductivity_w_mk=params.TISSUE["conductivity_w_mk"].max)
    cautery_params = {name: pick(spec) for name, spec in params.CAUTERY.items()}
    cautery_params["bottom"] = "body"  # (max: 32 layers down to 30 mm; min: one layer 0.5 mm thick)
    tool_temperature = params.INSTRUMENT["tip_temperature_c"].max
    surface = build_surface(load_mesh(REPO_ROOT / "static/meshes/patch.obj"), 64)
    centre = surface.position_mm[32, 32]
    tool = Instrument.from_config({
        "name": "ball", "shape": {"type": "ball", "radius_mm": 3.0, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
        "position_mm": list(centre), "direction": [0, 0, -1], "roll_deg": 0.0, "energized": True,
        "tip_temperature_c": tool_temperature, "path": [],
    })
    cautery = Cautery(surface, tissue, cautery_params, InstrumentFields([tool]))
    dt = params.SIMULATION["time_step_s"].max
    air = cautery_params["air_temperature_c"]
    low, high = min(37.0, 20.0, air), max(37.0, tool_temperature, air)
    for step in range(10_000):
        cautery.step(dt)
        if step % 1000 == 999:
            for field in (cautery.temperature_c()[surface.mask], cautery.temperature_depth_c()[:, surface.mask]):
                assert np.isfinite(field).all()
                assert field.min() >= low - 1e-3 and field.max() <= high + 1e-3
    # the tool did heat the tissue (at the low end a weak contact on one 0.5 mm layer held at 37 C below: 38.8 C)
    assert cautery.temperature_c()[32, 32] > (300.0 if extreme == "max" else 38.0)
    assert np.isfinite(cautery.damage_omega()).all() and np.isfinite(cautery.char_level()).all()
