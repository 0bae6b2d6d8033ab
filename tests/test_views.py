"""The scene's one frame path and the views behind one interface (lab.views): the blocks of the display maps travel
as a TileMask, PNG frames and the browsers' stream are both a View."""
import numpy as np
import pytest
from PIL import Image

from lab.runner import write_png
from lab.views import PngFrames, View
from sims.look.tile_mask import TileMask
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT


@pytest.fixture(scope="module")
def scene():
    return Scene.from_file(REPO_ROOT / "scenes" / "default.yaml", ["texture_size=64"], "cpu")


def test_the_display_changes_travel_as_a_tile_mask_on_the_display_grid(scene):
    pending = scene.pending_display_changes()
    assert isinstance(pending, TileMask) and pending.flags.dtype == bool
    assert pending.flags.shape == tuple(-(-64 // pending.tile) for _ in range(2)) == scene.display_tiles.grid
    scene.composite(pending)
    changed = scene.take_display_changes()
    assert isinstance(changed, TileMask) and changed.flags.all()  # the first compose writes every tile
    assert TileMask.of((changed.tile, changed.flags.astype(int))).flags.dtype == bool
    with pytest.raises(ValueError, match="blocks of"):
        scene.composite(TileMask(2 * pending.tile, pending.flags))


def test_png_frames_are_a_view_that_numbers_the_base_colour(scene, tmp_path):
    from lab.web.stream import TextureStream

    assert issubclass(TextureStream, View) and issubclass(PngFrames, View)
    frames = PngFrames(tmp_path / "frames", write_png)
    shown = [frames.show(scene) for _ in range(2)]
    scene.step()
    shown.append(frames.show(scene))
    assert [item["file"] for item in shown] == ["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    last = np.asarray(Image.open(tmp_path / "frames" / "frame_00002.png"))
    assert last.shape == (64, 64, 3) and np.array_equal(last, scene.composite())
