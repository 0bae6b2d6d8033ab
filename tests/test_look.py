"""The look (sims.look.compose, sims.look.film): blood's colour from its thickness against the two-flux equations it solves and
against what whole blood does to light (docs/model/look.md "Blood colour"), the film kept on simulated time, relief and gloss in the
normal and roughness maps, the dried stain."""
import numpy as np
import pytest
import scipy.linalg
import taichi as ti
from PIL import Image

from lab.runner import run
from sims.look.compose import (
    BLOOD_MU_A_DEOXY,
    BLOOD_MU_A_OXY,
    BLOOD_MU_S_REDUCED,
    CLOT_SATURATION,
    FRESH_SATURATION,
    blood_layer,
)
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT

BLEEDING = REPO_ROOT / "scenes" / "bleeding.yaml"


@ti.kernel
def _layer(ground: ti.types.vector(3, ti.f32), thickness_mm: ti.f32, saturation: ti.f32) -> ti.types.vector(3, ti.f32):
    return blood_layer(ground, thickness_mm, saturation)


def layer(ground, thickness_mm, saturation=FRESH_SATURATION) -> np.ndarray:
    return _layer(ti.Vector(list(map(float, ground))), float(thickness_mm), float(saturation)).to_numpy()


def two_flux(ground: float, thickness_mm: float, k: float, s: float) -> float:
    """Reflectance of a layer from the Kubelka-Munk differential equations themselves (not their closed form): down
    flux I and up flux J, dI/dz = -(K + S) I + S J, dJ/dz = (K + S) J - S I, I(0) = 1, J(h) = ground I(h); R = J(0)."""
    m = scipy.linalg.expm(np.array([[-(k + s), s], [-s, k + s]]) * thickness_mm)
    return (ground * m[0, 0] - m[1, 0]) / (m[1, 1] - ground * m[0, 1])


@pytest.mark.parametrize("thickness_mm", [0.002, 0.03, 0.3, 2.0])
@pytest.mark.parametrize("ground", [0.05, 0.6])
def test_the_blood_layer_solves_the_two_flux_equations(thickness_mm, ground):
    saturation = 0.6
    mu_a = saturation * np.array(BLOOD_MU_A_OXY) + (1 - saturation) * np.array(BLOOD_MU_A_DEOXY)
    expected = [two_flux(ground, thickness_mm, 2 * a, 0.75 * s) for a, s in zip(mu_a, BLOOD_MU_S_REDUCED)]
    np.testing.assert_allclose(layer([ground] * 3, thickness_mm, saturation), expected, rtol=2e-3, atol=2e-5)


def test_a_tenth_of_a_millimetre_hides_green_and_blue_while_red_passes_millimetres():
    """docs/model/look.md "Blood colour": 0.1 mm of blood already hides blue and green; red passes through millimetres (its absorption
    alone; with blood's scattering, about one). Over white."""
    white = np.ones(3)
    film = layer(white, 0.1)
    assert film[1] < 0.1 and film[2] < 0.1  # what comes back is blood's own few per cent, not the tissue
    assert film[0] > 0.5 > 5 * max(film[1], film[2])
    deep = layer(white, 5.0)  # blood's own colour
    assert np.all(layer(white, 0.05)[1:] < 0.05)  # green and blue: less than 5 % of white comes back through 0.05 mm
    assert layer(white, 0.5)[0] > 1.4 * deep[0]  # red still shows the tissue through half a millimetre
    assert np.array_equal(layer(white * 0.4, 0.0), white * np.float32(0.4))  # no blood: the tissue as it is


def test_a_settled_pool_is_darker_than_a_running_film():
    pale = np.array([0.55, 0.35, 0.28])  # coagulum, linear
    film, pool = layer(pale, 0.05), layer(pale, 3.0, CLOT_SATURATION)
    assert film[0] > 1.5 * pool[0]  # a thin film shows the pale tissue red through it; a clotted pool is dark red
    assert film[0] > 3 * film[1] and pool[0] > 3 * pool[1]  # both red
    assert pool[0] < 0.6 * layer(pale, 3.0)[0]  # clotted blood is darker than fresh blood as deep


def test_the_picture_depends_on_simulated_time_only(tmp_path):
    """final.png of the bleeding scene after 2 s is the same whether frames were written every 0.1 s or never."""
    pictures = []
    for name, every in (("plain", None), ("frames", 0.1)):
        scene = Scene.from_file(BLEEDING, ["texture_size=256"])
        run(scene, tmp_path / name, duration_s=2.0, frames_every_s=every, progress=False)
        pictures.append([np.asarray(Image.open(tmp_path / name / f"{file}.png"))
                         for file in ("final", "final_normal", "final_roughness")])
    assert len(list((tmp_path / "frames" / "frames").iterdir())) == 21
    for plain, framed in zip(*pictures):
        assert np.array_equal(plain, framed)


def _bled(changes=()):
    scene = Scene.from_file(BLEEDING, ["texture_size=128", "bleed_points.0.rate_ml_s=0.1", *changes])
    for _ in range(150):
        scene.step()
    return scene


def test_blood_stands_up_as_relief_and_is_glossy():
    """The normal map tilts away from the blood at a pool's edge (its surface is raised and rounded), and wet blood is
    smoother than the capsule."""
    scene = _bled()
    scene.composite()
    normal, roughness = scene.material_maps()
    depth = scene.film.resampler.array(scene.film.trail.to_numpy())
    rows, cols = np.gradient(depth)
    edge = scene.surface.mask & (np.hypot(rows, cols) > 0.02)  # mm per texel
    n = normal.astype(np.float64) - 127.5
    # glTF normal maps: x along columns, y toward lower rows; a raised edge tilts the normal down the slope
    along = -(n[..., 0] * cols - n[..., 1] * rows)
    assert edge.sum() > 50
    assert (along[edge] > 0).mean() > 0.9
    wet = scene.surface.mask & (depth > 0.1)
    dry = scene.surface.mask & (scene.film.resampler.array(scene.film.stain.to_numpy()) == 0)
    assert np.median(roughness[wet]) < 0.2 * 255 < 0.3 * 255 < np.median(roughness[dry])


def test_a_dried_stain_stays_after_the_blood_is_gone():
    scene = _bled(["bleeding.lifetime_s=0.3", "bleed_points.0.path=[{t_s: 1.0, rate_ml_s: 0.1}, {t_s: 1.01, rate_ml_s: 0}]",
                   "bleed_points.1.rate_ml_s=0"])
    clean = Scene.from_file(BLEEDING, ["texture_size=128", "bleed_points=[]"]).composite().astype(np.float64)
    for _ in range(300):  # 3 s after the bleeding stopped: ten lifetimes
        scene.step()
    assert scene.bleeding.metrics()["volume_ml"] < 1e-3
    shown = scene.composite().astype(np.float64)
    stained = scene.film.resampler.array(scene.film.stain.to_numpy()) > 0.1
    assert stained.sum() > 20
    assert shown[stained].mean() < 0.85 * clean[stained].mean()  # darker than the tissue there
    ratio = shown[stained][:, 1].mean() / shown[stained][:, 0].mean()
    assert ratio < clean[stained][:, 1].mean() / clean[stained][:, 0].mean()  # and redder-brown
    assert np.array_equal(shown[~stained & (scene.film.resampler.array(scene.film.stain.to_numpy()) == 0)],
                          clean[~stained & (scene.film.resampler.array(scene.film.stain.to_numpy()) == 0)])


def test_a_burn_sinks_and_its_char_is_matte():
    scene = Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", ["texture_size=128"])
    for _ in range(700):
        scene.step()
    scene.composite()
    normal, roughness = scene.material_maps()
    state = scene.state_arrays()
    char, omega = state["char"] > 0.8, state["damage_omega"]
    coagulated = (omega > 100) & ~(state["char"] > 0.05)
    healthy = scene.surface.mask & (omega == 0)
    assert char.sum() > 5 and coagulated.sum() > 50
    assert np.median(roughness[char]) > np.median(roughness[coagulated]) > np.median(roughness[healthy])
    height = scene.composer.relief.to_numpy()
    assert np.median(height[coagulated]) < np.median(height[healthy]) - 0.02  # shrinkage, mm


def test_a_surface_map_that_is_no_image_is_refused_with_its_key_named():
    from sims.scene.config import ConfigError

    with pytest.raises(ConfigError) as error:
        Scene.from_file(BLEEDING, ["texture_size=32", "look.stages=[{name: healthy, texture: textures/liver_healthy.png, "
                                   "surface: meshes/patch.obj, relief_mm: 0.1}]"])
    assert "look.stages.0.surface" in str(error.value) and "patch.obj" in str(error.value)


def test_the_look_smooths_the_film_everywhere_it_reaches_and_skips_only_dry_texels():
    """The smoothed blood depth the look lights equals a full pass (the coarse film read at every texel's fill source,
    then the tent filter): skipping texels far from any blood loses nothing."""
    from scipy.ndimage import convolve1d

    scene = _bled()
    scene.composite()
    film, fill = scene.film, scene.surface.fill_index
    read = film.resampler.array(film.trail.to_numpy()).ravel()[fill.ravel()].reshape(fill.shape)
    radius = film.display_per_texel // 2
    tent = (radius + 1 - np.abs(np.arange(-radius, radius + 1))) / (radius + 1) ** 2
    expected = convolve1d(convolve1d(read, tent, axis=1, mode="nearest"), tent, axis=0, mode="nearest")
    shown = scene.composer.blood.to_numpy()
    assert (shown > 0).mean() < 0.8 and (expected > 0).sum() > 100
    np.testing.assert_allclose(shown, expected, atol=1e-5)
