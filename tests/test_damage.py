"""Arrhenius damage and charring at constant temperature against the closed form."""
import math

import numpy as np
import pytest

from sims.cautery import GAS_CONSTANT, KELVIN, Cautery
from sims.instruments import InstrumentFields
from sims.surface import build_surface
from tests.helpers import cautery_values, plane_mesh, tissue_values


def constant_temperature_cautery(temperature_c, **tissue_changes):
    """No diffusion, no perfusion, no tool: T stays at temperature_c everywhere."""
    surface = build_surface(plane_mesh(10.0, 10.0, cells=2), 16)
    tissue = tissue_values(perfusion_1_s=0.0, initial_temperature_c=temperature_c, **tissue_changes)
    return Cautery(surface, tissue, cautery_values(), InstrumentFields([])), tissue


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
