"""The browser front end in real headless Chromium: the real lab (lab.web.app.LabApp) streaming the tissue texture
(lab.web.stream.TextureStream), and a TextureStream alone on a plane with material maps. The stream's bookkeeping and its
GLBs without a browser: tests/test_stream_glb.py.

For the browser tests, one LabApp for the module on a test scene (the liver patch at 256^2 texels with one ball
electrode that has no scripted path), with a flat blue background, so that a hole in the mesh (a tile missing from a
drawn frame) is unambiguous in a screenshot, and simple lighting (software WebGL draws several times faster without the
environment map and shadows). The tool's model and gizmo are hidden, so that they cover no burn. The electrode is driven
through the session's public commands (take_over, set_energized, release), as a browser's gizmo and checkbox do.
The lab's simulation loop runs on this (main) thread (Taichi), and only while a test waits in `Lab.run`; Chromium runs
on a thread of its own (testing.browser.BrowserThread), where every Playwright call is made. Every wait is a condition
with a generous timeout (the tests must pass on 2 shared cores at a load average of 10). Each page's camera is the
one the lab framed it with, read from the connected client.
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from testing import browser

needs_chromium = pytest.mark.skipif(not browser.have_chromium(), reason=f"needs the Debian chromium package at {browser.CHROMIUM} (apt-get install chromium)")

VIEWPORT = {"width": 800, "height": 500}
# viser's client URL option: draw the WebGL canvas at half resolution (screenshots stay 800 x 500). Software
# WebGL here draws about 1 frame/s at full resolution and 2 at half, which also shortens the browser's lag.
PAGE_QUERY = "?fixedDpr=0.5"
BACKGROUND = (20, 40, 220)
TOOL = "ball"
BALL_RADIUS_MM = 2.0
PRESS_MM = 0.3              # ball centre this far into the tissue along the normal
CIRCLE_RADIUS_MM, CIRCLE_RAD_PER_S = 4.0, 1.5   # the electrode burns circles to keep the texture changing
# Circles clear of the spots below, a fresh one per test (a circle burned over and over chars and stops changing)
STREAM_CENTRES = {"first": (-20.0, -13.0), "frozen": (18.0, 11.0), "second": (18.0, -13.0)}
# Pressed spots, in the middle of the view, away from viser's panel (top right) and notices (top left):
# the centre, and one off-centre spot whose mirror images (u or v flipped) must stay unburned.
ORIENTATION_SPOT = (-8.0, -6.0)
REGION_MM = 2.5             # half size of the squares checked about a spot (wider than the charred core of a burn)
OPEN_TIMEOUT_S = 240.0      # a page load, until every tile shows (software WebGL on a loaded machine)
WAIT_TIMEOUT_S = 120.0      # any other condition

SCENE_YAML = f"""
name: browser_test
mesh: meshes/patch.obj
texture_size: 256
models: [cautery]
duration_s: 3600
instruments:
  - name: {TOOL}
    shape: {{type: ball, radius_mm: {BALL_RADIUS_MM}}}
    tip_temperature_c: 300
    position_mm: [0, 0, 60]
    energized: false
"""


class Lab:
    """The real LabApp on the test scene and the browser thread. `run` runs the lab's loop here while the browser does
    something; `drive` says what the electrode does meanwhile (applied from the loop, through the session)."""

    def __init__(self, scene_file: Path, chrome: browser.BrowserThread):
        from scipy.spatial import cKDTree

        from lab.web.app import LabApp

        self.chrome = chrome
        self.app = LabApp(scene_file, "127.0.0.1", browser.free_port(), "cpu")
        self.app.server.scene.set_background_image(np.full((4, 4, 3), BACKGROUND, np.uint8), format="png")
        self.app.set_simple_lighting(True)
        for view in self.app.tool_views.values():
            view["body"].visible = False
            view["gizmo"].visible = False
        self.session = self.app.session
        surface = self.scene.surface
        self._texel_xyz = surface.position_mm[surface.mask].astype(np.float64)
        self._texel_normal = surface.normal[surface.mask].astype(np.float64)
        self._texel_tree = cKDTree(self._texel_xyz[:, :2])
        self.url = f"http://127.0.0.1:{self.app.server.get_port()}/"
        self._program, self._program_start, self._started = ("idle",), None, False

    @property
    def scene(self):
        return self.app.scene

    @property
    def stream(self):
        return self.app.stream

    @property
    def server(self):
        return self.app.server

    # --- what the electrode does (applied by the loop, about 20 times a second) ----------------
    def drive(self, *program) -> None:
        """("idle",) gives it back to its script (60 mm above the tissue, off); ("circle", x, y) burns a circle about
        (x, y); ("press", x, y) holds it energized on (x, y)."""
        self._program, self._program_start, self._started = program, None, False

    def surface_point(self, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
        _, index = self._texel_tree.query([x, y])
        return self._texel_xyz[index], self._texel_normal[index]

    def _drive(self) -> None:
        program, session = self._program, self.session
        if self._program_start is None:
            self._program_start = self.scene.time_s
        if program[0] == "idle":
            if not self._started:
                session.release(TOOL)
            self._started = True
            return
        if program[0] == "press" and self._started:
            return  # placed once
        x, y = program[1], program[2]
        if program[0] == "circle":
            angle = CIRCLE_RAD_PER_S * (self.scene.time_s - self._program_start)
            x, y = x + CIRCLE_RADIUS_MM * math.cos(angle), y + CIRCLE_RADIUS_MM * math.sin(angle)
        point, normal = self.surface_point(x, y)
        session.take_over(TOOL, point + normal * (BALL_RADIUS_MM - PRESS_MM))
        if not self._started:
            session.set_energized(TOOL, True)
        self._started = True

    # --- the loop -------------------------------------------------------------------------------
    def run(self, action=None, until=None, timeout_s: float = WAIT_TIMEOUT_S, what: str | None = None):
        """Run action(browser) on the browser thread while the lab's loop runs here (driving the electrode), until
        the action is done and until() holds (called on this thread, so it may read the scene). Returns what the
        action returned; raises what it raised, or AssertionError when timeout_s passed first."""
        job = self.chrome.submit(action or (lambda _: None))
        result = None

        def done():
            self._drive()
            return job.done() and (job.exception() is not None or until is None or until())

        finished = self.app.run(until=done, timeout_s=timeout_s)
        if job.done():
            result = job.result(timeout=0)  # raises what the browser side raised
        assert finished, (f"{what or getattr(until, '__name__', 'the browser action')} did not happen within {timeout_s:.0f} s "
                          f"({self.state()})")
        return result

    def state(self) -> str:
        """What the lab is doing, for failure messages."""
        clients = {client_id: self.stream.client_stats(client_id) for client_id in self.server.get_clients()}
        return (f"t = {self.scene.time_s:.2f} s, electrode {self._program}, held {self.scene.held_tools()}, notice "
                f"{self.session.notice!r}, stream {self.stream.stats}, browsers {clients}")

    def run_for(self, seconds: float) -> None:
        """The loop alone for this many seconds (of the stream's own delays, not a guess at the machine's speed)."""
        end = time.monotonic() + seconds
        self.run(until=lambda: time.monotonic() >= end, timeout_s=seconds + WAIT_TIMEOUT_S)

    def client(self, client_id: int):
        return self.server.get_clients().get(client_id)

    def close(self) -> None:
        self.app.close()


@pytest.fixture(scope="module")
def lab(tmp_path_factory, chrome):
    scene_file = tmp_path_factory.mktemp("browser") / "scene.yaml"
    scene_file.write_text(SCENE_YAML)
    lab = Lab(scene_file, chrome)
    yield lab
    lab.close()
    assert not lab.session.notice, f"the lab's loop stopped or refused a command: {lab.session.notice}"


@pytest.fixture(scope="module")
def page(lab):
    """One browser page for the module (page loads are slow in software WebGL); the last test closes it."""
    viewer = _open(lab)
    yield viewer
    if not lab.run(lambda _: viewer.closed):
        lab.run(lambda _: viewer.close())


def _tissue_count(image: np.ndarray) -> int:
    return int(browser.tissue_mask(image).sum())


def _holes(viewer, image: np.ndarray) -> int:
    """Background pixels where the page's camera sees the mesh."""
    return browser.hole_pixels(image, viewer.covered, BACKGROUND)


def _pixel(lab, viewer, x: float, y: float, offset_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Where the surface point above (x, y) (plus an offset) appears in the page's VIEWPORT screenshot."""
    point, _ = lab.surface_point(x, y)
    size = (VIEWPORT["width"], VIEWPORT["height"])
    return browser.project(point + np.asarray(offset_mm), *viewer.camera[:2], viewer.camera[2], size)[0]


def _open(lab) -> browser.Viewer:
    """A new page, with viser's panel minimized (as a user would, to see the tissue), once every tile of the mesh has
    arrived (no background left where the patch projects, for the camera the lab gave this page). The page gets
    `client_id`, `camera` (position, look_at, vertical fov in radians, as the browser reports it) and `covered`
    (the screenshot pixels the mesh covers)."""
    known = set(lab.server.get_clients())
    save_to = Path(tempfile.gettempdir()) / "tissue-lab-open-timeout.png"

    def load(instance):
        viewer = browser.Viewer(instance, lab.url + PAGE_QUERY, viewport=VIEWPORT)
        viewer.page.get_by_label("Minimize panel").first.click(timeout=OPEN_TIMEOUT_S * 1000)
        viewer.wait_for(lambda image: _tissue_count(image) > 1000, timeout_s=OPEN_TIMEOUT_S, save_to=save_to)
        return viewer

    viewer = lab.run(load, until=lambda: set(lab.server.get_clients()) - known, timeout_s=OPEN_TIMEOUT_S + 30,
                     what="the page connecting and showing tissue")
    (viewer.client_id,) = set(lab.server.get_clients()) - known
    camera = lab.client(viewer.client_id).camera  # as the browser reports it, now that it draws the lab's view
    viewer.camera = (np.array(camera.position), np.array(camera.look_at), float(camera.fov))
    viewer.covered = browser.footprint(lab.scene.surface.vertices_mm, lab.scene.surface.faces, *viewer.camera,
                                       (VIEWPORT["width"], VIEWPORT["height"]), erode_px=3)

    def whole_mesh_shown(image):
        return _holes(viewer, image) == 0 and _tissue_count(image) > 0.1 * viewer.covered.sum()

    lab.run(lambda _: viewer.wait_for(whole_mesh_shown, timeout_s=OPEN_TIMEOUT_S, save_to=save_to), timeout_s=OPEN_TIMEOUT_S + 30)
    return viewer


def _check_loop(lab) -> None:
    """The lab's loop ran on without an error (it would pause the scene and say so in the notice) or a refused
    command, and the simulation went on."""
    assert not lab.session.notice, f"the lab's loop stopped or refused a command: {lab.session.notice}"
    assert lab.session.broken is None and lab.session.running
    assert lab.scene.time_s > 0


@needs_chromium
def test_page_loads_from_localhost_only_and_shows_the_tissue(lab, page, tmp_path):
    lab.drive("circle", *STREAM_CENTRES["first"])
    image = lab.run(lambda _: page.screenshot())
    browser.save(image, tmp_path / "loaded.png")
    height, width = image.shape[:2]
    middle = image[height // 3: 2 * height // 3, width // 3: 2 * width // 3]
    assert browser.tissue_mask(middle).mean() > 0.5, f"the middle of the view does not show the tissue; see {tmp_path}"
    requests, errors = lab.run(lambda _: (list(page.requests), list(page.errors)))
    remote = [url for url in requests if not browser.is_local(url)]
    assert requests and not remote, f"the page fetched from outside localhost: {remote[:5]}"
    assert not errors, f"page errors: {errors[:3]}"
    _check_loop(lab)


@needs_chromium
def test_mesh_never_blanks_while_the_texture_streams(lab, page, tmp_path):
    lab.drive("circle", *STREAM_CENTRES["first"])
    sent_before = lab.stream.client_stats(page.client_id)["tiles_sent"]
    # Every frame the page draws for 10 s, and on until there are 20 of them. (Screenshots would make the page
    # draw extra frames, seconds each in software WebGL while the texture streams.)
    frames = lab.run(lambda _: page.record(min_seconds=10, min_frames=20, max_seconds=60), timeout_s=60 + WAIT_TIMEOUT_S)
    tiles_sent = lab.stream.client_stats(page.client_id)["tiles_sent"] - sent_before
    assert len(frames) >= 8, f"only {len(frames)} frames drawn in 60 s while streaming"
    counts = np.array([_tissue_count(image) for image in frames])
    holes = np.array([_holes(page, image) for image in frames])
    for index in np.flatnonzero(holes > 20):
        browser.save(frames[index], tmp_path / f"hole_{index:02d}.png")
    browser.save(frames[-1], tmp_path / "last.png")
    assert tiles_sent > 0, "nothing was streamed during the check"
    assert counts.min() > 0.8 * np.median(counts), f"tissue pixels dropped: {counts.tolist()}"
    assert (holes <= 20).all(), (f"frames with a hole in the mesh: {np.flatnonzero(holes > 20).tolist()} of {len(frames)} "
                                 f"(background pixels inside the mesh: {holes.tolist()}); see {tmp_path}")
    changes = [int((np.abs(a.astype(int) - b).max(axis=-1) > 30).sum()) for a, b in zip(frames, frames[1:])]
    assert max(changes) > 20, "the view never changed while streaming"
    _check_loop(lab)


@needs_chromium
def test_energized_instrument_whitens_the_tissue_under_it(lab, page, tmp_path):
    spots = {"centre": (0.0, 0.0), "spot": ORIENTATION_SPOT,
             "mirror_u": (-ORIENTATION_SPOT[0], ORIENTATION_SPOT[1]), "mirror_v": (ORIENTATION_SPOT[0], -ORIENTATION_SPOT[1])}
    pixels = {name: _pixel(lab, page, *xy) for name, xy in spots.items()}
    half_px = {name: max(4, int(round(np.abs(_pixel(lab, page, *xy, (REGION_MM, 0.0, 0.0)) - pixels[name]).max())))
               for name, xy in spots.items()}

    def white(image, name):  # whitish share of the square about a spot (its core may char dark)
        return browser.white_fraction(browser.region(image, pixels[name], half_px[name]))

    def turned_white(name):
        def check(image):
            return white(image, name) > 0.25
        check.__name__ = f"the tissue at {name} {spots[name]} mm turning white"
        return check

    lab.drive("idle")
    before = lab.run(lambda _: page.screenshot(), until=lambda: TOOL not in lab.scene.held_tools(), what="the electrode released")
    browser.save(before, tmp_path / "before.png")
    assert all(white(before, name) < 0.05 for name in spots), "a spot was white before the instrument touched it"
    try:
        for name in ("centre", "spot"):
            lab.drive("press", *spots[name])
            image = lab.run(lambda _, n=name: page.wait_for(turned_white(n), timeout_s=WAIT_TIMEOUT_S, save_to=tmp_path / "timeout.png"),
                            timeout_s=WAIT_TIMEOUT_S + 30)
            browser.save(image, tmp_path / f"{name}.png")
    finally:
        lab.drive("idle")
    # the burn is where the tool was, not mirrored (texture rows upside down or columns reversed)
    for mirror in ("mirror_u", "mirror_v"):
        assert white(image, mirror) < 0.05, f"{mirror} {spots[mirror]} turned white: the texture is mirrored on the mesh; see {tmp_path}"
    _check_loop(lab)


@needs_chromium
def test_a_browser_that_stops_drawing_keeps_its_tiles_until_it_has_drawn_their_successors(lab, page, tmp_path):
    """A page frozen in the DevTools debugger (no JavaScript, no frames) answers no sync requests: its replaced tile
    nodes are not removed while it is frozen, while the other page's go on being replaced and removed, and once it runs
    again it shows no hole (with a fixed removal delay it would get each new tile and the removal of the old one in one
    batch). The waits are the stream's own delay (a replaced node stays hide_after_s at least)."""
    lab.drive("circle", *STREAM_CENTRES["frozen"])
    frozen = _open(lab)
    stream = lab.stream

    def mine():
        return stream.client_stats(frozen.client_id)

    try:
        everything = stream.sync.mark()
        lab.run(until=lambda: stream.sync.confirmed_by(frozen.client_id) >= everything, what="the page confirming its tiles")

        def pause(_):
            cdp = frozen.context.new_cdp_session(frozen.page)
            paused = []
            cdp.on("Debugger.paused", lambda event: paused.append(event))
            cdp.send("Debugger.enable")
            cdp.send("Debugger.pause")
            deadline = time.monotonic() + WAIT_TIMEOUT_S
            while not paused and time.monotonic() < deadline:  # the page pauses at its next line of JavaScript
                frozen.page.wait_for_timeout(50)
            assert paused, "the page never paused in the debugger"
            return cdp

        cdp = lab.run(pause)
        paused_at, frozen_since = stream.sync.mark(), time.monotonic()
        other_removed_at_pause = stream.client_stats(page.client_id)["removed"]
        # Its nodes whose successors it had confirmed before the pause go within hide_after_s; those it had not
        # confirmed (sent shortly before the pause, or after it while it still had free node names) must stay.
        bound = WAIT_TIMEOUT_S if stream.max_hide_s is None else stream.max_hide_s - 8.0
        lab.run(until=lambda: time.monotonic() >= frozen_since + stream.hide_after_s + 1.0 and mine()["pending_removals"] > 0,
                timeout_s=bound, what="replaced tiles waiting on the frozen page")
        removed_before, pending_before, window_start = mine()["removed"], mine()["pending_removals"], time.monotonic()
        lab.run(until=lambda: time.monotonic() >= window_start + 3.0
                and stream.client_stats(page.client_id)["removed"] > other_removed_at_pause,
                timeout_s=bound, what="the other page's replaced tiles being removed while this one is frozen")
        removed_while_frozen = mine()["removed"] - removed_before
        if stream.max_hide_s is not None:
            assert time.monotonic() - frozen_since < stream.max_hide_s - 2.0, "the check took too long for the stream's bound"
        assert stream.sync.confirmed_by(frozen.client_id) < paused_at
        assert pending_before > 0, "nothing was replaced while the page was frozen"
        assert removed_while_frozen == 0, f"{removed_while_frozen} replaced nodes were removed while the page could not draw"
        lab.run(lambda _: cdp.send("Debugger.resume"))
        removed_at_resume = mine()["removed"]
        frames = lab.run(lambda _: frozen.record(min_seconds=5, min_frames=5, max_seconds=60), timeout_s=60 + WAIT_TIMEOUT_S)
        holes = np.array([_holes(frozen, image) for image in frames])
        for index in np.flatnonzero(holes > 20):
            browser.save(frames[index], tmp_path / f"hole_{index:02d}.png")
        assert (holes <= 20).all(), f"holes after the page ran again: {holes.tolist()}; see {tmp_path}"
        lab.run(until=lambda: mine()["removed"] > removed_at_resume, what="removals resuming")
        assert mine()["removed_unconfirmed"] == 0, "replaced nodes were removed without the page's confirmation"
    finally:
        lab.run(lambda _: frozen.close())
    _check_loop(lab)


@needs_chromium
def test_second_client_keeps_streaming_after_the_first_leaves(lab, page, tmp_path):
    lab.drive("circle", *STREAM_CENTRES["second"])
    second = _open(lab)
    try:
        lab.run(until=lambda: set(lab.server.get_clients()) == {page.client_id, second.client_id},
                what="two clients (the one frozen before gone)")
        lab.run(lambda _: page.close())  # the first client leaves mid-stream
        updates_before, sent_before = lab.stream.stats["updates"], lab.stream.client_stats(second.client_id)["tiles_sent"]
        frames = lab.run(lambda _: second.record(min_seconds=6, min_frames=6, max_seconds=60), timeout_s=60 + WAIT_TIMEOUT_S)
        assert len(frames) >= 4, f"the remaining client drew only {len(frames)} frames in 60 s"
        counts = [_tissue_count(image) for image in frames]
        holes = np.array([_holes(second, image) for image in frames])
        browser.save(frames[-1], tmp_path / "second_last.png")
        assert min(counts) > 0.8 * np.median(counts), f"tissue pixels dropped on the remaining client: {counts}"
        assert (holes <= 20).all(), f"holes in the mesh on the remaining client: {holes.tolist()}"
        changed = np.abs(frames[0].astype(int) - frames[-1]).max(axis=-1)
        assert (changed > 30).sum() > 20, "the remaining client stopped receiving texture updates"
        assert lab.stream.stats["updates"] > updates_before + 20, "the lab's loop stalled"
        assert lab.stream.client_stats(second.client_id)["tiles_sent"] > sent_before, "nothing was streamed to it"
        lab.run(until=lambda: set(lab.server.get_clients()) == {second.client_id}, what="the server forgetting the closed client")
    finally:
        lab.run(lambda _: second.close())
    _check_loop(lab)


# --- a TextureStream alone: material maps in the browser ------------------------------------------

SUN_POSITION_MM = (0.0, 40.0, 60.0)   # one directional light, from +y (the plane's +v) and above


def _material_plane():
    """A flat 40 x 40 mm plane in z = 0, u along +x and v along +y (so +v, "up" in the normal map, is +y)."""
    from types import SimpleNamespace

    from lab.reference.meshes import plane_mesh

    mesh = plane_mesh(40.0, 40.0, cells=16)
    return SimpleNamespace(vertices_mm=np.asarray(mesh.vertices, np.float32), faces=np.asarray(mesh.faces, np.int32),
                           uv=np.asarray(mesh.visual.uv, np.float32))


def _normal_map(direction, size: int) -> np.ndarray:
    """A uniform tangent-space normal map (x = +u, y = +v, z out) in glTF's encoding."""
    normal = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    return np.broadcast_to(np.rint(normal * 127.5 + 127.5).astype(np.uint8), (size, size, 3)).copy()


@needs_chromium
def test_the_normal_and_roughness_maps_of_the_tiles_reach_the_shader(chrome, tmp_path):
    """A plane under one light from +v and above: a normal map tilted toward +v (G above 128) turns it to the light
    and draws it brighter than a flat one, tilted toward -v darker; a low roughness where the plane mirrors the light
    into the camera draws a highlight that a high roughness does not; no page errors."""
    import viser

    from lab.web.stream import TextureStream, camera_for, set_initial_camera

    surface = _material_plane()
    server = viser.ViserServer(host="127.0.0.1", port=browser.free_port(), verbose=False)
    server.scene.set_background_image(np.full((4, 4, 3), BACKGROUND, np.uint8), format="png")
    server.scene.configure_environment_map(None)
    server.scene.configure_default_lights(enabled=False)
    server.scene.add_light_directional("/sun", color=(255, 255, 255), intensity=2.5, position=SUN_POSITION_MM)
    set_initial_camera(server, surface)
    stream = TextureStream(server, surface, tiles=2, hide_after_s=0.2)
    size = 64
    rgb = np.full((size, size, 3), 170, np.uint8)
    matte, glossy = np.full((size, size), 200, np.uint8), np.full((size, size), 25, np.uint8)
    # the normal that mirrors the light into a camera straight above: halfway between the two directions
    camera, look_at = camera_for(surface)
    halfway = np.asarray(SUN_POSITION_MM) / np.linalg.norm(SUN_POSITION_MM) + (camera - look_at) / np.linalg.norm(camera - look_at)
    viewer = None
    try:
        stream.update(rgb, normal=_normal_map((0, 0, 1), size), roughness=matte)
        viewer = chrome.submit(lambda instance: browser.Viewer(instance, f"http://127.0.0.1:{server.get_port()}/{PAGE_QUERY}",
                                                                viewport=VIEWPORT)).result(timeout=OPEN_TIMEOUT_S)
        deadline = time.monotonic() + OPEN_TIMEOUT_S
        while not server.get_clients():
            assert time.monotonic() < deadline, "the page did not connect"
            time.sleep(0.05)
        (client_id,) = server.get_clients()
        console = []  # the tiles reach the page from the next update on: every message about them is kept

        def listen(_):
            viewer.page.on("console", lambda message: console.append((message.type, message.text)))
            viewer.page.get_by_label("Minimize panel").first.click(timeout=OPEN_TIMEOUT_S * 1000)

        chrome.submit(listen).result()
        height, width = VIEWPORT["height"], VIEWPORT["width"]
        middle = (slice(int(height * 0.3), int(height * 0.7)), slice(int(width * 0.35), int(width * 0.65)))

        def shown(normal, roughness, name) -> np.ndarray:
            """The middle of the view once the page has drawn every tile with these maps and no older tile is left."""
            stream.update(rgb, normal=normal, roughness=roughness)
            mark, deadline = stream.sync.mark(), time.monotonic() + WAIT_TIMEOUT_S
            while stream.sync.confirmed_by(client_id) < mark or stream.pending_removals or stream.client_stats(client_id)["nodes"] < 4:
                assert time.monotonic() < deadline, f"the page did not draw the {name} tiles ({stream.client_stats(client_id)})"
                time.sleep(0.05)
                stream.update(rgb, normal=normal, roughness=roughness)
            image = chrome.submit(lambda _: viewer.screenshot()).result()
            browser.save(image, tmp_path / f"{name}.png")
            assert not (np.abs(image[middle].astype(int) - BACKGROUND).max(axis=-1) < 30).any(), f"the plane does not fill the middle; see {tmp_path}"
            return image[middle].astype(np.float64)

        flat = shown(_normal_map((0, 0, 1), size), matte, "flat")
        toward = shown(_normal_map((0, 0.5, 1), size), matte, "toward_light")
        away = shown(_normal_map((0, -0.5, 1), size), matte, "away_from_light")
        mirror_matte = shown(_normal_map(halfway, size), matte, "mirror_matte")
        mirror_glossy = shown(_normal_map(halfway, size), glossy, "mirror_glossy")
        errors = chrome.submit(lambda _: list(viewer.errors)).result()
    finally:
        if viewer is not None:
            chrome.submit(lambda _: viewer.close()).result()
        stream.close()
        server.stop()
    levels = {name: image.mean() for name, image in
              [("flat", flat), ("toward", toward), ("away", away), ("mirror_matte", mirror_matte), ("mirror_glossy", mirror_glossy)]}
    assert levels["toward"] > levels["flat"] + 4 and levels["flat"] > levels["away"] + 4, (levels, tmp_path)
    highlight = mirror_glossy.max(axis=-1) - mirror_matte.max(axis=-1)
    assert (highlight > 40).mean() > 0.01, (f"no highlight where the glossy plane mirrors the light ({levels}, "
                                            f"largest change {highlight.max():.0f}); see {tmp_path}")
    complaints = [text for kind, text in console if kind == "error" or "gltf" in text.lower()]
    assert not errors and not complaints, f"page errors: {errors[:3]}, console: {complaints[:3]}"
