"""Where a scene's pictures go, behind one small interface: `show(scene)` once per frame, `close()` at the end. Two
back ends: every browser (lab.web.stream.TextureStream: the tiles that changed, as GLB nodes) and numbered PNG files
(PngFrames: a headless run's --frames-every). A view takes what it needs from the scene's one frame path
(sims.scene.assembly.Scene.pending_display_changes, composite, material_maps, take_display_changes)."""
from __future__ import annotations

from pathlib import Path


class View:
    """One destination of a scene's frames."""

    def show(self, scene) -> dict:
        """Show the scene as it is now (a sims.scene.assembly.Scene); returns what it cost ({} when nothing to say)."""
        raise NotImplementedError

    def close(self) -> None:
        """Nothing more will be shown."""


class PngFrames(View):
    """Frames as folder/frame_00000.png, frame_00001.png, ...: the whole base colour (H, W, 3) each time."""

    def __init__(self, folder: Path, write_png):
        """write_png(path, rgb): how the run writes a PNG (lab.runner.write_png: its compression)."""
        self.folder, self.write_png, self.count = Path(folder), write_png, 0
        self.folder.mkdir()

    def show(self, scene) -> dict:
        path = self.folder / f"frame_{self.count:05d}.png"
        self.write_png(path, scene.composite())
        self.count += 1
        return {"file": path.name}
