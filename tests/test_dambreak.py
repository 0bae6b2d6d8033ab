"""Dam break bench: Martin & Moyce interpolation and error, walls that keep every particle on the chart,
and a short dam break against Martin & Moyce."""
import math

import numpy as np
import pytest

from lab.bench import dambreak
from lab.reference import dambreak as reference
from sims.blood.particles import Bleeding
from sims.scene import params

MM = np.asarray(reference.MARTIN_MOYCE)


def test_martin_moyce_front_hits_the_data_and_interpolates_linearly():
    for T, Z in reference.MARTIN_MOYCE:
        assert reference.martin_moyce_front(T) == pytest.approx(Z)
    middle = 0.5 * (MM[0] + MM[1])
    assert reference.martin_moyce_front(middle[0]) == pytest.approx(middle[1])
    assert reference.martin_moyce_front(3.0) == pytest.approx(3.728 + (3.0 - 2.95) / (3.598 - 2.95) * (4.528 - 3.728))
    values = reference.martin_moyce_front(MM[:, 0])
    np.testing.assert_allclose(values, MM[:, 1])
    assert math.isnan(reference.martin_moyce_front(0.5)) and math.isnan(reference.martin_moyce_front(6.0))


def test_front_error_of_a_known_history():
    offsets = np.array([0.1, -0.3, 0.2, 0.0, 0.1, -0.1, 0.05, 0.4, -0.2, 0.1])
    error = reference.front_error(np.concatenate([[0.0], MM[:, 0]]), np.concatenate([[1.0], MM[:, 1] + offsets]))
    assert error["points"] == 10
    assert error["mean_abs_a"] == pytest.approx(np.abs(offsets).mean())
    assert error["max_abs_a"] == pytest.approx(0.4)
    assert error["mean_signed_a"] == pytest.approx(offsets.mean())
    # a straight line between samples: Z = 1 + T ahead of Martin & Moyce by (1 + T) - Z_MM at their times
    T = np.linspace(0.0, 2.0, 41)
    error = reference.front_error(T, 1.0 + T)
    inside = MM[MM[:, 0] <= 2.0]
    assert error["points"] == len(inside) == 3
    assert error["mean_abs_a"] == pytest.approx(np.abs(1.0 + inside[:, 0] - inside[:, 1]).mean())
    assert math.isnan(reference.front_error([0.0, 0.5], [1.0, 1.1])["mean_abs_a"])


def test_walls_keep_a_dense_clump_inside_with_a_large_step():
    """A 1a x 2.5a chart in the corner of its texture: down-left hits the texture's edges, up-right the mask's.
    A clump far denser than rest explodes, then piles into the corner gravity points to, 0.05 s per step."""
    surface, texel, size = dambreak.tank_surface(1.0, chart_length_a=1.0)
    values = {name: spec.default for name, spec in params.BLEEDING.items()}
    values.update(stiffness_mm_s2=1e5, near_stiffness_mm_s2=1e5, max_speed_mm_s=1e4, clotting_rate_1_s=0.0, blood_viscosity_mpa_s=0.0, substeps=1)
    count = 600
    centre = np.array([0.5 * 25.0 / texel, size - 1.25 * 25.0 / texel])  # middle of the chart, grid units
    clump = centre + np.random.default_rng(3).normal(scale=0.3, size=(count, 2))  # about 0.3 mm across
    walled = Bleeding(surface, values, (0.0, 0.0, 0.0), count, walls=True)
    open_ = Bleeding(surface, values, (0.0, 0.0, 0.0), count)
    for gravity in [(-6000.0, 0.0, -9810.0), (6000.0, 0.0, 9810.0)]:
        for bleeding in (walled, open_):
            bleeding.set_gravity(gravity)
            bleeding.place(clump)
            for _ in range(30):
                bleeding.step(0.05)
        pos = walled.pos.to_numpy()[: walled.count]
        assert walled.count == count and walled.accounting()["left_surface"] == 0
        assert np.isfinite(pos).all() and np.isfinite(walled.vel.to_numpy()[:count]).all()
        cols, rows = np.floor(pos[:, 0]).astype(int), np.floor(pos[:, 1]).astype(int)
        assert ((cols >= 0) & (cols < size) & (rows >= 0) & (rows < size)).all()
        assert surface.mask[rows, cols].all()
        x_mm, z_mm = pos[:, 0] * texel, (size - pos[:, 1]) * texel
        if gravity[0] < 0:  # piled up in the corner gravity points to
            assert (x_mm < 12.5).all() and (z_mm < 31.25).all()
        else:
            assert (x_mm > 12.5).all() and (z_mm > 31.25).all()
        assert open_.accounting()["left_surface"] > 0  # without walls the same clump loses particles: the walls did the work


def test_short_dam_break_front_follows_martin_and_moyce_early():
    """Coarse (1 mm spacing, 1,450 particles) to T = 2.5: the front only moves forward and stays within 0.4 a of
    Martin & Moyce (measured: +0.11, +0.16, +0.06, -0.03 a at T = 0.85, 1.21, 1.60, 2.28)."""
    result = dambreak.simulate(1.0, 2, t_end=2.5)
    Z = np.asarray(result["Z"])
    assert 0.9 * len(dambreak.column_positions(1.0)) < result["particles"] <= len(dambreak.column_positions(1.0))
    assert result["column_height_a"] == pytest.approx(2.0, abs=0.05)
    assert np.diff(Z).min() > -0.01
    assert Z[-1] > 2.5
    error = result["error"]
    assert error["points"] == 4
    assert error["max_abs_a"] < 0.4, error
    assert result["particle_steps_per_s"] > 0 and math.isfinite(result["ms_per_simulated_s"])
