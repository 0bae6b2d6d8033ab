"""The scene's models behind one interface (sims.scene.models): a model added to the registry runs beside the others
with no change to the scene, models step in the registry's order, and live parameters reach the model that reads them."""
import math

import numpy as np
import pytest

from sims.scene import models
from sims.scene.assembly import Scene
from sims.scene.checked import Refused
from sims.scene.config import REPO_ROOT, ConfigError, load_scene_config

HEMOSTASIS = REPO_ROOT / "scenes" / "hemostasis.yaml"


class Ticks(models.SceneModel):
    """A model the look does not show: counts its steps, records the order models step in, can be made NaN."""

    name, sections = "ticks", ()
    order: list = []  # names of the models in the order they stepped (this class and the patched HeatModel append)

    def __init__(self, surface, config, links):
        super().__init__(config)
        self.steps, self.value = 0, 0.0
        self.texels = int(surface.mask.sum())

    def step(self, dt, time_s):
        Ticks.order.append(self.name)
        self.steps += 1
        return True

    def reset(self):
        self.steps = 0

    def state_arrays(self, display_grid=True):
        return {"tick_value": np.full(2, self.value, np.float32)}

    def metrics(self, time_s, dt):
        return {"steps": self.steps, "texels": self.texels}


@pytest.fixture()
def with_ticks(monkeypatch):
    """The registry with Ticks after the cautery and the bleeding; the heat model's steps recorded too."""
    monkeypatch.setitem(models.MODELS, "ticks", Ticks)
    heat_step = models.HeatModel.step

    def recorded(self, dt, time_s):
        Ticks.order.append(self.name)
        return heat_step(self, dt, time_s)

    monkeypatch.setattr(models.HeatModel, "step", recorded)
    Ticks.order = []
    return Ticks


def test_a_model_in_the_registry_steps_resets_and_reports_beside_the_others(with_ticks):
    scene = Scene(load_scene_config(HEMOSTASIS, {"models": ["ticks", "cautery"], "texture_size": 64}), "cpu")
    for _ in range(3):
        scene.step()
    ticks = scene.model("ticks")
    assert ticks.steps == 3 and ticks.texels == int(scene.surface.mask.sum())
    assert Ticks.order == ["cautery", "ticks"] * 3  # the registry's order, not the file's
    metrics = scene.metrics()
    assert metrics["ticks"] == {"steps": 3, "texels": ticks.texels} and "cautery" in metrics and "bleeding" not in metrics
    assert "tick_value" in scene.state_arrays() and "temperature_c" in scene.state_arrays()
    assert scene.non_finite_field() is None
    ticks.value = math.nan
    scene.step()
    assert scene.non_finite_field() == "tick_value"
    scene.reset()
    assert ticks.steps == 0 and scene.time_s == 0.0
    assert scene.bleed_points == [] and scene.bleeding is None and scene.model("bleeding") is None


def test_a_scene_file_may_name_only_the_models_in_the_registry(with_ticks):
    config = load_scene_config(HEMOSTASIS, {"models": ["ticks"], "texture_size": 64})
    assert config["models"] == ["ticks"]
    with pytest.raises(ConfigError, match="smoke.*expected one of: cautery, bleeding, ticks"):
        load_scene_config(HEMOSTASIS, {"models": ["smoke"]})


def test_a_live_parameter_reaches_the_model_that_reads_its_section():
    scene = Scene(load_scene_config(HEMOSTASIS, {"texture_size": 64}), "cpu")
    blood = scene.model("bleeding")
    scene.set_parameter("look.blood_trail_s", 2.5)
    assert blood.config["look"]["blood_trail_s"] == 2.5
    scene.set_parameter("tissue.conductivity_w_mk", 1.5)
    assert scene.model("cautery").config["tissue"]["conductivity_w_mk"] == 1.5
    assert scene.cautery.diffusivity_mm2_s > 0.3  # the heat model reads the new value
    with pytest.raises(KeyError, match="not a parameter of the bleeding model"):
        blood.set("tissue.conductivity_w_mk", 1.0)
    with pytest.raises(Refused):
        scene.set_parameter("cautery.layers", 3)  # takes a rebuild
