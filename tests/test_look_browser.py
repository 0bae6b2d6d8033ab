"""The look's material reaches the browser: in Debian chromium, blood on the tissue has a specular highlight (its
brightest pixels far above its median) and the highlight moves over the blood when the camera orbits, so it comes
from the browser's lighting of the normal and roughness maps, not from the colour; and the mesh is shaded smoothly,
not triangle by triangle. Waits are for conditions (a loaded 2-core machine: software WebGL draws a frame in
seconds)."""
import numpy as np
import pytest

from sims.scene.config import REPO_ROOT
from testing import browser

needs_chromium = pytest.mark.skipif(not browser.have_chromium(), reason=f"needs Debian chromium at {browser.CHROMIUM} (.ci/run installs it)")
VIEWPORT = {"width": 900, "height": 700}
AZIMUTHS_DEG = (-35.0, 0.0)
ELEVATION_DEG = 45.0
BLOOD_MM = 0.1          # texels under at least this much blood, within REACH_MM of the vessel, are the blood region
REACH_MM = 14.0
DISTANCE_MM = 45.0
HIGHLIGHT_LEVELS = 60   # the measure: the brightest blood pixels at least this far above the median
CLOSE_MM = 12.0         # the close-up's distance
STEP_PX = 1.5           # shading steps: pixels this far either side of a line
FACET_RATIO = 1.6       # smooth shading: the steps across the mesh's edges at most this many times those inside
                        # (measured 1.20 with smooth shading, 2.39 with flat)
LIT_LEVELS = 100        # shading steps are counted in the highlight: pixels brighter than this


@pytest.fixture(scope="module")
def lab():
    from lab.web.app import LabApp

    app = LabApp(REPO_ROOT / "scenes" / "bleeding.yaml", "127.0.0.1", browser.free_port(), "cpu",
                 overrides=("texture_size=256", "bleed_points.0.rate_ml_s=0.1"))
    assert app.run(until=lambda: app.scene.time_s >= 2.0, timeout_s=300)
    app.set_running(False)
    yield app
    app.close()


def _blood_texels(scene) -> np.ndarray:
    depth = scene.film.resampler.array(scene.film.trail.to_numpy())
    positions = scene.surface.position_mm[scene.surface.mask & (depth > BLOOD_MM)].astype(np.float64)
    vessel = scene.bleed_points[0].position_at(scene.time_s)
    return positions[np.linalg.norm(positions - vessel, axis=1) < REACH_MM]


def _shading_steps(surface, near_mm, image, eye, centre, fov_rad):
    """(mean luminance step across the mesh's edges, mean step across its triangles' middles, steps counted) for the
    triangles within 1 mm of near_mm, between the pixels STEP_PX either side of each line along an edge's screen
    direction, where the brighter of the two is lit (LIT_LEVELS up to 250, short of saturation). Flat shading lights
    each triangle by its own plane, so in a highlight its steps gather on the edges."""
    from scipy.spatial import cKDTree

    vertices, faces = np.asarray(surface.vertices_mm, np.float64), np.asarray(surface.faces)
    centroids = vertices[faces].mean(axis=1)
    faces = faces[cKDTree(near_mm).query(centroids, distance_upper_bound=1.0)[0] < 1.0]
    size = (image.shape[1], image.shape[0])
    corners = browser.project(vertices[faces].reshape(-1, 3), eye, centre, fov_rad, size).reshape(-1, 3, 2)
    luminance = image.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])

    def steps(points, along):
        normal = np.stack([-along[:, 1], along[:, 0]], axis=1) / np.linalg.norm(along, axis=1, keepdims=True)
        a, b = np.rint(points + STEP_PX * normal).astype(int), np.rint(points - STEP_PX * normal).astype(int)
        inside = np.all((a >= 0) & (a < size) & (b >= 0) & (b < size), axis=1)
        first, second = luminance[a[inside, 1], a[inside, 0]], luminance[b[inside, 1], b[inside, 0]]
        lit = (np.maximum(first, second) > LIT_LEVELS) & (np.maximum(first, second) < 250)
        return np.abs(first - second)[lit]

    edge_steps = np.concatenate([steps(0.5 * (corners[:, k] + corners[:, (k + 1) % 3]),
                                       corners[:, (k + 1) % 3] - corners[:, k]) for k in range(3)])
    middle_steps = np.concatenate([steps(corners.mean(axis=1), corners[:, (k + 1) % 3] - corners[:, k]) for k in range(3)])
    return float(edge_steps.mean()), float(middle_steps.mean()), len(edge_steps)


def _most_curved(surface, near_mm) -> np.ndarray:
    """The centroid (mm) of the triangle within 1 mm of near_mm whose normal turns most from its neighbours'."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(np.asarray(surface.vertices_mm, np.float64), np.asarray(surface.faces), process=True)
    turn = np.zeros(len(mesh.faces))
    np.maximum.at(turn, mesh.face_adjacency[:, 0], mesh.face_adjacency_angles)
    np.maximum.at(turn, mesh.face_adjacency[:, 1], mesh.face_adjacency_angles)
    centroids = mesh.triangles_center
    turn[cKDTree(near_mm).query(centroids, distance_upper_bound=1.0)[0] >= 1.0] = -1.0
    return centroids[int(np.argmax(turn))]


@needs_chromium
def test_blood_has_a_smooth_highlight_that_moves_when_the_camera_orbits(lab, chrome, tmp_path):
    viewer = chrome.submit(lambda b: browser.Viewer(b, f"http://127.0.0.1:{lab.server.get_port()}/", viewport=VIEWPORT))
    assert lab.run(until=lambda: viewer.done() and len(lab.server.get_clients()) > 0, timeout_s=180)
    viewer = viewer.result(timeout=0)
    minimized = chrome.submit(lambda _: viewer.page.get_by_label("Minimize panel").first.click(timeout=240_000))
    assert lab.run(until=minimized.done, timeout_s=300)
    minimized.result(timeout=0)
    for view in lab.tool_views.values():  # nothing in front of the blood
        view["body"].visible = view["gizmo"].visible = False
    for marker, _ in lab.point_views.values():
        marker.visible = False
    client = next(iter(lab.server.get_clients().values()))
    blood = _blood_texels(lab.scene)
    assert len(blood) > 200, "too little blood to look at"
    centre = blood.mean(axis=0)
    distance = DISTANCE_MM
    highlights = []
    for azimuth in AZIMUTHS_DEG:
        a, e = np.radians(azimuth), np.radians(ELEVATION_DEG)
        position = centre + distance * np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
        client.camera.position = tuple(float(v) for v in position)  # position first: it keeps the orientation
        client.camera.look_at = tuple(float(v) for v in centre)
        assert lab.run(until=lambda: np.allclose(client.camera.position, position, atol=0.5)
                       and np.allclose(client.camera.look_at, centre, atol=0.5), timeout_s=120), "the camera did not move"
        pixels = browser.project(blood, position, centre, float(client.camera.fov), (VIEWPORT["width"], VIEWPORT["height"]))
        inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < VIEWPORT["width"] - 1) & (pixels[:, 1] >= 0) & (pixels[:, 1] < VIEWPORT["height"] - 1)
        assert inside.mean() > 0.6, f"the blood is not in view: {inside.mean():.2f} of it, camera {client.camera.position} -> {client.camera.look_at}"

        def blood_luminance(image):
            rgb = image[pixels[inside, 1].astype(int), pixels[inside, 0].astype(int)].astype(np.float64)
            return rgb @ np.array([0.2126, 0.7152, 0.0722])

        def lit_blood(image):  # the blood has arrived (red) and the page drew the new view
            rgb = image[pixels[inside, 1].astype(int), pixels[inside, 0].astype(int)].astype(np.int32)
            return np.median(rgb[:, 0] - rgb[:, 1]) > 40

        holder = {}
        job = chrome.submit(lambda _: viewer.wait_for(lit_blood, timeout_s=240, save_to=tmp_path / f"timeout_{azimuth:+.0f}.png"))
        assert lab.run(until=job.done, timeout_s=300)
        image = job.result(timeout=0)
        job = chrome.submit(lambda _: viewer.page.wait_for_timeout(3000) or viewer.screenshot(timeout_s=240))  # settled
        assert lab.run(until=job.done, timeout_s=300)
        image = job.result(timeout=0)
        browser.save(image, tmp_path / f"view_{azimuth:+.0f}.png")
        luminance = blood_luminance(image)
        top = np.percentile(luminance, 99.5)
        holder["brightest"] = blood[inside][luminance >= top]
        print(f"azimuth {azimuth:+.0f}: blood luminance median {np.median(luminance):.0f}, 99.5th percentile {top:.0f}")
        assert top - np.median(luminance) >= HIGHLIGHT_LEVELS, f"no highlight on the blood; see {tmp_path}"
        highlights.append(holder["brightest"].mean(axis=0))
    # up close over the most curved blood (where flat shading shows each triangle): steps across edges and middles
    bump = _most_curved(lab.scene.surface, blood)
    position = bump + CLOSE_MM * np.array([0.0, -np.cos(np.radians(ELEVATION_DEG)), np.sin(np.radians(ELEVATION_DEG))])
    client.camera.position = tuple(float(v) for v in position)
    client.camera.look_at = tuple(float(v) for v in bump)
    assert lab.run(until=lambda: np.allclose(client.camera.position, position, atol=0.5)
                   and np.allclose(client.camera.look_at, bump, atol=0.5), timeout_s=120), "the camera did not move"
    job = chrome.submit(lambda _: viewer.page.wait_for_timeout(3000) or viewer.screenshot(timeout_s=240))
    assert lab.run(until=job.done, timeout_s=300)
    image = job.result(timeout=0)
    browser.save(image, tmp_path / "close.png")
    across, within, count = _shading_steps(lab.scene.surface, blood, image, position, bump, float(client.camera.fov))
    print(f"close-up: luminance steps across triangles' edges {across:.1f}, across their middles {within:.1f} ({count} lit)")
    assert count >= 50, f"too little of the highlight in the close-up; see {tmp_path}"
    assert across <= FACET_RATIO * within, f"the mesh is lit triangle by triangle (flat shading); see {tmp_path}"
    moved = float(np.linalg.norm(highlights[0] - highlights[1]))
    print(f"the highlight moved {moved:.1f} mm over the blood between the views")
    assert moved > 2.0, f"the highlight stayed where it was ({moved:.1f} mm): baked into the colour? see {tmp_path}"
    chrome.submit(lambda _: viewer.close()).result(timeout=30)
