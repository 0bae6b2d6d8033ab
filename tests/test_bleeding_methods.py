"""A scene picks its bleeding method (bleeding.method, sims.blood.methods): the parameters, metrics and state arrays come from
the method in use, with the common keys in the same units for both, and a key of the other method is refused."""
import numpy as np
import pytest

from sims.scene import params
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT, ConfigError, load_scene_config

COMMON = ("blood_area_mm2", "max_thickness_mm", "volume_ml", "spawned_ml", "on_surface_ml", "suctioned_ml",
          "left_surface_ml", "dried_ml")


def bleeding_scene(method: str, *changes: str, size: int = 64) -> Scene:
    return Scene.from_file(REPO_ROOT / "scenes" / "bleeding.yaml",
                           [f"texture_size={size}", "bleeding={}", f"bleeding.method={method}", "bleed_points.0.rate_ml_s=0.2", *changes])


@pytest.mark.parametrize("method", ["particles", "height_field"])
def test_the_method_in_use_gives_the_parameters_metrics_and_state(method):
    scene = bleeding_scene(method, *(["bleeding.grid_divisor=1"] if method == "height_field" else []))  # display grid
    assert scene.bleeding.method == method
    offered = {key.split(".", 1)[1] for key in scene.parameters() if key.startswith("bleeding.")}
    assert offered == set(params.BLEEDING_METHODS[method])  # the sliders follow the method
    rebuild = {key for key, parameter in scene.parameters().items() if key.startswith("bleeding.") and not parameter.live}
    assert rebuild == ({"bleeding.capacity"} if method == "particles" else {"bleeding.grid_divisor"})
    for _ in range(40):
        scene.step()
    metrics = scene.metrics()["bleeding"]
    assert metrics["method"] == method
    spawned = 40 * 0.01 * 0.2
    assert metrics["spawned_ml"] == pytest.approx(spawned, rel=0.1)  # ml for both methods (particles: whole ones)
    accounted = metrics["on_surface_ml"] + metrics["suctioned_ml"] + metrics["left_surface_ml"] + metrics["dried_ml"]
    assert accounted == pytest.approx(metrics["spawned_ml"], rel=1e-9)
    assert metrics["volume_ml"] == metrics["on_surface_ml"] > 0.5 * spawned
    assert metrics["blood_area_mm2"] > 0 and metrics["max_thickness_mm"] > 0
    thickness = scene.state_arrays()["blood_thickness_mm"]
    assert thickness.shape == scene.surface.mask.shape and np.isfinite(thickness).all()
    assert thickness.max() == pytest.approx(metrics["max_thickness_mm"], rel=1e-5)
    assert scene.composite().shape == (64, 64, 3)


def test_the_height_field_on_a_coarser_grid_is_shown_on_the_display_grid():
    """bleeding.grid_divisor 4: blood runs on 32^2 texels under a 128^2 display. Bleed points (display texels) land on
    the coarse texel under them, the displayed depth is the coarse depth read bilinearly (a convex combination: never
    deeper than the deepest coarse texel, and it holds the same volume), and the metrics come from the coarse grid."""
    scene = bleeding_scene("height_field", "bleeding.grid_divisor=4", "look.blood_trail_s=0", size=128)
    blood = scene.bleeding
    assert blood.surface.size == 32 and scene.film.trail.shape == (32, 32)
    for _ in range(40):
        scene.step()
    depth = blood.depth_mm()
    shown = scene.film.resampler.array(scene.film.trail.to_numpy())  # what the look reads at display texels
    arrays = scene.state_arrays()
    assert arrays["blood_thickness_mm"].shape == arrays["blood_stain_mm"].shape == (128, 128)
    assert 0 < shown.max() <= depth.max() * (1 + 1e-6)
    assert scene.metrics()["bleeding"]["max_thickness_mm"] == pytest.approx(depth.max(), rel=1e-6)
    volume_shown = float((arrays["blood_thickness_mm"] * scene.surface.texel_area_mm2)[scene.surface.mask].sum())
    volume = scene.metrics()["bleeding"]["volume_ml"] * 1000.0
    print(f"coarse grid: {volume:.2f} mm^3 on the surface, {volume_shown:.2f} mm^3 read on the display grid")
    assert volume_shown == pytest.approx(volume, rel=0.1)
    point = scene.texel_near(scene.bleed_points[0].position_at(0.0))
    assert arrays["blood_thickness_mm"][point] > 0.5 * shown.max()  # the blood is where the point bleeds


def test_a_key_of_the_other_method_is_refused_with_the_method_named():
    path = REPO_ROOT / "scenes" / "bleeding.yaml"
    assert load_scene_config(path)["bleeding"]["method"] == "height_field"  # the shipped scenes use the height field
    with pytest.raises(ConfigError) as error:
        load_scene_config(path, ["bleeding.method=height_field", "bleeding.particle_spacing_mm=0.5"])
    assert error.value.key == "bleeding.particle_spacing_mm" and "particles method" in error.value.message
    with pytest.raises(ConfigError) as error:
        load_scene_config(path, ["bleeding.method=particles", "bleeding.pinning_depth_mm=0.1"])
    assert error.value.key == "bleeding.pinning_depth_mm" and "height_field method" in error.value.message
    with pytest.raises(ConfigError) as error:
        load_scene_config(path, ["bleeding.method=goo"])
    assert error.value.key == "bleeding.method"
    assert load_scene_config(path, ["bleeding={}"])["bleeding"]["method"] == "height_field"  # a scene that names none
    with pytest.raises(ConfigError) as error:  # one written for the particles without naming them: told what to add
        load_scene_config(path, ["bleeding={substeps: 2}"])
    assert error.value.key == "bleeding.substeps" and "add bleeding.method: particles" in error.value.message
