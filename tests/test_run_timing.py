"""A headless run's timings: the first step (kernels loaded or compiled) apart from the steps after it."""
import json

import pytest

from lab import runner
from sims.scene import Scene
from tests.test_cli import write_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The small scene (0.01 s steps), built once: each run goes on from where the last one stopped."""
    return Scene.from_file(write_scene(tmp_path_factory.mktemp("scene")), arch="cpu")


def _metrics(scene, tmp_path, duration_s: float) -> dict:
    """metrics.json of a run of `scene` for duration_s, as written and as returned."""
    returned = runner.run(scene, tmp_path / "out", duration_s, progress=False)
    written = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert written == returned
    return written


def test_steps_per_s_leaves_out_the_first_step(scene, tmp_path):
    metrics = _metrics(scene, tmp_path, 0.2)
    assert metrics["steps"] == 20  # the scene's first run
    first, wall = metrics["first_step_s"], metrics["wall_s"]
    assert isinstance(first, float) and 0.0 < first < wall
    assert metrics["steps_per_s"] == pytest.approx(19 / (wall - first), rel=1e-9)


@pytest.mark.parametrize("duration_s, first_step", [(0.01, True), (0.0, False)])
def test_a_run_without_later_steps_has_no_rate(scene, tmp_path, duration_s, first_step):
    """One step: its time, and no rate (JSON null, where a bare division gave a rate or Infinity); none: neither."""
    metrics = _metrics(scene, tmp_path, duration_s)
    assert metrics["steps_per_s"] is None
    assert (metrics["first_step_s"] is not None) == first_step
