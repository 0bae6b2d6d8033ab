"""The browser front end in real headless Chromium: the real lab (lab.app.LabApp) streaming the tissue texture
(lab.stream.TextureStream); below them, tests of the stream's bookkeeping and its GLBs without a browser.

For the browser tests, one LabApp for the module on a test scene (the liver patch at 256^2 texels with one ball
electrode that has no scripted path), with a flat blue background, so that a hole in the mesh (a tile missing from a
drawn frame) is unambiguous in a screenshot, and simple lighting (software WebGL draws several times faster without the
environment map and shadows). The tool's model and gizmo are hidden, so that they cover no burn. The electrode is driven
through the session's public commands (take_over, set_energized, release), as a browser's gizmo and checkbox do.
The lab's simulation loop runs on this (main) thread (Taichi), and only while a test waits in `Lab.run`; Chromium runs
on a thread of its own (tests.browser.BrowserThread), where every Playwright call is made. Every wait is a condition
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

from tests import browser

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

        from lab.app import LabApp

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
def chromium():
    thread = browser.BrowserThread()
    yield thread
    thread.close()


@pytest.fixture(scope="module")
def lab(tmp_path_factory, chromium):
    scene_file = tmp_path_factory.mktemp("browser") / "scene.yaml"
    scene_file.write_text(SCENE_YAML)
    lab = Lab(scene_file, chromium)
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


# --- the stream without a browser -------------------------------------------------------------

def _bumpy_patch(cells: int = 24):
    """A 60 x 40 mm patch with bumps (normals vary), UVs over [0, 1]^2, as TextureStream wants it."""
    from types import SimpleNamespace

    from tests.helpers import plane_mesh

    mesh = plane_mesh(60.0, 40.0, cells=cells)
    vertices = np.asarray(mesh.vertices, np.float64).copy()
    vertices[:, 2] = 3.0 * np.sin(vertices[:, 0] / 7.0) * np.cos(vertices[:, 1] / 5.0)
    return SimpleNamespace(vertices_mm=vertices.astype(np.float32), faces=np.asarray(mesh.faces, np.int32),
                           uv=np.asarray(mesh.visual.uv, np.float32))


class _Recorder:
    """Wraps the add_glb of the connected clients' scenes (the stream sends each browser its own tile nodes) to keep
    what the stream sends."""

    def __init__(self, server):
        self.sent = []
        for client in server.get_clients().values():
            original = client.scene.add_glb

            def add_glb(name, glb_data, _original=original, **kwargs):
                self.sent.append((name, glb_data))
                return _original(name, glb_data, **kwargs)

            client.scene.add_glb = add_glb


@pytest.fixture
def server():
    """A viser server with one connected client (a raw websocket client that answers as a browser does)."""
    import viser

    from tests.raw_client import RawClient

    instance = viser.ViserServer(host="127.0.0.1", port=browser.free_port(), verbose=False)
    client = RawClient(instance.get_port())
    deadline = time.monotonic() + 30
    while not instance.get_clients() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert instance.get_clients(), "the raw client did not connect"
    yield instance
    client.close()
    instance.stop()


def _applied(server, stream, timeout_s: float = 10.0) -> None:
    """Wait until every client has applied every tile node queued to it so far (a tile is replaced for a client only
    once it has applied the tile's current node)."""
    mark, deadline = stream.sync.mark(), time.monotonic() + timeout_s
    while not all(stream.sync.positions(client_id)[0] >= mark for client_id in server.get_clients()):
        assert time.monotonic() < deadline, "the client did not apply its tiles"
        time.sleep(0.02)


def _glb_parts(glb: bytes):
    import json
    import struct

    magic, version, total = struct.unpack_from("<4sII", glb, 0)
    assert magic == b"glTF" and version == 2 and total == len(glb)
    json_length, _ = struct.unpack_from("<I4s", glb, 12)
    document = json.loads(glb[20:20 + json_length])
    binary_length, kind = struct.unpack_from("<I4s", glb, 20 + json_length)
    assert kind == b"BIN\x00"
    return document, glb[28 + json_length:28 + json_length + binary_length]


def _accessor(document, binary, index):
    formats = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
    sizes = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    data = np.frombuffer(binary, formats[accessor["componentType"]], accessor["count"] * sizes[accessor["type"]], view["byteOffset"])
    return data.reshape(accessor["count"], sizes[accessor["type"]])


def test_stream_sends_only_changed_tiles_and_removes_replaced_nodes_later(server):
    from lab.stream import TextureStream

    recorder = _Recorder(server)
    stream = TextureStream(server, _bumpy_patch(), tiles=4, hide_after_s=0.3)
    image = np.full((64, 64, 3), 120, np.uint8)
    first = stream.update(image)
    assert first["tiles_sent"] == 16 and first["bytes"] == sum(len(glb) for _, glb in recorder.sent)
    assert stream.update(image)["tiles_sent"] == 0
    _applied(server, stream)
    image[40:44, 10:14] = 255  # inside one tile, far from its borders
    assert stream.update(image)["tiles_sent"] == 1
    assert stream.node_count == 17  # the replaced node stays under the new one for now
    time.sleep(0.35)
    deadline = time.monotonic() + 10  # and goes once the client confirmed its successor (a few 0.2 s round trips)
    while stream.node_count > 16 and time.monotonic() < deadline:
        time.sleep(0.05)
        stream.update(image)
    assert stream.node_count == 16
    image[40:44, 10:14] = 0
    stream.update(image)
    assert len(recorder.sent) == 18 and len({name for name, _ in recorder.sent}) == 17, "the removed node's name is used again"
    stream.close()
    assert stream.update(image)["tiles_sent"] == 0


def test_stream_rate_limit_defers_changed_tiles_and_sends_their_newest_crop(server):
    import io

    from PIL import Image

    from lab.stream import TextureStream

    recorder = _Recorder(server)
    stream = TextureStream(server, _bumpy_patch(), tiles=4, max_tiles_per_s=10.0)
    image = np.zeros((64, 64, 3), np.uint8)
    stream.update(image)  # the first texture goes whole, whatever the limit
    _applied(server, stream)
    sent, deferred, started = 0, 0, time.monotonic()
    for value in range(1, 30):
        image[:] = value  # every tile changes on every update
        result = stream.update(image)
        sent += result["tiles_sent"]
        deferred += result["tiles_deferred"]
        time.sleep(0.02)
    assert deferred > 0 and sent <= 10.0 * (time.monotonic() - started) + 6  # the rate, plus half a second's burst
    newest = {}

    def every_tile_newest():
        newest.clear()
        for name, glb in recorder.sent[16:]:
            document, binary = _glb_parts(glb)
            view = document["bufferViews"][document["images"][0]["bufferView"]]
            crop = np.asarray(Image.open(io.BytesIO(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]])))
            newest[document["accessors"][0]["min"][0], document["accessors"][0]["min"][1]] = crop
        return len(newest) == 16 and all((crop == 29).all() for crop in newest.values())

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # nothing changes any more: the deferred tiles catch up
        stream.update(image)
        if every_tile_newest():
            break
        time.sleep(0.1)
    assert every_tile_newest(), "every tile ends with the newest texture"
    stream.close()


def _sent_image(glb: bytes) -> np.ndarray:
    import io

    from PIL import Image

    document, binary = _glb_parts(glb)
    view = document["bufferViews"][document["images"][0]["bufferView"]]
    return np.asarray(Image.open(io.BytesIO(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]])))


def test_stream_sends_the_largest_change_first_and_lets_faint_changes_settle(server):
    """With one tile's budget: a fresh burn goes before a tile that changed less; a one-level change (tissue cooling)
    waits settle_s and then goes too."""
    from lab.stream import TextureStream

    recorder = _Recorder(server)
    stream = TextureStream(server, _bumpy_patch(), tiles=4, max_tiles_per_s=2.0, settle_s=1.0)  # one token per 0.5 s
    image = np.full((64, 64, 3), 120, np.uint8)
    stream.update(image)
    _applied(server, stream)
    image[3:13, 3:13] = 130     # inside the top-left tile only (crops overlap by 2 texels): a change of 10 levels
    image[40:44, 40:44] = 250   # a fresh burn inside another tile
    first = stream.update(image)
    assert first["tiles_sent"] == 1 and first["tiles_deferred"] == 1
    assert (_sent_image(recorder.sent[-1][1]) == 250).any(), "the burn should go first"
    time.sleep(0.6)
    assert stream.update(image)["tiles_sent"] == 1 and (_sent_image(recorder.sent[-1][1]) == 130).any()
    time.sleep(0.6)
    image[20:28, 20:28] = 140   # a third tile changes and goes...
    assert stream.update(image)["tiles_sent"] == 1
    sent_at = time.monotonic()
    image[20:28, 20:28] = 141   # ...and right after, by one level more
    _applied(server, stream)
    time.sleep(max(0.0, sent_at + 0.6 - time.monotonic()))  # a token is back, settle_s (since the tile's last send) not over yet
    assert stream.update(image) == {"tiles_sent": 0, "bytes": 0, "tiles_deferred": 1}, "a faint change waits to settle"
    time.sleep(0.5)
    assert stream.update(image)["tiles_sent"] == 1 and (_sent_image(recorder.sent[-1][1]) == 141).any()
    assert stream.update(image)["tiles_deferred"] == 0
    stream.close()


def test_tile_glbs_cover_the_mesh_and_map_the_texture_the_right_way_up(server):
    import io

    from PIL import Image

    from lab.stream import TextureStream

    recorder = _Recorder(server)
    surface = _bumpy_patch()
    stream = TextureStream(server, surface, tiles=4)
    height, width = 96, 128
    rows, cols = np.mgrid[0:height, 0:width]
    image = np.stack([cols * 2, rows * 2, np.full_like(rows, 60)], axis=-1).astype(np.uint8)  # smooth: neighbours differ by 2
    stream.update(image)
    visible_faces = 0
    for _, glb in recorder.sent:
        document, binary = _glb_parts(glb)
        primitive = document["meshes"][0]["primitives"][0]
        positions = _accessor(document, binary, primitive["attributes"]["POSITION"])
        st = _accessor(document, binary, primitive["attributes"]["TEXCOORD_0"])
        faces = _accessor(document, binary, primitive["indices"]).reshape(-1, 3)
        view = document["bufferViews"][document["images"][0]["bufferView"]]
        crop = np.asarray(Image.open(io.BytesIO(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]])).convert("RGB"))
        assert document["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] == 0.0
        # every real vertex: the crop texel under its glTF UV (origin top left) is the image texel under its OBJ UV
        for position, uv_tile in zip(positions[:40], st[:40]):
            match = np.flatnonzero(np.abs(surface.vertices_mm - position).max(axis=1) < 1e-5)
            if len(match) == 0:
                continue  # a normal ghost corner
            u, v = surface.uv[match[0]]
            expected = image[min(int((1.0 - v) * height), height - 1), min(int(u * width), width - 1)]
            got = crop[min(int(uv_tile[1] * crop.shape[0]), crop.shape[0] - 1), min(int(uv_tile[0] * crop.shape[1]), crop.shape[1] - 1)]
            assert np.abs(got.astype(int) - expected).max() <= 2, (u, v, got, expected)
        ghosts = sum(document["accessors"][t["POSITION"]]["sparse"]["count"] // 2 for t in primitive.get("targets", []))
        visible_faces += len(faces) - ghosts
    assert visible_faces == len(surface.faces)
    stream.close()


def test_browser_recomputed_tile_normals_equal_the_welded_whole_mesh_normals(server):
    """What the viser client does (per tile: three.js computeVertexNormals, then the morph target) gives the normals
    of the whole mesh welded at seams: no shading steps at tile borders."""
    from lab.stream import TextureStream

    recorder = _Recorder(server)
    surface = _bumpy_patch()
    # split the vertices on x = 0 into two copies, as at a UV seam: the normals must still be welded there
    vertices, faces = surface.vertices_mm, surface.faces.copy()
    on_seam = np.flatnonzero(np.abs(vertices[:, 0]) < 1e-4)
    copies = len(vertices) + np.arange(len(on_seam))
    right = vertices[faces].mean(axis=1)[:, 0] > 0
    remap = np.arange(len(vertices) + len(on_seam))
    remap[on_seam] = copies
    faces[right] = remap[faces[right]]
    surface.vertices_mm = np.concatenate([vertices, vertices[on_seam]])
    surface.uv = np.concatenate([surface.uv, surface.uv[on_seam]])
    surface.faces = faces
    stream = TextureStream(server, surface, tiles=4)
    stream.update(np.zeros((64, 64, 3), np.uint8))
    welded = {}
    vertices = surface.vertices_mm.astype(np.float64)
    tri = vertices[surface.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    for corner in range(3):
        for face, vertex in enumerate(surface.faces[:, corner]):
            key = tuple(np.round(vertices[vertex], 4))
            welded[key] = welded.get(key, 0) + cross[face]
    worst, plain_worst = 0.0, 0.0
    for _, glb in recorder.sent:
        document, binary = _glb_parts(glb)
        primitive = document["meshes"][0]["primitives"][0]
        positions = _accessor(document, binary, primitive["attributes"]["POSITION"]).astype(np.float64)
        faces = _accessor(document, binary, primitive["indices"]).reshape(-1, 3).astype(np.int64)
        sparse = document["accessors"][primitive["targets"][0]["POSITION"]]["sparse"]
        ids = np.frombuffer(binary, np.uint16, sparse["count"], document["bufferViews"][sparse["indices"]["bufferView"]]["byteOffset"])
        deltas = np.frombuffer(binary, np.float32, 3 * sparse["count"], document["bufferViews"][sparse["values"]["bufferView"]]["byteOffset"]).reshape(-1, 3)
        tri = positions[faces]
        face_cross = np.cross(tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 1])  # three.js: (c - b) x (a - b)
        sums = np.zeros_like(positions)
        for corner in range(3):
            np.add.at(sums, faces[:, corner], face_cross)
        real = np.setdiff1d(np.arange(len(positions)), ids)
        drawn = positions.copy()
        drawn[ids] += deltas
        ghost_faces = np.isin(faces, ids).any(axis=1)
        assert np.allclose(drawn[faces[ghost_faces]][:, 1:], drawn[faces[ghost_faces]][:, :1], atol=1e-4), "ghosts are drawn with zero area"
        plain = np.zeros_like(positions)
        for corner in range(3):
            np.add.at(plain, faces[~ghost_faces][:, corner], face_cross[~ghost_faces])
        for index in real:
            expected = welded[tuple(np.round(positions[index], 4))]
            expected = expected / np.linalg.norm(expected)
            got = sums[index] / np.linalg.norm(sums[index])
            worst = max(worst, np.degrees(np.arccos(np.clip(got @ expected, -1, 1))))
            without = plain[index] / np.linalg.norm(plain[index])
            plain_worst = max(plain_worst, np.degrees(np.arccos(np.clip(without @ expected, -1, 1))))
    assert plain_worst > 2.0, "the test patch should need the fix"
    assert worst < 0.05, f"tile normals differ from the whole mesh's by {worst:.3f} degrees"
    stream.close()
