"""The browser lab's start: a page that connects while a scene builds (the first build, a rebuild, a switch) sees the
"Building the scene" notice, then the scene, and the server lives on; the scripted clock starts only once a browser
has drawn the whole tissue texture. Browsers are raw websockets (testing/raw_client.py) that record notifications."""
import time

from sims.scene.config import REPO_ROOT
from testing import browser
from testing.raw_client import RawClient

SCENE = REPO_ROOT / "scenes" / "default.yaml"


class Watcher(RawClient):
    """A raw client that keeps the titles of the notifications it was shown."""

    def __init__(self, *args, **kwargs):
        self.titles: list[str] = []
        super().__init__(*args, **kwargs)

    def _handle(self, message: dict) -> None:
        if message.get("type") == "NotificationShowMessage":
            self.titles.append(message["props"]["title"])
        super()._handle(message)


def wait(condition, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the condition did not hold in time"
        time.sleep(0.02)


def test_pages_that_connect_during_builds_see_the_notice_then_the_scene_and_the_clock_waits_for_a_drawn_texture():
    from lab.web.app import LabApp

    joined: list[Watcher] = []

    class App(LabApp):
        def _on_build(self, stage, name, seconds, notes=()):
            super()._on_build(stage, name, seconds, notes)
            if stage == "start":  # a page connects mid-build, as one that reconnects after a restart
                page = Watcher(self.server.get_port(), answer_requests=len(joined) > 0)  # the first never confirms
                joined.append(page)
                wait(lambda: "Building the scene" in page.titles)

    app = App(SCENE, "127.0.0.1", browser.free_port(), "cpu", overrides=("texture_size=128",), wait_for_viewer=True)
    try:
        first = joined[0]
        wait(lambda: "Scene ready" in first.titles)
        assert first.titles.index("Building the scene") < first.titles.index("Scene ready")
        tiles = app.stream.tiles ** 2
        # a page that got every tile but never confirmed drawing them does not start the clock
        assert app.run(until=lambda: len({name for _, name, _ in first.glbs}) >= tiles, timeout_s=90)
        assert app.run(until=lambda: first.requests_seen > 0, timeout_s=30)
        assert app.session.waiting_for_viewer and app.scene.steps == 0 and not app.stream.drawn_whole()
        released = []  # (every tile drawn, scene time) when the lab starts the clock (the loop steps right after, so
        joined_now = app.session.viewer_joined  # the state is taken at the call, not some loop passes later)
        app.session.viewer_joined = lambda: (released.append((app.stream.drawn_whole(), app.scene.time_s)), joined_now())
        second = Watcher(app.server.get_port())  # it answers: once it has drawn every tile the drill starts
        assert app.run(until=lambda: not app.session.waiting_for_viewer, timeout_s=90)
        assert released == [(True, 0.0)]
        start = app.scene.steps
        assert app.run(until=lambda: app.scene.steps > start + 5, timeout_s=60)

        for change in (lambda: app.session.set_quality("fast"), lambda: app.session.switch_scene("scenes/default.yaml")):
            builds, pages = app.session.builds, len(joined)
            change()
            assert app.run(until=lambda: app.session.builds > builds and len(joined) > pages, timeout_s=120)
            page = joined[-1]
            wait(lambda: "Scene ready" in page.titles)
            assert page.titles.index("Building the scene") < page.titles.index("Scene ready")
            start = app.scene.steps
            assert app.run(until=lambda: app.scene.steps > start + 5, timeout_s=60)
        assert app.session.builds == 3 and app.session.notice == ""
        for name in ["scenes/bleeding.yaml", "scenes/hemostasis.yaml"] * 5 + ["scenes/default.yaml"]:
            app.session.switch_scene(name)  # a burst of switches (a trainer scrolling the dropdown): the last one wins
        assert app.run(until=lambda: app.session.builds > 3 and app.scene.steps > 3, timeout_s=120)
        assert app.session.builds == 4 and app.scene.name == "liver_cautery" and app.session.notice == ""
        for page in [*joined, second]:
            page.close()
    finally:
        app.close()
