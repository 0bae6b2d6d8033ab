"""The code paths a GPU takes, run on the CPU: the same bytes as the CPU's own paths.

On a GPU (sims.core.backend.on_cpu() False) every loop runs in parallel (sims.core.backend.serial), the particle sort and the
tile schedule's lists are built by blocks (sims.core.scan) instead of on one thread. Those paths must give what the
CPU's give, so that a scene is the same scene on any device.
"""
import numpy as np
import pytest

from sims.core import backend
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT, load_scene_config
from sims.surface.sleep_tiles import LIST_BLOCK


def state_after(scene_file: str, changes: list, steps: int, gpu_paths: bool) -> dict:
    scene = Scene(load_scene_config(REPO_ROOT / "scenes" / scene_file, changes))
    for _ in range(steps):
        scene.step()
    models = [model for model in (scene.cautery, scene.bleeding) if model is not None]
    if scene.cautery is not None:  # more than one block of tiles (sims.surface.sleep_tiles.LIST_BLOCK)
        assert scene.cautery.tiles.tiles > 4 * LIST_BLOCK
    assert [model.tiles.parallel_lists if hasattr(model, "tiles") else model.parallel_sort
            for model in models] == [gpu_paths] * len(models)
    return scene.state_arrays()


@pytest.mark.parametrize("scene_file, changes, steps", [
    ("hemostasis.yaml", ["texture_size=512"], 150),
    ("bleeding.yaml", ["texture_size=128", "bleeding.method=particles"], 60),
    ("default.yaml", ["texture_size=512", "cautery.scheme=implicit"], 100)])
def test_the_gpu_paths_give_the_cpu_bytes(monkeypatch, scene_file, changes, steps):
    cpu = state_after(scene_file, changes, steps, gpu_paths=False)
    monkeypatch.setattr(backend, "on_cpu", lambda: False)
    gpu = state_after(scene_file, changes, steps, gpu_paths=True)
    assert cpu.keys() == gpu.keys()
    for key in cpu:
        assert np.array_equal(cpu[key], gpu[key]), key
