"""The browser front end in real headless Chromium: lab.stream.TextureStream on a viser server.

One viser server, one scene (the liver patch at 256^2 with a ball electrode that has no scripted
path) and one simulation thread for the whole module: the thread steps the scene, moves the
electrode as the running test asks, and streams the composite texture about 10 times a second.
The scene background is a flat blue so that a hole in the mesh (a tile missing from a drawn frame)
is unambiguous in a screenshot.
"""
from __future__ import annotations

import math
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests import browser

pytestmark = pytest.mark.skipif(not browser.have_chromium(), reason=f"needs the Debian chromium package at {browser.CHROMIUM} (apt-get install chromium)")

REPO_ROOT = Path(__file__).resolve().parents[1]
VIEWPORT = {"width": 800, "height": 500}
FOV_DEG = 50.0
BACKGROUND = (20, 40, 220)
BALL_RADIUS_MM = 2.0
PRESS_MM = 0.3              # ball centre this far into the tissue along the normal
STEPS_PER_UPDATE = 5        # 0.05 s of simulated time per update
UPDATE_PERIOD_S = 0.1
CIRCLE_RADIUS_MM, CIRCLE_RAD_PER_S = 4.0, 1.5   # the electrode burns circles to keep the texture changing
STREAM_CENTRES = {"first": (-20.0, -13.0), "second": (18.0, -13.0)}

SCENE_YAML = f"""
name: browser_test
mesh: meshes/patch.obj
texture_size: 256
models: [cautery]
duration_s: 3600
instruments:
  - name: ball
    shape: {{type: ball, radius_mm: {BALL_RADIUS_MM}}}
    tip_temperature_c: 300
    position_mm: [0, 0, 60]
    energized: false
"""


class Lab:
    """Server, stream and simulation thread. Tests change what the electrode does through `drive`."""

    def __init__(self, scene_file: Path):
        import viser
        from scipy.spatial import cKDTree

        from lab.stream import TextureStream, camera_for, set_initial_camera
        from sims.scene import Scene

        self.scene = Scene.from_file(scene_file, arch="cpu")
        # Taichi materialises fields on the first kernel launch, and only the main thread may do that:
        # one step and one composite here, before the simulation thread takes the scene over.
        self.scene.step()
        self.scene.composite()
        surface = self.scene.surface
        self._texel_xyz = surface.position_mm[surface.mask].astype(np.float64)
        self._texel_normal = surface.normal[surface.mask].astype(np.float64)
        self._texel_tree = cKDTree(self._texel_xyz[:, :2])
        self.port = browser.free_port()
        self.url = f"http://127.0.0.1:{self.port}/"
        self.server = viser.ViserServer(host="127.0.0.1", port=self.port, verbose=False)
        self.server.scene.set_background_image(np.full((4, 4, 3), BACKGROUND, np.uint8), format="png")
        aspect = VIEWPORT["width"] / VIEWPORT["height"]
        set_initial_camera(self.server, surface, fov_deg=FOV_DEG, aspect=aspect)
        self.camera = camera_for(surface, fov_deg=FOV_DEG, aspect=aspect)
        self.covered = browser.footprint(surface.vertices_mm, surface.faces, *self.camera, math.radians(FOV_DEG),
                                         (VIEWPORT["width"], VIEWPORT["height"]), erode_px=3)
        self.stream = TextureStream(self.server, surface)
        self.errors: list[BaseException] = []
        self.updates: list[dict] = []
        self._program, self._program_start = ("idle",), None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim", daemon=True)
        self._thread.start()

    # --- what the electrode does (read by the simulation thread every step) --------------------
    def drive(self, *program) -> None:
        """("idle",) lifts it off; ("circle", x, y) burns a circle about (x, y); ("press", x, y) holds it energized on (x, y)."""
        with self._lock:
            self._program, self._program_start = program, None

    def surface_point(self, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
        _, index = self._texel_tree.query([x, y])
        return self._texel_xyz[index], self._texel_normal[index]

    def pixel(self, x: float, y: float) -> np.ndarray:
        """Where the surface point above (x, y) appears in a VIEWPORT screenshot."""
        point, _ = self.surface_point(x, y)
        size = (VIEWPORT["width"], VIEWPORT["height"])
        return browser.project(point, *self.camera, math.radians(FOV_DEG), size)[0]

    def _pose(self, t_s: float):
        with self._lock:
            if self._program_start is None:
                self._program_start = t_s
            program, elapsed = self._program, t_s - self._program_start
        if program[0] == "idle":
            return np.array([0.0, 0.0, 60.0]), False
        if program[0] == "circle":
            angle = CIRCLE_RAD_PER_S * elapsed
            x, y = program[1] + CIRCLE_RADIUS_MM * math.cos(angle), program[2] + CIRCLE_RADIUS_MM * math.sin(angle)
        else:
            x, y = program[1], program[2]
        point, normal = self.surface_point(x, y)
        return point + normal * (BALL_RADIUS_MM - PRESS_MM), True

    def _run(self) -> None:
        base = self.scene.instruments[0].base
        try:
            while not self._stop.is_set():
                started = time.monotonic()
                for _ in range(STEPS_PER_UPDATE):
                    base.position_mm, base.energized = self._pose(self.scene.time_s)
                    self.scene.step()
                result = self.stream.update(self.scene.composite())
                self.updates.append({**result, "t": time.monotonic()})
                self._stop.wait(max(0.0, UPDATE_PERIOD_S - (time.monotonic() - started)))
        except BaseException as exc:  # reported by the tests
            self.errors.append(exc)
            raise

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=30)
        self.stream.close()
        self.server.stop()


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    scene_file = tmp_path_factory.mktemp("browser") / "scene.yaml"
    scene_file.write_text(SCENE_YAML)
    lab = Lab(scene_file)
    yield lab
    lab.close()
    assert not lab.errors, f"the simulation thread raised: {lab.errors!r}"


@pytest.fixture(scope="module")
def chromium():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        instance = browser.launch(playwright)
        yield instance
        instance.close()


@pytest.fixture(scope="module")
def page(lab, chromium):
    """One browser page for the module (page loads are slow in software WebGL); the last test closes it."""
    viewer = _open(chromium, lab)
    yield viewer
    if not viewer.closed:
        viewer.close()


def _tissue_count(image: np.ndarray) -> int:
    return int(browser.tissue_mask(image).sum())


def _holes(lab, image: np.ndarray) -> int:
    return browser.hole_pixels(image, lab.covered, BACKGROUND)


def _open(chromium, lab) -> browser.Viewer:
    """A new page, once every tile of the mesh has arrived (no background left where the patch projects)."""
    viewer = browser.Viewer(chromium, lab.url, viewport=VIEWPORT)

    def whole_mesh_shown(image):
        return _holes(lab, image) == 0 and _tissue_count(image) > 0.1 * lab.covered.sum()

    viewer.wait_for(whole_mesh_shown, timeout_s=90, save_to=Path(tempfile.gettempdir()) / "tissue-lab-open-timeout.png")
    return viewer


def _check_thread(lab) -> None:
    assert not lab.errors, f"the simulation thread raised: {lab.errors!r}"
    assert lab.alive, "the simulation thread stopped"


def test_page_loads_from_localhost_only_and_shows_the_tissue(lab, page, tmp_path):
    lab.drive("circle", *STREAM_CENTRES["first"])
    image = page.screenshot()
    browser.save(image, tmp_path / "loaded.png")
    height, width = image.shape[:2]
    middle = image[height // 3: 2 * height // 3, width // 3: 2 * width // 3]
    assert browser.tissue_mask(middle).mean() > 0.5, "the middle of the view does not show the tissue"
    remote = [url for url in page.requests if not browser.is_local(url)]
    assert page.requests and not remote, f"the page fetched from outside localhost: {remote[:5]}"
    assert not page.errors, f"page errors: {page.errors[:3]}"
    _check_thread(lab)


def test_mesh_never_blanks_while_the_texture_streams(lab, page, tmp_path):
    lab.drive("circle", *STREAM_CENTRES["first"])
    sent_before = lab.stream.stats["tiles_sent"]
    # Every frame the page draws for 10 s, and on until there are 20 of them. (Screenshots would make the page
    # draw extra frames; software WebGL draws about one a second here while the texture streams.)
    frames = page.record(min_seconds=10, min_frames=20, max_seconds=40)
    tiles_sent = lab.stream.stats["tiles_sent"] - sent_before
    assert len(frames) >= 8, f"only {len(frames)} frames drawn in 40 s while streaming"
    counts = np.array([_tissue_count(image) for image in frames])
    holes = np.array([_holes(lab, image) for image in frames])
    for index in np.flatnonzero(holes > 20):
        browser.save(frames[index], tmp_path / f"hole_{index:02d}.png")
    browser.save(frames[-1], tmp_path / "last.png")
    assert tiles_sent > 0, "nothing was streamed during the check"
    assert counts.min() > 0.8 * np.median(counts), f"tissue pixels dropped: {counts.tolist()}"
    assert (holes <= 20).all(), f"frames with a hole in the mesh: {np.flatnonzero(holes > 20).tolist()} of {len(frames)} (pixels {holes.tolist()}); see {tmp_path}"
    changes = [int((np.abs(a.astype(int) - b).max(axis=-1) > 30).sum()) for a, b in zip(frames, frames[1:])]
    assert max(changes) > 20, "the view never changed while streaming"
    _check_thread(lab)
