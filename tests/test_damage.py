"""Arrhenius damage and charring at constant temperature against the closed form."""
import math

import numpy as np
import pytest

from lab.reference.meshes import plane_mesh
from sims.heat.cautery import GAS_CONSTANT, KELVIN, Cautery
from sims.scene.instruments import InstrumentFields
from sims.surface.texels import build_surface
from testing.helpers import surface_only_values, tissue_values


def constant_temperature_cautery(temperature_c, **tissue_changes):
    """No diffusion, no perfusion, no tool: T stays at temperature_c everywhere."""
    surface = build_surface(plane_mesh(10.0, 10.0, cells=2), 16)
    tissue = tissue_values(perfusion_1_s=0.0, initial_temperature_c=temperature_c, **tissue_changes)
    return Cautery(surface, tissue, surface_only_values(), InstrumentFields([])), tissue


@pytest.mark.parametrize("temperature_c", [50.0, 60.0, 70.0])
def test_omega_matches_closed_form(temperature_c):
    cautery, tissue = constant_temperature_cautery(temperature_c)
    dt, steps = 0.01, 200
    for _ in range(steps):
        cautery.step(dt)
    rate = math.exp(tissue["arrhenius_ln_a"] - tissue["activation_energy_j_mol"] / (GAS_CONSTANT * (temperature_c + KELVIN)))
    omega = cautery.damage_omega()[8, 8]
    assert omega == pytest.approx(rate * dt * steps, rel=1e-3)


def test_liver_at_60c_coagulates_at_3_46_s():
    cautery, _ = constant_temperature_cautery(60.0)
    dt, t = 0.01, 0.0
    while cautery.damage_omega()[8, 8] < 1.0 and t < 10.0:
        cautery.step(dt)
        t += dt
    assert t == pytest.approx(3.46, rel=0.05)


def test_henriques_skin_at_extreme_temperature_stays_finite():
    """A = 3.1e98 overflows float32; ln A and the Omega cap keep everything finite at 400 C."""
    cautery, _ = constant_temperature_cautery(400.0, arrhenius_ln_a=math.log(3.1e98), activation_energy_j_mol=6.28e5, char_rate_1_s_c=0.01)
    for _ in range(50):
        cautery.step(0.05)
    assert np.isfinite(cautery.damage_omega()).all()
    assert cautery.damage_omega()[8, 8] > 1e3
    # char grows at rate * (T - T_char) per second, capped at 1
    assert cautery.char_level()[8, 8] == pytest.approx(1.0)


def test_char_grows_linearly_above_char_temperature():
    cautery, tissue = constant_temperature_cautery(200.0, char_temperature_c=180.0, char_rate_1_s_c=0.01)
    for _ in range(100):
        cautery.step(0.01)
    assert cautery.char_level()[8, 8] == pytest.approx(0.01 * 20.0 * 1.0, rel=1e-3)


def test_tissue_at_body_temperature_takes_no_damage_below_the_threshold():
    """Liver's A and Ea, fitted at 50-80 C, give 3e-4 Omega/s at 37 C: an idle lab would whiten the whole tissue in
    minutes. No damage accumulates at or below damage_threshold_c (43 C); with the threshold under 37 C it does."""
    cautery, tissue = constant_temperature_cautery(37.0)
    for _ in range(60):
        cautery.step(10.0)  # ten minutes
    assert cautery.damage_omega().max() == 0.0
    cautery, tissue = constant_temperature_cautery(37.0, damage_threshold_c=20.0)
    for _ in range(60):
        cautery.step(10.0)
    rate = math.exp(tissue["arrhenius_ln_a"] - tissue["activation_energy_j_mol"] / (GAS_CONSTANT * (37.0 + KELVIN)))
    assert cautery.damage_omega()[8, 8] == pytest.approx(rate * 600.0, rel=1e-3)


@pytest.mark.parametrize("scheme", ["explicit", "implicit"])
def test_damage_starts_only_once_the_tissue_crosses_the_threshold(scheme):
    """Both schemes: a plate at 80 C touching all of a 37 C plane of one insulated layer relaxes the layer toward 80 C at
    the contact rate; its Omega stays 0 until T passes 43 C and then follows the exact integral from the crossing on
    (dt 1 ms: within 1 %)."""
    from lab.reference import analytic
    from sims.scene.instruments import Instrument

    plate = Instrument.from_config({
        "name": "plate", "shape": {"type": "ball", "radius_mm": 100.0, "length_mm": 1, "width_mm": 1, "thickness_mm": 1},
        "position_mm": [0.0, 0.0, -99.0], "direction": [0, 0, -1], "roll_deg": 0.0, "energized": True,
        "tip_temperature_c": 80.0, "path": []})
    surface = build_surface(plane_mesh(4.0, 4.0, cells=2), 16)
    tissue = tissue_values(perfusion_1_s=0.0, initial_temperature_c=37.0)
    cautery = Cautery(surface, tissue, surface_only_values(layers=1, depth_mm=1.0), InstrumentFields([plate]), scheme=scheme)
    rate = cautery.contact_rate_1_s
    crossing = math.log((80.0 - 37.0) / (80.0 - 43.0)) / rate
    dt, steps = 0.001, 0
    while (steps + 2) * dt < crossing:
        cautery.step(dt)
        steps += 1
    assert cautery.damage_omega_depth()[0, 8, 8] == 0.0
    while steps * dt < crossing + 2.0:
        cautery.step(dt)
        steps += 1
    exact = analytic.arrhenius_omega_under_relaxation(steps * dt, 37.0, 80.0, rate, tissue["arrhenius_ln_a"], tissue["activation_energy_j_mol"], 43.0)
    assert exact > 0.01
    assert cautery.damage_omega_depth()[0, 8, 8] == pytest.approx(exact, rel=0.01)
