"""The burn at display resolution (sims.heat.display: state.npz, the look) against the metrics and the heat grid: Omega
is read through its log, so its edge stays where the heat grid puts it (issue 38, point 9)."""
import numpy as np
import pytest
import taichi as ti
import yaml

from lab.reference.meshes import plane_mesh
from sims.heat.cautery import LOG_OMEGA_FLOOR
from sims.scene.assembly import Scene
from sims.scene.config import load_scene_config


def held_ball(tmp_path, u_scale: float, divisor: int) -> Scene:
    """A 1.5 mm ball at 250 C pressed 0.3 mm into a 40 mm liver plane (texture 384², heat grid 384 / divisor) and held
    2 s; u_scale 1/3 stretches texels 3:1 along x (lab.reference.meshes.plane_mesh)."""
    plane_mesh(40.0, 40.0, u_scale=u_scale).export(tmp_path / "plane.obj")
    scene = {"name": "held", "mesh": str(tmp_path / "plane.obj"), "texture_size": 384, "models": ["cautery"],
             "cautery": {"heat_grid_divisor": divisor},
             "instruments": [{"name": "ball", "shape": {"type": "ball", "radius_mm": 1.5}, "tip_temperature_c": 250,
                              "position_mm": [0.0, 0.0, 1.2], "energized": True}]}
    (tmp_path / "held.yaml").write_text(yaml.safe_dump(scene))
    scene = Scene(load_scene_config(tmp_path / "held.yaml"))
    for _ in range(round(2.0 / scene.time_step_s)):
        scene.step()
    return scene


def shown_area_mm2(scene: Scene) -> float:
    """Area of the display texels whose state.npz Omega is at least 1."""
    state = scene.state_arrays()
    burnt = state["texel_mask"] & (state["damage_omega"] >= 1.0)
    return float(scene.surface.texel_area_mm2[burnt].sum(dtype=np.float64))


@pytest.mark.parametrize("u_scale", [1.0, 1 / 3], ids=["square", "stretched"])
def test_the_burn_shown_is_the_burn_reported_and_the_one_a_finer_heat_grid_gives(tmp_path, u_scale):
    """Heat on a 192² grid under a 384² display: the area of Omega >= 1 in state.npz and metrics.json agree within 3 %
    (bilinear Omega: +8 % square, +35 % stretched), and both within 3 % of heat run on the display grid itself (the
    heat grid's whole texels: -2 % and -15 %)."""
    coarse = held_ball(tmp_path, u_scale, divisor=2)
    reported = coarse.metrics()["cautery"]["coagulated_area_mm2"]
    assert reported > 5.0
    assert shown_area_mm2(coarse) == pytest.approx(reported, rel=0.03)
    fine = held_ball(tmp_path, u_scale, divisor=1)
    assert reported == pytest.approx(fine.metrics()["cautery"]["coagulated_area_mm2"], rel=0.03)


def test_the_look_reads_omega_as_the_state_does(tmp_path):
    """What the look's kernels read (HeatDisplay.omega) is state.npz's damage_omega; where no heat texel around is
    damaged it is exactly 0."""
    scene = held_ball(tmp_path, 1.0, divisor=2)
    shape = scene.surface.mask.shape
    read = ti.field(ti.f32, shape)

    @ti.kernel
    def look():
        for r, c in read:
            read[r, c] = scene.heat_display.omega(r, c)

    look()
    state, mask = scene.state_arrays()["damage_omega"], scene.surface.mask
    assert state.max() > 100.0
    np.testing.assert_allclose(read.to_numpy()[mask], state[mask], rtol=1e-4, atol=1e-30)  # float32 log and exp
    assert (state[mask] == 0.0).mean() > 0.9


def test_a_level_set_of_an_exponential_stays_put():
    """Omega = exp(x / mm) up to x = 15 mm, 0 beyond, on a 3:1 stretched coarse grid read on the fine one: exact inside
    (log-linear), so the level Omega = 1 stays at x = 0; zeros stay zeros."""
    from sims.surface.resample import GridResampler
    from sims.surface.texels import build_surface, surface_at

    fine = build_surface(plane_mesh(40.0, 40.0, u_scale=1 / 3), 96)
    coarse = surface_at(fine, 48)
    x = coarse.position_mm[..., 0]
    omega = np.where(coarse.mask, np.where(x > 15.0, 0.0, np.exp(x)), 0.0).astype(np.float32)
    read = GridResampler(coarse, fine).array(omega, LOG_OMEGA_FLOOR)
    fine_x, mask = fine.position_mm[..., 0], fine.mask
    inside = mask & (np.abs(fine_x) < 10.0)
    np.testing.assert_allclose(read[inside], np.exp(fine_x[inside]), rtol=1e-3)  # log-linear: exact up to rounding
    assert (read >= 1.0)[inside & (fine_x > 0.0)].all()  # fine texel centres lie 0.625 mm either side of x = 0
    assert not (read >= 1.0)[inside & (fine_x < 0.0)].any()  # bilinear Omega reads 1.09 at x = -0.625 mm
    assert (read[mask & (fine_x > 15.0 + 2.5)] == 0.0).all()  # a coarse texel (2.5 mm in x) past the last damage


def test_the_area_read_on_a_burns_box_is_the_area_read_on_the_whole_grid():
    """GridResampler.area_mm2 reads only the display rows and columns near coarse texels at the level (and those
    reading their nearest coarse texel): the same area as the whole grid read, on a sphere of many UV charts, for a
    burn at each of a few points and for none."""
    from lab.bench.heat import sphere_surface
    from sims.surface.resample import GridResampler
    from sims.surface.texels import surface_at

    fine = sphere_surface(128)
    coarse = surface_at(fine, 64)
    resampler = GridResampler(coarse, fine)
    assert len(resampler.elsewhere) > 0  # chart rims finer than the coarse grid: read from their nearest coarse texel
    rows, cols = np.nonzero(coarse.mask)
    for k in (0, len(rows) // 3, len(rows) - 1):
        distance = np.linalg.norm(coarse.position_mm - coarse.position_mm[rows[k], cols[k]], axis=-1)
        for omega in (np.exp(4.0 - 4.0 * distance), np.zeros(coarse.mask.shape)):
            omega = np.where(coarse.mask, omega, 0.0).astype(np.float32)
            whole = resampler.fine_area_mm2[resampler.array(omega, LOG_OMEGA_FLOOR) >= 1.0].sum(dtype=np.float64)
            assert resampler.area_mm2(omega, 1.0, LOG_OMEGA_FLOOR) == whole
