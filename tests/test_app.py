"""The browser lab (lab.app) in a real browser (Debian chromium via Playwright): sliders reach the simulation, live
or by a rebuild of the scene, and bleed points are added by clicking the tissue.

One LabApp for the module on the hemostasis scene (cautery and bleeding) at 128² texels. Its simulation loop runs
on this (main) thread, only while a test waits in `in_browser`: Taichi compiles a rebuilt scene only on the thread
that started it. The browser runs on a thread of its own (tests.browser.BrowserThread).
"""
import json
import math
import time

import numpy as np
import pytest
import yaml

from sims.config import REPO_ROOT
from tests import browser

needs_chromium = pytest.mark.skipif(not browser.have_chromium(), reason=f"needs Debian chromium at {browser.CHROMIUM} (.ci/run installs it)")
VIEWPORT = {"width": 1100, "height": 700}
CLICK_XY_MM = (-12.0, -4.0)   # a tissue spot left of the panel, away from the tools and the vessel's blood
SHARED: dict = {}           # what one test leaves for a later one


@pytest.fixture(scope="module")
def lab():
    from lab.app import LabApp

    app = LabApp(REPO_ROOT / "scenes" / "hemostasis.yaml", "127.0.0.1", browser.free_port(), "cpu", overrides=("texture_size=128",))
    app.set_simple_lighting(True)  # software WebGL: the page answers clicks about twice as fast
    yield app
    app.close()


@pytest.fixture(scope="module")
def chrome():
    thread = browser.BrowserThread()
    yield thread
    thread.close()


@pytest.fixture(scope="module")
def page(lab, chrome):
    """One page for the module (page loads are slow in software WebGL); the canvas drawn at half resolution."""
    url = f"http://127.0.0.1:{lab.server.get_port()}/?fixedDpr=0.5"
    viewer = in_browser(lab, chrome, lambda instance: browser.Viewer(instance, url, viewport=VIEWPORT), timeout_s=90)
    yield viewer
    chrome.submit(lambda _: viewer.close()).result(timeout=30)


def in_browser(lab, chrome, action, until=None, timeout_s: float = 30.0):
    """Run action(browser) on the browser thread while the lab's simulation loop runs here, then on until until()
    (called on this thread: it may read the scene). Returns what action returned."""
    job = chrome.submit(action)
    done = lab.run(until=lambda: job.done() and (job.exception() is not None or until is None or until()), timeout_s=timeout_s)
    result = job.result(timeout=0)  # raises what the browser side raised, or TimeoutError
    assert done, f"{getattr(until, '__name__', 'the condition')} did not hold within {timeout_s} s (notice: {lab.notice!r})"
    return result


def slider_input(page, label: str):
    """The number box next to a viser slider with this label."""
    text = page.get_by_text(label, exact=True)
    return text.locator("xpath=ancestor::*[.//input][1]").locator("input").last


def enter(page, folder: str, label: str, value) -> None:
    """Type a value into a slider's box (opening its folder if the slider is hidden) and press Enter."""
    text = page.get_by_text(label, exact=True)
    if not text.is_visible():
        page.get_by_text(folder, exact=True).click()
    text.wait_for(timeout=30_000)
    box = slider_input(page, label)
    box.fill(str(value))
    box.press("Enter")


# --- without a browser --------------------------------------------------------------------------

def test_overrides_read_back_as_the_same_values():
    from lab.app import override_texts
    from sims.config import parse_override

    values = {"a": 1e-05, "b": 1e16, "c": 0.02, "d": 512, "e": [1e-05, -2.5, 3.0], "f": [{"t_s": 1.0, "rate_ml_s": None}], "g": True}
    for text, (key, value) in zip(override_texts(values), values.items()):
        parts, read = parse_override(text)
        assert parts == [key] and read == value and type(read) is type(value), text
    assert yaml.safe_load("1e-05") == "1e-05"  # why: YAML 1.1 floats need a dot


def test_time_goes_on_from_where_it_is_when_the_time_step_changes(lab):
    scene = lab.scene
    scene.reset()
    for _ in range(7):
        scene.step()
    assert scene.time_s == 7 * 0.01  # exactly steps * dt while dt is unchanged (byte-identical runs)
    scene.config["time_step_s"] = 0.02
    for _ in range(3):
        scene.step()
    assert scene.time_s == pytest.approx(0.07 + 3 * 0.02, abs=1e-12)
    scene.config["time_step_s"] = 0.01
    scene.step()
    assert scene.time_s == pytest.approx(0.14, abs=1e-12)
    scene.reset()
    for _ in range(5):
        scene.step()
    assert scene.time_s == 5 * 0.01


# --- in the browser ------------------------------------------------------------------------------

@needs_chromium
def test_slider_changed_in_the_browser_changes_the_simulation(lab, chrome, page):
    def conductivity_set():
        return abs(lab.scene.config["tissue"]["conductivity_w_mk"] - 1.5) < 1e-6

    in_browser(lab, chrome, lambda _: enter(page.page, "Tissue", "conductivity_w_mk (W/(m K))", 1.5), until=conductivity_set)
    assert lab.scene.cautery.diffusivity_mm2_s > 0.3  # the heat model reads the new value


@needs_chromium
def test_values_outside_a_range_cannot_be_entered(lab, chrome, page):
    def typed_and_put_back(_):
        enter(page.page, "Tissue", "conductivity_w_mk (W/(m K))", 50)
        box = slider_input(page.page, "conductivity_w_mk (W/(m K))")
        deadline = time.monotonic() + 15
        while float(box.input_value() or "nan") != 5.0 and time.monotonic() < deadline:
            page.page.wait_for_timeout(100)
        return box.input_value()

    def clamped():
        return lab.scene.config["tissue"]["conductivity_w_mk"] == 5.0

    shown = in_browser(lab, chrome, typed_and_put_back, until=clamped)
    assert float(shown) == 5.0, f"the browser still shows {shown}"


@needs_chromium
def test_time_step_and_fluid_substeps_change_live(lab, chrome, page):
    scene, builds = lab.scene, lab.builds

    def type_both(_):
        enter(page.page, "Simulation", "time_step_s (s)", 0.02)
        enter(page.page, "Bleeding", "substeps", 4)

    def both_set():
        return lab.scene.config["time_step_s"] == 0.02 and lab.scene.bleeding.params["substeps"] == 4

    in_browser(lab, chrome, type_both, until=both_set)
    steps0, time0 = scene.steps, scene.time_s
    assert lab.run(until=lambda: scene.steps >= steps0 + 10, timeout_s=20)
    assert lab.scene is scene and lab.builds == builds, "a live parameter rebuilt the scene"
    assert scene.time_s == pytest.approx(time0 + (scene.steps - steps0) * 0.02, abs=1e-9), "time jumped"


@needs_chromium
def test_bleed_point_added_by_clicking_the_tissue_bleeds_there(lab, chrome, page):
    from scipy.spatial import cKDTree

    scene = lab.scene
    surface = scene.surface
    texels = surface.position_mm[surface.mask].astype(np.float64)
    target = texels[cKDTree(texels[:, :2]).query(CLICK_XY_MM)[1]]
    client = next(iter(lab.server.get_clients().values()))
    camera = (np.asarray(client.camera.position), np.asarray(client.camera.look_at), float(client.camera.fov))
    names = {point.name for point in scene.bleed_points}

    def new_points():
        return [point for point in lab.scene.bleed_points if point.name not in names]

    def add_and_click(_):
        tab = page.page
        box = max((c.bounding_box() for c in tab.locator("canvas").all()), key=lambda b: (b or {}).get("width", 0) * (b or {}).get("height", 0))
        x, y = browser.project(target, camera[0], camera[1], camera[2], (box["width"], box["height"]))[0]
        tab.get_by_text("Add bleed point (then click the tissue)", exact=True).click()
        for _ in range(10):  # the client must have been told to report clicks first
            tab.wait_for_timeout(700)
            tab.mouse.click(box["x"] + x, box["y"] + y)
            tab.wait_for_timeout(300)
            if new_points():
                return
        raise AssertionError("no bleed point after 10 clicks on the tissue")

    def bleeding_there():
        added = new_points()
        if not added:
            return False
        position = added[0].position_at(lab.scene.time_s)
        blood = lab.scene.bleeding.particle_arrays()["particle_position_mm"]
        return int((np.linalg.norm(blood - position, axis=1) < added[0].item["radius_mm"] + 1.5).sum()) >= 10

    in_browser(lab, chrome, add_and_click, until=bleeding_there, timeout_s=45)
    (point,) = new_points()
    position = point.position_at(scene.time_s)
    assert np.linalg.norm(texels - position, axis=1).min() < 1e-4, "the bleed point is not on the surface"
    assert np.linalg.norm(position - target) < 1.5, f"bleed point at {position}, clicked at {target}"
    assert point.name in lab.point_folders, "the new point has no sliders"
    SHARED["bleed_point"] = point.name  # the rebuild test checks it survives a rebuild


@needs_chromium
def test_rebuild_type_sliders_restart_the_scene_once_with_the_new_values(lab, chrome, page):
    scene, builds = lab.scene, lab.builds
    # in the browser: the texture size; the rebuild waits for REBUILD_DELAY_S of quiet
    in_browser(lab, chrome, lambda _: enter(page.page, "Simulation", "texture_size (texels)", 96), until=lambda: lab._rebuild_at is not None)
    radius = lab.sliders["instruments.1.shape.radius_mm"]  # then a drag of the ball electrode's radius, from the GUI side
    for value in np.linspace(1.6, 2.4, 20):
        radius.value = float(value)
    assert lab.run(until=lambda: lab.builds > builds and lab._rebuild_at is None, timeout_s=60)
    rebuilt = lab.scene
    assert lab.run(until=lambda: rebuilt.time_s > 2 * 0.5, timeout_s=30)  # a second rebuild would have come by now
    assert lab.builds == builds + 1 and rebuilt is not scene
    assert rebuilt.surface.mask.shape == (96, 96) and rebuilt.composite().shape[:2] == (96, 96)
    assert rebuilt.instruments[1].shape["radius_mm"] == pytest.approx(2.4)
    # what was changed live before stays changed; the point added by clicking is there again
    assert rebuilt.config["tissue"]["conductivity_w_mk"] == 5.0 and rebuilt.config["time_step_s"] == 0.02
    assert rebuilt.bleeding.params["substeps"] == 4
    assert SHARED.get("bleed_point") in {point.name for point in rebuilt.bleed_points}

    def shown(_):
        text = page.page.get_by_text("texture_size (texels)", exact=True)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if not text.is_visible():
                page.page.get_by_text("Simulation", exact=True).click()
            text.wait_for(timeout=20_000)
            if slider_input(page.page, "texture_size (texels)").input_value() == "96":
                return True
            page.page.wait_for_timeout(300)
        return False

    assert in_browser(lab, chrome, shown), "the rebuilt GUI does not show the new texture size"


def test_scene_switch_keeps_the_quality_and_drops_the_scene_changes(lab):
    from lab.app import QUALITY

    builds = lab.builds
    lab.quality_dropdown.value = "fast"           # fires the GUI callbacks, as a browser would
    lab.scene_dropdown.value = "scenes/bleeding.yaml"
    assert lab.run(until=lambda: lab.scene.name == "liver_bleeding" and lab._rebuild_at is None, timeout_s=60)
    assert lab.builds == builds + 1, "the quality change and the switch should build once"
    assert lab.overrides == QUALITY["fast"] and lab.quality == "fast"
    assert lab.scene.surface.mask.shape == (256, 256) and lab.scene.bleeding.params["substeps"] == 1
    assert lab.scene.config["time_step_s"] == 0.01 and not lab.added_points
    assert [point.name for point in lab.scene.bleed_points] == ["vessel"]
    assert math.isfinite(lab.scene.time_s)


def test_rebuilds_never_run_the_taichi_runtime_out_of_field_trees(lab):
    """Taichi frees no field of a dropped scene and allows 512 field trees per runtime (a hemostasis build makes 14):
    every rebuild starts a fresh runtime, so the count stays where one build puts it however long a session lasts."""
    import taichi as ti

    trees = []
    for size in (64, 80, 64, 80, 64, 80):
        lab.overrides["texture_size"] = size
        lab._schedule_rebuild()
        builds = lab.builds
        assert lab.run(until=lambda: lab.builds > builds and lab.scene.steps >= 3, timeout_s=60)
        trees.append(ti.lang.impl.get_runtime().prog.get_snode_tree_size())
        assert lab.scene.surface.mask.shape == (size, size)
    assert trees[-1] <= trees[0], f"field trees grew over rebuilds: {trees}"
    rgb = lab.scene.composite()
    assert rgb.shape == (80, 80, 3) and rgb.std() > 0
    assert lab.scene.time_s > 0 and json.dumps(lab.scene.metrics(), allow_nan=False)  # finite numbers throughout


def test_a_scene_whose_mesh_fails_to_load_brings_the_previous_scene_back(lab, tmp_path):
    (tmp_path / "broken.obj").write_text("v 0 0 0\nthis is not a mesh\n")
    scene_file = tmp_path / "broken.yaml"
    scene_file.write_text(yaml.safe_dump({"name": "broken", "mesh": str(tmp_path / "broken.obj"), "models": ["cautery"]}))
    name, builds = lab.scene.name, lab.builds
    lab._switch_scene(scene_file)
    assert lab.scene.name == name and lab.builds == builds + 1
    assert "broken.obj" in lab.notice and "not switched" in lab.notice
    steps = lab.scene.steps
    assert lab.run(until=lambda: lab.scene.steps > steps + 3, timeout_s=30)
