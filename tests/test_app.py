"""The browser lab's GUI in a real browser (Debian chromium via Playwright): sliders reach the simulation."""
import socket
import time
from pathlib import Path

import pytest

from sims.config import REPO_ROOT

CHROMIUM = Path("/usr/bin/chromium")
pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian chromium (.ci/run installs it)")
BROWSER_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking", "--disable-component-update", "--no-first-run"]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="module")
def lab():
    from lab.app import LabApp

    app = LabApp(REPO_ROOT / "scenes" / "default.yaml", "127.0.0.1", free_port(), "cpu", overrides=("texture_size=128",))
    app.scene.step()  # first kernel launches on this (main) thread
    app.start()
    yield app
    app.close()


@pytest.fixture(scope="module")
def page(lab):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
        tab = browser.new_page(viewport={"width": 1280, "height": 800})
        tab.goto(f"http://127.0.0.1:{lab.server.get_port()}")
        tab.wait_for_selector("canvas", timeout=60_000)
        yield tab
        browser.close()


def slider_input(page, label: str):
    """The number box next to a viser slider with this label."""
    text = page.get_by_text(label, exact=True)
    text.wait_for(timeout=30_000)
    return text.locator("xpath=ancestor::*[.//input][1]").locator("input").last


def wait_for(condition, seconds: float = 15.0) -> bool:
    deadline = time.time() + seconds
    while time.time() < deadline:
        if condition():
            return True
        time.sleep(0.2)
    return False


def test_slider_changed_in_the_browser_changes_the_simulation(lab, page):
    page.get_by_text("Tissue", exact=True).click()
    box = slider_input(page, "conductivity_w_mk (W/(m K))")
    box.fill("1.5")
    box.press("Enter")
    assert wait_for(lambda: abs(lab.scene.config["tissue"]["conductivity_w_mk"] - 1.5) < 1e-6)
    assert lab.scene.cautery.diffusivity_mm2_s > 0.3  # the heat model reads the new value


def test_values_outside_a_range_cannot_be_entered(lab, page):
    box = slider_input(page, "conductivity_w_mk (W/(m K))")
    box.fill("50")
    box.press("Enter")
    time.sleep(1.0)
    assert lab.scene.config["tissue"]["conductivity_w_mk"] <= 5.0
