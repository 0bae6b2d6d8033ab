"""What reaches the lab over viser's websocket from clients that behave as any web page can (testing.raw_client):
values are not checked by viser, a foreign web page is refused (lab.web.origin), a client may send only what the viser
client's widgets send (lab.web.client_guard), and a client that never answers or stops reading slows only itself
(lab.web.stream, lab.web.client_sync)."""
from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import msgspec.msgpack
import numpy as np
import pytest

from lab.reference.meshes import plane_mesh
from testing import browser
from testing.raw_client import RawClient, pipelined_connection


@pytest.fixture
def server():
    import viser

    instance = viser.ViserServer(host="127.0.0.1", port=browser.free_port(), verbose=False)
    yield instance
    instance.stop()


def _wait(predicate, timeout_s: float = 30.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"{what or 'the condition'} not met in {timeout_s} s"
        time.sleep(0.02)


def _connect(server, **kwargs) -> tuple[RawClient, int]:
    """A raw client and its id on the server, once viser counts it as connected."""
    before = set(server.get_clients())
    client = RawClient(server.get_port(), **kwargs)
    _wait(lambda: set(server.get_clients()) - before, what="the client connecting")
    return client, (set(server.get_clients()) - before).pop()


class _Inputs:
    """A dropdown, a float slider, a button, transform controls and a scene click callback; keeps every value that
    reaches a callback, with the id of the client it came from."""

    def __init__(self, server):
        self.seen: list[tuple] = []
        self._lock = threading.Lock()
        dropdown = server.gui.add_dropdown("Scene", options=("liver", "kidney"))
        dropdown.on_update(lambda event: self._keep("dropdown", event.client_id, event.target.value))
        slider = server.gui.add_slider("Rate", min=0.0, max=1.0, step=0.01, initial_value=0.5)
        slider.on_update(lambda event: self._keep("slider", event.client_id, event.target.value))
        server.gui.add_button("Reset").on_click(lambda event: self._keep("button", event.client_id, True))
        gizmo = server.scene.add_transform_controls("/tool")
        gizmo.on_update(lambda event: self._keep("gizmo", event.client_id, tuple(event.target.wxyz) + tuple(event.target.position)))
        server.scene.on_click()(lambda event: self._keep("click", event.client_id, tuple(event.ray_origin) + tuple(event.ray_direction)))

    def _keep(self, *entry) -> None:
        with self._lock:
            self.seen.append(entry)

    def values(self, kind: str, client_id: int | None = None) -> list:
        with self._lock:
            return [value for k, c, value in self.seen if k == kind and client_id in (None, c)]


def _same(a, b) -> bool:
    """Equal, NaN equal to NaN, element by element for tuples."""
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return a == b


def test_viser_hands_whatever_a_client_sends_to_the_callbacks(server):
    """Documents what the lab's callbacks must check themselves: viser passes on a dropdown value outside its options,
    NaN and out-of-range slider values, and NaN or infinite poses and rays, exactly as sent."""
    inputs = _Inputs(server)
    client, client_id = _connect(server)
    nan, inf = float("nan"), float("inf")
    assert client.wait_for_gui("Scene")["props"]["options"] == ["liver", "kidney"]
    assert client.wait_for_gui("Rate")["props"]["max"] == 1.0
    client.set_gui_value("Scene", "../../etc/passwd")
    client.set_gui_value("Rate", nan)
    # callbacks read the handle's value when they run (in viser's thread pool): one value at a time
    _wait(lambda: inputs.values("slider", client_id), what="the NaN reaching the slider's callback")
    client.set_gui_value("Rate", 1e9)
    client.click_button("Reset")
    client.move_transform("/tool", (nan, 0.0, 0.0, 0.0), (1.0, -inf, 2.0))
    client.click_scene((0.0, 0.0, nan), (0.0, 0.0, -1.0))
    expected = {"dropdown": ["../../etc/passwd"], "slider": [nan, 1e9], "button": [True],
                "click": [(0.0, 0.0, nan, 0.0, 0.0, -1.0)]}
    pose = (nan, 0.0, 0.0, 0.0, 1.0, -inf, 2.0)  # wxyz, position

    def arrived():
        return all(len(inputs.values(kind, client_id)) >= len(values) for kind, values in expected.items()) \
            and any(_same(value, pose) for value in inputs.values("gizmo", client_id))

    _wait(arrived, what="every value reaching its callback")
    for kind, values in expected.items():
        assert _same(tuple(inputs.values(kind, client_id)), tuple(values)), (kind, inputs.values(kind, client_id))
    client.close()


def test_a_foreign_origin_is_disconnected_before_it_learns_or_changes_anything(server):
    from lab.web.origin import refuse_foreign_origins

    guard = refuse_foreign_origins(server)
    port = server.get_port()
    assert guard.allows(f"http://localhost:{port}") and guard.allows(f"http://127.0.0.1:{port}/") and guard.allows(None)
    assert not guard.allows(f"http://localhost:{port + 1}") and not guard.allows("null")
    assert not guard.allows(f"http://127.0.0.1.evil.example:{port}")
    inputs = _Inputs(server)
    own, own_id = _connect(server, origin=f"http://127.0.0.1:{port}")
    uuid = own.wait_for_gui("Rate")["uuid"]
    camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 1.0], "fov": 0.9,
              "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 960, "look_at": [0.0, 0.0, 0.0],
              "up_direction": [0.0, 0.0, 1.0]}
    # the fastest a page can be: its messages in the same TCP write as the upgrade request
    attack = pipelined_connection(port, "http://evil.example", [camera] + [
        {"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": 0.25 + 0.001 * i}} for i in range(20)])
    assert attack == {"status": 101, "close_code": 1008, "frames": 0}, "the scene or GUI went to a foreign page"
    evil = RawClient(port, origin="http://evil.example")
    _wait(lambda: not evil.connected, what="the foreign client being disconnected")
    assert evil.close_code == 1008 and not evil.counts and not evil.send_gui_update(uuid, 0.75)
    own.set_gui_value("Rate", 0.125)
    script, script_id = _connect(server)  # no Origin: not a web page
    script.set_gui_value("Rate", 0.375)
    _wait(lambda: inputs.values("slider") == [0.125, 0.375], what="the own page's and the script's values arriving")
    assert inputs.values("slider", own_id) == [0.125] and set(server.get_clients()) == {own_id, script_id}
    assert guard.refused == 2 and guard.last_refused == "http://evil.example"
    own.close()
    script.close()


@pytest.mark.skipif(not browser.have_chromium(), reason=f"needs the Debian chromium package at {browser.CHROMIUM}")
def test_a_real_page_from_the_server_itself_still_connects(server):
    from playwright.sync_api import sync_playwright

    from lab.web.origin import refuse_foreign_origins

    guard = refuse_foreign_origins(server)
    with sync_playwright() as playwright:
        chromium = browser.launch(playwright)
        try:
            page = chromium.new_page()
            page.goto(f"http://127.0.0.1:{server.get_port()}/", wait_until="domcontentloaded")
            _wait(lambda: server.get_clients(), timeout_s=120, what="the page connecting")
        finally:
            chromium.close()
    assert guard.refused == 0


# --- a silent or stalled client and the texture stream --------------------------------------

TILES, POOL, HIDE_S, RATE = 4, 16, 0.5, 16.0   # 16 tiles, 16 spare node names per browser, 16 tile versions/s
UPDATES, PERIOD_S = 40, 0.05                     # every update changes every tile


def _patch():
    """A bumpy 60 x 40 mm patch with UVs over [0, 1]^2, as TextureStream wants it."""
    mesh = plane_mesh(60.0, 40.0, cells=16)
    vertices = np.asarray(mesh.vertices, np.float64).copy()
    vertices[:, 2] = 3.0 * np.sin(vertices[:, 0] / 7.0) * np.cos(vertices[:, 1] / 5.0)
    return SimpleNamespace(vertices_mm=vertices.astype(np.float32), faces=np.asarray(mesh.faces, np.int32),
                           uv=np.asarray(mesh.visual.uv, np.float32))


def _stream_run(server, other: str | None) -> dict:
    """Tiles a normal client receives over UPDATES updates while `other` ("silent": reads, never answers the sync
    requests; "stalled": stops reading after its first tiles; None: no one) is connected too."""
    from lab.web.stream import TextureStream

    normal, normal_id = _connect(server)
    extra, extra_id = _connect(server, answer_requests=other != "silent", max_queue=4) if other else (None, None)
    stream = TextureStream(server, _patch(), tiles=TILES, hide_after_s=HIDE_S, max_pool=POOL, max_tiles_per_s=RATE)
    try:
        image = np.zeros((64, 64, 3), np.uint8)
        stream.update(image)
        for client in (normal, extra) if extra else (normal,):
            client.wait_for(lambda c=client: len(c.glbs) >= TILES * TILES)
        if other == "stalled":
            extra.stall()
        received_before, published_before, start = len(normal.glbs), stream.stats["tiles_sent"], time.monotonic()
        for index in range(1, UPDATES + 1):
            image[:] = (index * 16) % 256
            stream.update(image)
            time.sleep(max(0.0, start + index * PERIOD_S - time.monotonic()))
        queued = stream.client_stats(normal_id)["tiles_sent"]
        normal.wait_for(lambda: len(normal.glbs) >= queued, timeout_s=10)
        return {"received": len(normal.glbs) - received_before, "published": stream.stats["tiles_sent"] - published_before,
                "other": stream.client_stats(extra_id) if extra else None}
    finally:
        stream.close()
        for client in (normal, extra):
            if client is not None:
                client.close()
        _wait(lambda: not server.get_clients(), what="the clients leaving")


def test_a_client_that_never_answers_or_stops_reading_slows_only_itself(server):
    """With one stream for every browser, a node could be removed only once every browser had confirmed its
    successor: a silent client held each removal for 15 s and dried up the shared node pool (the normal client got
    about a fifth of its rate). Now each browser has its own nodes and confirmations."""
    alone = _stream_run(server, None)
    assert alone["received"] >= 0.8 * alone["published"] > 0, alone
    for other in ("silent", "stalled"):
        run = _stream_run(server, other)
        assert run["received"] >= 0.8 * alone["received"], (other, run, alone)
        # what the server queued for the other client is bounded by its nodes: its tiles and its spare names
        assert run["other"]["tiles_sent"] <= TILES * TILES + POOL and run["other"]["removed"] == 0, (other, run)


def test_a_new_client_gets_every_tile_and_one_that_leaves_takes_its_nodes(server):
    from lab.web.stream import TextureStream

    first, first_id = _connect(server)
    stream = TextureStream(server, _patch(), tiles=TILES, hide_after_s=600.0)  # replaced nodes stay for the test
    try:
        image = np.full((64, 64, 3), 100, np.uint8)
        stream.update(image)
        image[40:44, 10:14] = 200
        # one tile replaced for the first client: it goes once that client has applied the tile's first node
        _wait(lambda: stream.update(image) is not None and len(first.glbs) == TILES * TILES + 1, what="the replacement tile")
        second, second_id = _connect(server)
        stream.update(image)
        second.wait_for(lambda: len(second.glbs) >= TILES * TILES)
        assert len(second.glbs) == TILES * TILES and stream.client_stats(second_id)["nodes"] == TILES * TILES
        assert stream.node_count == 2 * TILES * TILES + 1  # the first client's replaced node is still there
        second.close()
        _wait(lambda: second_id not in server.get_clients(), what="the second client leaving")
        stream.update(image)
        assert stream.node_count == TILES * TILES + 1 and stream.client_stats(second_id)["nodes"] == 0
        assert first.wait_for(lambda: len(first.glbs) == TILES * TILES + 1)
    finally:
        stream.close()
        first.close()


# --- what a client may send: only what the viser client's widgets send (lab.web.client_guard) ------------------------

def _messages_guard(server):
    """The lab.web.client_guard.ClientGuard of this server (lab.web.origin installs it)."""
    from lab.web import client_guard

    return next(guard for guard in list(client_guard._GUARDS) if guard.port == server.get_port())


def test_malformed_frames_close_their_connection_quietly_and_are_counted(server, caplog):
    """Each used to end in a traceback of 11 lines or more (viser's handler raised, websockets logged it), without
    limit; a type the client sends but the lab does not use is dropped and the connection kept."""
    import socket

    from lab.web.origin import refuse_foreign_origins

    guard = refuse_foreign_origins(server).messages
    frames = [b"\xc1", "a text frame", b"\x91" * 100_000 + b"\xc0", msgspec.msgpack.encode({"type": "NoSuchMessage"}),
              msgspec.msgpack.encode({"type": "GuiRemoveMessage", "uuid": "x"}), msgspec.msgpack.encode({"uuid": "no type"})]
    for frame in frames:
        client = RawClient(server.get_port(), send_camera=False)
        client.send_frame(frame)
        _wait(lambda: not client.connected, what=f"the connection closing after {frame[:20]!r}")
        assert client.close_code == 1003
    for data in (b"", b"GARBAGE\r\n\r\n"):  # a bare TCP connect and close; then a request that is not HTTP
        with socket.create_connection(("127.0.0.1", server.get_port())) as sock:
            sock.sendall(data)
    kept, _ = _connect(server)
    kept.send({"type": "ShareUrlRequest"})  # would have the server open a public share tunnel to the lab
    kept.send({"type": "GuiButtonHoldMessage", "uuid": "x", "frequency": 1.0})
    _wait(lambda: guard.dropped["failed handshake"] >= 2 and guard.dropped["GuiButtonHoldMessage"] == 1,
          what="the refused handshakes and messages being counted")
    assert guard.dropped["malformed"] == len(frames) and guard.dropped["ShareUrlRequest"] == 1 and kept.connected
    assert not [record.getMessage() for record in caplog.records if record.exc_info], "a traceback was logged"
    kept.close()


def test_the_page_forbids_framing_by_other_sites(server):
    import urllib.request

    from lab.web.origin import refuse_foreign_origins

    refuse_foreign_origins(server)
    with urllib.request.urlopen(f"http://127.0.0.1:{server.get_port()}/") as response:
        assert response.status == 200 and response.headers["X-Frame-Options"] == "SAMEORIGIN"
        assert response.headers["Content-Security-Policy"] == "frame-ancestors 'self'"


@pytest.fixture(scope="module")
def lab():
    """A LabApp on the hemostasis scene at 128² texels; its loop runs on this thread only inside `_run`."""
    from lab.web.app import LabApp
    from sims.scene.config import REPO_ROOT

    app = LabApp(REPO_ROOT / "scenes" / "hemostasis.yaml", "127.0.0.1", browser.free_port(), "cpu", overrides=("texture_size=128",))
    yield app
    app.close()


def _run(lab, until, what: str, timeout_s: float = 90.0) -> None:
    """The lab's simulation loop on this thread until until() holds."""
    assert lab.run(until=until, timeout_s=timeout_s), f"{what} did not happen in {timeout_s} s (notice: {lab.session.notice!r})"


def _steps_on(lab, what: str) -> None:
    start = lab.scene.steps
    _run(lab, lambda: lab.scene.steps >= start + 10, what)
    assert not lab.session.notice.startswith("simulation stopped"), lab.session.notice


def test_a_client_writing_handle_internals_breaks_nothing_for_the_others(lab):
    """viser assigned every key of a GUI update to the server's handle: {gui_api: 0} on "Simple lighting" then a
    rebuild ended the process; {gui_api: 0} on a slider stopped the simulation for everyone at the next reset to
    defaults; {update_cb: []} disabled Reset and {sync_cb: 0} broke Speed for every browser."""
    port = lab.server.get_port()
    hostile, other = RawClient(port, strict=True), RawClient(port, strict=True)
    guard = _messages_guard(lab.server)
    conductivity = "conductivity_w_mk (W/(m K))"
    _run(lab, lambda: len(lab.server.get_clients()) >= 2 and conductivity in hostile.gui and conductivity in other.gui,
         "both clients connecting")
    default = lab.session.parameter_value("tissue.conductivity_w_mk")
    other.set_gui_value(conductivity, 1.5)
    _run(lab, lambda: lab.session.parameter_value("tissue.conductivity_w_mk") == 1.5, "the other's conductivity arriving")
    before = sum(guard.dropped.values())
    for label, updates in (("Simple lighting", {"gui_api": 0}), (conductivity, {"gui_api": 0}), ("Reset", {"update_cb": []}),
                           ("Speed (x real time)", {"sync_cb": 0}), ("Speed (x real time)", {"value": 2.0, "sync_cb": 0})):
        hostile.send({"type": "GuiUpdateMessage", "uuid": hostile.wait_for_gui(label)["uuid"], "updates": updates})
    _run(lab, lambda: sum(guard.dropped.values()) >= before + 5, "the five updates being dropped")
    assert lab.session.speed == 1.0
    other.click_button("Reset tissue to defaults")
    _run(lab, lambda: lab.session.parameter_value("tissue.conductivity_w_mk") == default, "the reset to defaults")
    _steps_on(lab, "stepping after the reset to defaults")
    lab.session.notice = ""
    time_s = lab.scene.time_s
    other.click_button("Reset")
    _run(lab, lambda: lab.scene.time_s < time_s, "the other's Reset")
    other.set_gui_value("Speed (x real time)", 2.0)
    hostile.wait_for(lambda: hostile.gui["Speed (x real time)"]["props"].get("value") == 2.0)  # relayed to the others
    assert lab.session.speed == 2.0
    builds = lab.session.builds
    other.set_gui_value("Quality", "fast")
    _run(lab, lambda: lab.session.builds > builds and lab.shown_builds == lab.session.builds, "the rebuild", timeout_s=180)
    _steps_on(lab, "stepping after the rebuild")
    hostile.close()
    other.close()


def test_a_refused_gizmo_pose_reaches_no_other_browser_and_goes_back_everywhere(lab):
    """viser relayed a client's gizmo pose to the other browsers before the lab looked at it; a bleed-point marker
    was not put back either: after position (NaN, 0, 0) on /bleed/vessel it vanished in the other browsers while the
    vessel kept bleeding."""
    port = lab.server.get_port()
    hostile, other = RawClient(port, strict=True), RawClient(port, strict=True)
    _run(lab, lambda: len(lab.server.get_clients()) >= 2 and "/bleed/vessel" in hostile.nodes and "/bleed/vessel" in other.nodes,
         "both clients seeing the marker")
    guard = _messages_guard(lab.server)
    where = tuple(float(v) for v in lab.scene.bleed_point("vessel").position_at(lab.scene.time_s))
    refused = [("/bleed/vessel", (1.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0)), ("/bleed/vessel", (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1e308)),
               ("/bleed/vessel", (1.0, 0.0, 0.0, 0.0), (900.0, 0.0, 0.0)),  # finite, but far outside the tissue: the lab refuses it
               ("/tools/ball_electrode", (1.0, 0.0, 0.0, 0.0), (-math.inf, 0.0, 0.0))]
    for name, wxyz, position in refused:
        seen = len(hostile.positions[name])
        lab.session.notice = ""
        hostile.move_transform(name, wxyz, position)
        _run(lab, lambda: "refused" in lab.session.notice and len(hostile.positions[name]) > seen, f"{position} put back")
        back = hostile.positions[name][-1]
        assert all(map(math.isfinite, back)), back
        other.wait_for(lambda: other.positions[name] and other.positions[name][-1] == back)
    assert other.positions["/bleed/vessel"][-1] == hostile.positions["/bleed/vessel"][-1] == pytest.approx(where)
    assert all(all(map(math.isfinite, position)) and max(map(abs, position)) < 1e6
               for positions in other.positions.values() for position in positions), "a refused pose was relayed"
    assert guard.dropped["pose not relayed"] >= 3
    hostile.close()
    other.close()
