"""The axisymmetric heat reference (lab/bench/heat_reference.py): the solver against Carslaw & Jaeger, heat
conservation, the maximum principle, Arrhenius at constant temperature, and grid convergence of the ball contact."""
import math

import numpy as np
import pytest

from lab.bench import heat_reference as hr

BODY_C = 37.0


def column(cell_mm: float, depth_mm: float = 20.0, **tissue_changes) -> hr.AxisymmetricHeat:
    """One column (r in [0, 1] mm, insulated sides): no r dependence, a 1D problem in z; insulated top and bottom."""
    tissue = dict(hr.tissue_defaults(), **tissue_changes)
    return hr.AxisymmetricHeat(np.array([0.0, 1.0]), hr.graded_faces(cell_mm, 3.0, depth_mm), tissue)


@pytest.mark.parametrize("scheme", ["cn", "euler"])
def test_heated_slab_cools_like_carslaw_and_jaeger(scheme):
    """A slab 0 < z < L at T_body + dT over a half-space at T_body, top insulated, no perfusion (Carslaw & Jaeger
    2.2(9) with its mirror image): the surface follows T_body + dT erf(L / sqrt(4 alpha t))."""
    slab_mm, excess_c = 0.5, 50.0
    model = column(0.025, perfusion_1_s=0.0)
    tissue = model.tissue
    alpha_mm2_s = tissue["conductivity_w_mk"] / (tissue["density_kg_m3"] * tissue["specific_heat_j_kgk"]) * 1e6
    start = np.where(model.z_centres[:, None] * 1e3 < slab_mm, BODY_C + excess_c, BODY_C)
    model.set_temperature(start)
    dt, t = 0.005, 0.0
    for check in (0.25, 1.0, 4.0, 10.0):
        while t < check - 1e-9:
            model.step(dt, scheme)
            t += dt
        exact = excess_c * math.erf(slab_mm / math.sqrt(4 * alpha_mm2_s * t))
        measured = model.surface_temperature_c()[0] - BODY_C
        assert measured == pytest.approx(exact, rel=0.02), (t, measured, exact)


def test_radial_gaussian_spreads_with_the_cylindrical_metric():
    """One layer in z (insulated top and bottom), no perfusion: a Gaussian in r of variance s² (per axis) stays a
    Gaussian of variance s² + 2 alpha t with amplitude s² / (s² + 2 alpha t) (docs/model/heat.md "Reference solutions"). A flat metric (face
    areas not 2 pi r dz) would spread it at the wrong rate."""
    sigma_mm, amplitude_c, seconds = 0.5, 50.0, 2.0
    tissue = dict(hr.tissue_defaults(), perfusion_1_s=0.0)
    model = hr.AxisymmetricHeat(np.linspace(0.0, 10.0, 201), np.array([0.0, 1.0]), tissue)
    alpha_mm2_s = tissue["conductivity_w_mk"] / (tissue["density_kg_m3"] * tissue["specific_heat_j_kgk"]) * 1e6
    r_mm = model.r_centres * 1e3

    def gaussian(t):
        variance = sigma_mm ** 2 + 2 * alpha_mm2_s * t
        return BODY_C + amplitude_c * sigma_mm ** 2 / variance * np.exp(-r_mm ** 2 / (2 * variance))

    model.set_temperature(gaussian(0.0)[None, :])
    for _ in range(200):
        model.step(seconds / 200)
    error = np.abs(model.temperature_c[0] - gaussian(seconds)).max()
    assert error < 0.005 * amplitude_c
    assert model.temperature_c[0, 0] - BODY_C == pytest.approx(gaussian(seconds)[0] - BODY_C, rel=0.01)


@pytest.mark.parametrize("scheme", ["cn", "euler"])
@pytest.mark.parametrize("far_boundary, perfusion_1_s", [("insulated", 0.0), ("body", 3.6e-3)])
def test_heat_content_changes_by_the_heat_that_came_in(scheme, far_boundary, perfusion_1_s):
    """No perfusion and insulated far faces: the heat content changes by the integrated contact flux alone (1e-6
    relative). With perfusion and far faces held at body temperature the budget still closes with those terms."""
    result = hr.ball_contact_reference(grid_mm=0.1, dt_s=0.02, contact_s=1.0, end_s=3.0, sample_times_s=(1.0, 3.0),
                                       r_max_mm=8.0, z_max_mm=8.0, far_boundary=far_boundary, perfusion_1_s=perfusion_1_s,
                                       scheme=scheme)
    energy = result["energy_j"]
    assert energy["surface"] > 0.5  # J: the ball did heat the tissue
    if perfusion_1_s == 0.0:
        assert energy["perfusion"] == 0.0 and energy["far"] == 0.0
    else:
        assert energy["perfusion"] < 0.0
    incoming = energy["surface"] + energy["perfusion"] + energy["far"]
    assert energy["content_change"] == pytest.approx(incoming, rel=1e-6)


@pytest.mark.parametrize("scheme, dt_s, conductance, tip_c", [("euler", 10.0, 1.0e5, 400.0), ("euler", 1.0, 5000.0, 250.0),
                                                              ("cn", 1.0, 5000.0, 250.0)])
def test_temperatures_stay_between_body_and_tip_at_a_large_step(scheme, dt_s, conductance, tip_c):
    """Backward Euler is an M-matrix step: every cell and surface temperature stays within [T_body, T_tip] at any step
    (here 10 s with the slider's largest contact conductance); Crank-Nicolson with its Euler start at 1 s also does on
    this contact (not guaranteed in general)."""
    r_faces, z_faces = hr.graded_faces(0.05, 2.0, 10.0), hr.graded_faces(0.05, 1.5, 10.0)
    model = hr.AxisymmetricHeat(r_faces, z_faces, hr.tissue_defaults())
    w = hr.ball_contact_weights(r_faces, 1.5, 0.2, 0.3)
    lowest, highest = math.inf, -math.inf
    for seconds, exchange in ((4.0 * dt_s, conductance * w), (20.0 * dt_s, np.zeros_like(w))):
        model.set_top(exchange, np.full_like(w, tip_c))
        for _ in range(int(round(seconds / dt_s))):
            model.step(dt_s, scheme)
            lowest = min(lowest, model.temperature_c.min(), model.surface_temperature_c().min())
            highest = max(highest, model.temperature_c.max(), model.surface_temperature_c().max())
        if exchange.any():
            assert highest > 0.5 * (BODY_C + tip_c)  # the contact did heat the tissue
    assert lowest >= BODY_C - 1e-9
    assert highest <= tip_c + 1e-9


def test_arrhenius_at_constant_temperature_matches_the_closed_form():
    """At constant 60 C Omega = t exp(ln A - Ea / (R T)): 1 after about 3.46 s (docs/model/heat.md "Damage": 3.46 s); at 42 C,
    under the 43 C threshold, no damage."""
    hot = column(0.5, depth_mm=2.0, perfusion_1_s=0.0, initial_temperature_c=60.0)
    tissue = hot.tissue
    rate = math.exp(tissue["arrhenius_ln_a"] - tissue["activation_energy_j_mol"] / (hr.GAS_CONSTANT * (60.0 + hr.KELVIN)))
    dt, t, previous = 0.01, 0.0, 0.0
    while hot.omega[0, 0] < 1.0:
        previous = hot.omega[0, 0]
        hot.step(dt)
        t += dt
        assert t < 10.0
    crossing = t - dt + dt * (1.0 - previous) / (hot.omega[0, 0] - previous)
    assert crossing == pytest.approx(1.0 / rate, rel=1e-9)
    assert crossing == pytest.approx(3.46, abs=0.05)
    assert np.allclose(hot.temperature_c, 60.0)
    assert np.allclose(hot.omega, hot.omega[0, 0]) and hot.omega_surface[0] == pytest.approx(hot.omega[0, 0])
    warm = column(0.5, depth_mm=2.0, perfusion_1_s=0.0, initial_temperature_c=42.0)
    for _ in range(100):
        warm.step(0.1)
    assert warm.omega.max() == 0.0 and warm.omega_surface.max() == 0.0


def test_coarse_and_fine_grids_agree_on_the_coagulated_zone():
    """The ball contact (250 C, 1.5 mm, 0.2 mm in, 2 s) on 0.1 and 0.05 mm grids: coagulation depth on the axis within
    0.01 mm (a fifth of the finer cell; measured 0.0004 mm), surface area within 1 % (measured 0.1 %), at lift-off and 10 s
    after it. The zone is that of a real burn: about 1.2 mm deep, about 8 mm² at the surface."""
    options = dict(dt_s=0.02, end_s=12.0, sample_times_s=(2.0, 12.0), r_max_mm=10.0, z_max_mm=10.0)
    coarse = hr.ball_contact_reference(grid_mm=0.1, **options)
    fine = hr.ball_contact_reference(grid_mm=0.05, **options)
    for a, b in zip(coarse["samples"], fine["samples"]):
        assert a["coagulation_depth_mm"] == pytest.approx(b["coagulation_depth_mm"], abs=0.01)
        assert a["coagulated_area_mm2"] == pytest.approx(b["coagulated_area_mm2"], rel=0.01)
    later = fine["samples"][-1]
    assert 1.0 < later["coagulation_depth_mm"] < 1.4
    assert 7.0 < later["coagulated_area_mm2"] < 9.0
    assert later["coagulated_volume_mm3"] > 0.5 * later["coagulated_area_mm2"] * later["coagulation_depth_mm"]
