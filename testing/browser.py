"""Shared helpers for headless-browser checks of the viser front end (Playwright, Debian chromium).

No browser download ever: Playwright drives the system chromium at CHROMIUM with software WebGL
(SwiftShader), as docs/guide/tests.md "Browser tests" describes. Software WebGL is slow, so helpers poll instead of
sleeping for fixed times.
"""
from __future__ import annotations

import io
import queue
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
from PIL import Image

from lab.bench.common import free_port  # noqa: F401  (the tests and tools take a port for their lab from here)

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]
VIEWPORT = {"width": 960, "height": 600}
LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1", "[::1]"}


def have_chromium() -> bool:
    return Path(CHROMIUM).is_file()



def launch(playwright):
    """A headless chromium from the system package (never a Playwright download)."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)


class BrowserThread:
    """A headless chromium driven by Playwright's sync API on a thread of its own, so that the main thread can run
    the lab's simulation loop meanwhile (Taichi compiles a rebuilt scene only on the thread that started it).
    `submit(fn)` runs fn(browser) on that thread and returns a Future; every Playwright object must be used there."""

    def __init__(self, start_timeout_s: float = 120.0):
        self._jobs: queue.Queue = queue.Queue()
        self._ready: Future = Future()
        self._thread = threading.Thread(target=self._main, name="browser", daemon=True)
        self._thread.start()
        self._ready.result(timeout=start_timeout_s)

    def _main(self) -> None:
        from playwright.sync_api import sync_playwright

        try:
            with sync_playwright() as playwright:
                instance = launch(playwright)
                self._ready.set_result(True)
                while (job := self._jobs.get()) is not None:
                    fn, future = job
                    if not future.set_running_or_notify_cancel():
                        continue
                    try:
                        future.set_result(fn(instance))
                    except BaseException as exc:  # handed to whoever waits on the future
                        future.set_exception(exc)
                instance.close()
        except BaseException as exc:
            if not self._ready.done():
                self._ready.set_exception(exc)

    def submit(self, fn) -> Future:
        future: Future = Future()
        self._jobs.put((fn, future))
        return future

    def close(self, timeout_s: float = 30.0) -> None:
        self._jobs.put(None)
        self._thread.join(timeout=timeout_s)


def is_local(url: str) -> bool:
    parsed = urlparse(url)
    if parsed.scheme in ("data", "blob", "about"):
        return True
    return parsed.hostname in LOCAL_HOSTS


FRAME_COUNTER_JS = """
(() => {
  window.__drawnFrames = 0; window.__drawCalls = 0;
  let pending = false;
  for (const ctx of [WebGLRenderingContext, WebGL2RenderingContext]) {
    const orig = ctx.prototype.drawElements;
    ctx.prototype.drawElements = function (...args) {
      window.__drawCalls++;
      if (!pending) { pending = true; window.__drawnFrames++; requestAnimationFrame(() => { pending = false; }); }
      return orig.apply(this, args);
    };
  }
})();
"""


class Viewer:
    """One browser page on a viser server; remembers every request URL and console error."""

    def __init__(self, browser, url: str, viewport=None, count_frames: bool = False):
        self.context = browser.new_context(viewport=viewport or VIEWPORT)
        self.page = self.context.new_page()
        if count_frames:  # window.__drawnFrames: frames in which WebGL drew anything; window.__drawCalls
            self.page.add_init_script(FRAME_COUNTER_JS)
        self.requests: list[str] = []
        self.errors: list[str] = []
        self.page.on("request", lambda request: self.requests.append(request.url))
        self.page.on("websocket", lambda ws: self.requests.append(ws.url))
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        self.page.goto(url, wait_until="domcontentloaded")
        # viser has two canvases (WebGL and a 2D overlay that stays 0 x 0); wait for one that is drawn at a size
        self.page.wait_for_function("() => [...document.querySelectorAll('canvas')].some(c => c.width > 0 && c.height > 0)", timeout=60_000)

    def screenshot(self, timeout_s: float = 60.0) -> np.ndarray:
        """(H, W, 3) uint8 of the viewport (the page has to draw a frame for it: up to seconds in software WebGL)."""
        return decode(self.page.screenshot(type="png", timeout=timeout_s * 1000))

    def wait_for(self, predicate, timeout_s: float = 60.0, interval_s: float = 0.5, save_to=None) -> np.ndarray:
        """Poll screenshots until predicate(image) is true; returns that image or raises TimeoutError (after saving the
        last screenshot to save_to, when given)."""
        deadline = time.monotonic() + timeout_s
        image = None
        while time.monotonic() < deadline:
            image = self.screenshot(timeout_s=max(deadline - time.monotonic(), 1.0))
            if predicate(image):
                return image
            self.page.wait_for_timeout(interval_s * 1000)
        if save_to is not None and image is not None:
            save(image, save_to)
        raise TimeoutError(f"the page never satisfied {getattr(predicate, '__name__', 'the condition')} in {timeout_s} s")

    def record(self, min_seconds: float, min_frames: int, max_seconds: float, scale: float = 1.0) -> list[np.ndarray]:
        """Every frame the page draws (DevTools screencast, JPEG) for at least min_seconds and until min_frames
        frames came, at most max_seconds. Cheaper than screenshots, which make the page draw extra frames
        (seconds each in software WebGL while the scene streams)."""
        cast = Screencast(self, format="jpeg", scale=scale)
        cast.start()
        started = time.monotonic()
        try:
            while True:
                self.page.wait_for_timeout(250)
                elapsed = time.monotonic() - started
                if (elapsed >= min_seconds and len(cast.frames) >= min_frames) or elapsed >= max_seconds:
                    break
        finally:
            cast.stop()
        return [decode(data) for _, data in cast.frames]

    @property
    def closed(self) -> bool:
        return self.page.is_closed()

    def close(self) -> None:
        self.context.close()


def decode(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def save(image: np.ndarray, path) -> None:
    Image.fromarray(np.asarray(image, np.uint8)).save(path)


def tissue_mask(image: np.ndarray) -> np.ndarray:
    """Pixels of lit liver tissue: clearly red (red well above green and blue). Background, UI and burns are not."""
    rgb = np.asarray(image, np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 90) & (r - g > 40) & (r - b > 30)


def white_fraction(image: np.ndarray, level: int = 100) -> float:
    """Fraction of pale pixels (min(R, G, B) > level): coagulated tissue (pale tan, sRGB about 160-190, 130-155,
    115-140 unlit); lit red liver (green and blue below about 60) stays far below."""
    return float((np.asarray(image).min(axis=-1) > level).mean())


def region(image: np.ndarray, centre_xy, half: int) -> np.ndarray:
    x, y = (int(round(v)) for v in centre_xy)
    return image[max(y - half, 0):y + half, max(x - half, 0):x + half]


def project(points_mm, camera_position, look_at, fov_rad: float, size_wh, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points for a pinhole camera like three.js's (vertical fov, square pixels).
    When the view direction is parallel to `up` (camera straight above), screen up is world +y."""
    points = np.atleast_2d(np.asarray(points_mm, np.float64))
    eye, target = np.asarray(camera_position, np.float64), np.asarray(look_at, np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    up = np.asarray(up, np.float64)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(forward, [0.0, 1.0, 0.0]) if abs(forward[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    rel = points - eye
    depth = rel @ forward
    focal = 0.5 * size_wh[1] / np.tan(fov_rad / 2)
    x = size_wh[0] / 2 + focal * (rel @ right) / depth
    y = size_wh[1] / 2 - focal * (rel @ true_up) / depth
    return np.stack([x, y], axis=1)


class Screencast:
    """Every frame the page draws, through the DevTools screencast (Playwright screenshots are too slow for that)."""

    def __init__(self, viewer: Viewer, format: str = "png", scale: float = 1.0):
        self.format = format
        self.scale = scale
        self.viewer = viewer
        self.frames: list[tuple[float, bytes]] = []
        self.session = viewer.context.new_cdp_session(viewer.page)
        self.session.on("Page.screencastFrame", self._on_frame)

    def _on_frame(self, event) -> None:
        import base64

        self.frames.append((time.monotonic(), base64.b64decode(event["data"])))
        try:
            self.session.send("Page.screencastFrameAck", {"sessionId": event["sessionId"]})
        except Exception:  # the session may be closing
            pass

    def start(self) -> None:
        size = self.viewer.page.viewport_size
        self.session.send("Page.startScreencast", {"format": self.format, "quality": 90, "everyNthFrame": 1, "maxWidth": int(size["width"] * self.scale), "maxHeight": int(size["height"] * self.scale)})

    def stop(self) -> None:
        try:
            self.session.send("Page.stopScreencast")
            self.session.detach()
        except Exception:
            pass


def footprint(vertices_mm, faces, camera_position, look_at, fov_rad: float, size_wh, erode_px: int = 4) -> np.ndarray:
    """(H, W) bool: pixels the mesh covers in a view (see project), shrunk by erode_px so edges do not count."""
    from PIL import ImageDraw
    from scipy import ndimage

    xy = project(vertices_mm, camera_position, look_at, fov_rad, size_wh)
    canvas = Image.new("1", tuple(int(v) for v in size_wh), 0)
    draw = ImageDraw.Draw(canvas)
    for tri in np.asarray(faces):
        draw.polygon([tuple(p) for p in xy[tri]], fill=1)
    covered = np.asarray(canvas, bool)
    return ndimage.binary_erosion(covered, iterations=erode_px) if erode_px > 0 else covered


def hole_pixels(image: np.ndarray, covered: np.ndarray, background_rgb, tolerance: int = 30) -> int:
    """Background-coloured pixels where the mesh should be: a missing tile shows up as thousands of them."""
    is_background = np.abs(np.asarray(image, np.int32) - np.asarray(background_rgb, np.int32)).max(axis=-1) <= tolerance
    return int((is_background & covered).sum())
