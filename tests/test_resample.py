"""The heat grid read on the display grid (sims.surface.resample, cautery.heat_grid_divisor): no value crosses from one UV
chart to its neighbour in UV space, bounds hold, and a burn measures the same on either grid."""
import numpy as np
import pytest

from lab.bench.heat import SPHERE_RADIUS_MM, sphere_surface
from sims.scene.config import REPO_ROOT
from sims.surface.resample import GridResampler
from sims.surface.texels import surface_at


@pytest.fixture(scope="module")
def sphere_pair():
    fine = sphere_surface(256)
    return surface_at(fine, 128), fine


def two_charts_touching_in_uv():
    """Two 10 mm squares 10 mm apart in z whose UV charts share the line u = 0.5 (no gutter between them)."""
    import trimesh
    from trimesh.visual import TextureVisuals

    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    vertices = np.concatenate([np.c_[10 * corners, np.zeros(4)], np.c_[10 * corners, np.full(4, 10.0)]])
    uv = np.concatenate([corners * [0.5, 1.0], corners * [0.5, 1.0] + [0.5, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return trimesh.Trimesh(vertices, faces, visual=TextureVisuals(uv=uv), process=False)


def test_values_never_cross_to_a_chart_that_only_touches_in_uv():
    """f = z on the coarse grid of two charts side by side in UV but 10 mm apart: every display texel reads its own
    chart's value exactly (a tap across the shared line would mix in 10 mm)."""
    from sims.surface.texels import build_surface

    fine = build_surface(two_charts_touching_in_uv(), 64)
    coarse = surface_at(fine, 32)
    read = GridResampler(coarse, fine).array(coarse.position_mm[..., 2])
    np.testing.assert_allclose(read[fine.mask], fine.position_mm[..., 2][fine.mask], atol=1e-4)


def test_a_linear_field_on_the_sphere_of_many_charts_is_read_to_within_a_coarse_texel(sphere_pair):
    """f = z (mm) on the coarse grid, read at every fine texel: off by at most a coarse texel's reach everywhere,
    bilinear inside the charts, and within the coarse values' bounds."""
    coarse, fine = sphere_pair
    resampler = GridResampler(coarse, fine)
    read = resampler.array(np.where(coarse.mask, coarse.position_mm[..., 2], 0.0))
    error = np.abs(read - fine.position_mm[..., 2])[fine.mask]
    coarse_side = float(np.median((np.linalg.norm(coarse.tangent_u, axis=-1) + np.linalg.norm(coarse.tangent_v, axis=-1))[coarse.mask]))
    assert error.max() < 1.5 * coarse_side < 0.2 * SPHERE_RADIUS_MM
    assert np.median(error) < 0.1 * coarse_side  # bilinear inside charts
    values = coarse.position_mm[..., 2][coarse.mask]
    assert values.min() - 1e-4 <= read[fine.mask].min() and read[fine.mask].max() <= values.max() + 1e-4


def test_the_taichi_gather_matches_the_numpy_one(sphere_pair):
    import taichi as ti

    coarse, fine = sphere_pair
    resampler = GridResampler(coarse, fine)
    values = np.random.default_rng(3).uniform(37.0, 250.0, coarse.mask.shape).astype(np.float32)
    src, dst = ti.field(ti.f32, coarse.mask.shape), ti.field(ti.f32, fine.mask.shape)
    src.from_numpy(values)

    @ti.kernel
    def gather():
        for r, c in dst:
            dst[r, c] = resampler.sample(src, r, c)

    gather()
    np.testing.assert_allclose(dst.to_numpy()[fine.mask], resampler.array(values)[fine.mask], rtol=1e-6)
    layered = np.stack([values, 2.0 * values])
    assert resampler.array(layered).shape == (2,) + fine.mask.shape


def test_the_default_scene_burns_alike_on_the_display_grid_and_on_a_grid_half_as_fine(tmp_path):
    """The first 3 s of the default scene (stroke and spatula) with heat on the 512² display grid and on the 256²
    heat grid (the default): coagulated area and depth within 3 %, the state arrays at display size and the look
    nearly the same."""
    from sims.scene.assembly import Scene

    runs = {}
    for divisor in (1, 2):
        scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", [f"cautery.heat_grid_divisor={divisor}"])
        for _ in range(300):
            scene.step()
        runs[divisor] = scene.metrics()["cautery"], scene.state_arrays(), scene.composite().astype(float)
    (fine, fine_state, fine_rgb), (coarse, coarse_state, coarse_rgb) = runs[1], runs[2]
    assert coarse["coagulated_area_mm2"] > 20.0
    for key in ("coagulated_area_mm2", "coagulation_depth_mm", "coagulated_volume_mm3"):
        assert coarse[key] == pytest.approx(fine[key], rel=0.03), key
    for name, values in fine_state.items():
        assert coarse_state[name].shape == values.shape, name
    mask = fine_state["texel_mask"]
    burnt = (fine_state["damage_omega"] >= 1.0) != (coarse_state["damage_omega"] >= 1.0)
    assert burnt[mask].mean() < 0.01  # texels the two disagree on: the rim of the burn
    assert np.abs(fine_rgb - coarse_rgb).mean() < 2.0
