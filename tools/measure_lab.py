"""Measure the browser lab in a real browser, and optionally save a screenshot of it (not part of the test suite).

    python tools/measure_lab.py [--sizes 512 256] [--seconds 10] [--tries 5] [--simple-lighting] [--half-resolution] [--out runs/measure_lab]
    python tools/measure_lab.py --screenshot docs/lab_browser.png

For each texture size, `python -m lab serve`'s LabApp runs the default scene and Debian chromium (Playwright, software
WebGL through SwiftShader, as in the tests; never a downloaded browser) shows it at 1280 x 720.
1. Stream: the scene's scripted demo from t = 0 for --seconds. Server side, every texture update is logged (tiles and
   bytes handed to viser); browser side, every frame the page draws is captured (DevTools screencast), and frames
   whose pixels changed are counted.
2. Latency: every tool taken over by hand where it is (its script stops) and switched off, then the ball electrode
   placed through the session (energized, 250 C, 0.3 mm into the tissue) onto a fresh spot; the time until the spot
   changes visibly in the screencast (mean colour of a 2 x 2 mm square off by more than 25 levels from before the
   move) is taken, --tries spots, median. The instruments' models and gizmos are hidden during this part, so that
   they do not cover the spot. Also logged: when the composite texture on the server first showed the change
   (simulation + compose), and the first stream update after that which published tiles (the stream publishes the
   tiles that changed most first, so a fresh burn's tile is among them; the stream has no public per-tile record).
Everything goes through the lab's public API (lab.session.LabSession commands, LabApp.tool_views, the stream's
`update` and `stats`); the only probe is a wrapper around the app's `stream.update` that logs each texture update.
Results: a table on stdout and OUT/results.json.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from testing import browser  # noqa: E402

VIEWPORT = {"width": 1280, "height": 720}
SPOTS_XY_MM = [(-20.0, -8.0), (-10.0, -10.0), (0.0, -10.0), (-15.0, -2.0), (-4.0, -4.0), (6.0, -9.0), (-24.0, 0.0)]
CHANGE_LEVELS = 25.0      # a region's mean colour off by more than this (0..255) counts as a visible change
SQUARE_MM = 2.0           # side of the square checked about the spot
HIDE_NOTICE_JS = """() => {
  const title = [...document.querySelectorAll('*')].find(e => e.childElementCount === 0 && e.textContent.trim() === 'Software WebGL rendering detected');
  let node = title;
  while (node && node.getAttribute && node.getAttribute('role') !== 'alert') node = node.parentElement;
  if (node || title) (node || title.parentElement.parentElement).style.display = 'none';
}"""
TIP_TEMPERATURE_C = 250.0  # of the electrode placed for the latency
PRESS_MM = 0.3            # its ball centre this far into the tissue along the normal
SHOT_LOOK_AT_MM, SHOT_FROM = (0.0, 3.0, 1.0), (0.0, -26.0, 40.0)   # the screenshot's camera: target, offset (mm)


def run_while(app, job, until=None, timeout_s: float = 120.0):
    """The lab's loop on this thread while the browser job runs (see tests/test_app.py in_browser)."""
    app.run(until=lambda: job.done() and (job.exception() is not None or until is None or until()), timeout_s=timeout_s)
    return job.result(timeout=0)


def open_lab(size: int | None, arch: str, simple_lighting: bool = False):
    from lab.web.app import LabApp

    overrides = (f"texture_size={size}",) if size else ()
    app = LabApp(REPO / "scenes" / "default.yaml", "127.0.0.1", browser.free_port(), arch, overrides=overrides)
    app.set_simple_lighting(simple_lighting)
    log = []  # (monotonic s, tiles_sent, bytes, tiles_deferred, rgb)
    update = app.stream.update

    def logged(rgb, *maps, **options):
        result = update(rgb, *maps, **options)
        log.append((time.monotonic(), result["tiles_sent"], result["bytes"], result["tiles_deferred"], np.array(rgb)))
        del log[:-60]  # the images of the last 2 s or so (the counts go to totals)
        logged.totals.append((log[-1][0], result["tiles_sent"], result["bytes"], result["tiles_deferred"]))
        return result

    logged.totals = []
    app.stream.update = logged
    return app, log, logged.totals


def the_client(app, chrome, viewer):
    """The one browser connected to the lab (the loop runs until it is there)."""
    run_while(app, chrome.submit(lambda _: pump(viewer, 0.2)), until=lambda: len(app.server.get_clients()) > 0, timeout_s=60)
    return next(iter(app.server.get_clients().values()))


def canvas_box(page) -> dict:
    boxes = [c.bounding_box() for c in page.locator("canvas").all()]
    return max((b for b in boxes if b), key=lambda b: b["width"] * b["height"])


def start_cast(viewer) -> browser.Screencast:
    cast = browser.Screencast(viewer, format="jpeg", scale=1.0)
    cast.start()
    return cast


def pump(viewer, seconds: float, stop: threading.Event | None = None) -> None:
    """Let Playwright dispatch the screencast's frames (the sync API does so only inside its own calls), for `seconds`
    or until `stop` is set."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (stop is not None and stop.is_set()):
        viewer.page.wait_for_timeout(100)


def frames_after(cast, t0: float):
    return [(t, data) for t, data in list(cast.frames) if t >= t0]


def decode(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float32)


def measure_stream(app, totals, chrome, viewer, seconds: float) -> dict:
    app.session.reset()  # applied by the loop's first tick
    start = time.monotonic()
    cast = chrome.submit(lambda _: start_cast(viewer)).result(timeout=30)
    run_while(app, chrome.submit(lambda _: pump(viewer, seconds)), timeout_s=seconds + 60)
    chrome.submit(lambda _: cast.stop()).result(timeout=30)
    end = time.monotonic()
    window = [row for row in totals if start <= row[0] <= end]
    sent = [row for row in window if row[1] > 0]
    images = [decode(data) for t, data in frames_after(cast, start)]
    changed = sum(1 for a, b in zip(images, images[1:]) if (np.abs(a - b).max(axis=-1) > 30).sum() > 20)
    return {
        "seconds": end - start,
        "simulated_s": app.scene.time_s,
        "steps_per_s": app.scene.steps / (end - start),  # counted from the reset, the loop's first command
        "updates": len(window),
        "updates_with_tiles": len(sent),
        "updates_with_tiles_per_s": len(sent) / (end - start),
        "tiles_per_update": float(np.mean([row[1] for row in sent])) if sent else 0.0,
        "bytes_per_update": float(np.mean([row[2] for row in sent])) if sent else 0.0,
        "bytes_per_s": sum(row[2] for row in window) / (end - start),
        "tiles_deferred": sum(row[3] for row in window),
        "browser_frames_per_s": len(images) / (end - start),
        "browser_changed_frames_per_s": changed / (end - start),
    }


def hold_every_tool(app) -> None:
    """Every tool taken over by hand where it is now (its script stops) and switched off."""
    for tool in app.scene.instruments:
        pose = tool.pose_at(app.scene.time_s)
        app.session.take_over(tool.name, pose.position_mm, pose.direction, pose.roll_deg)
        app.session.set_energized(tool.name, False)


def measure_latency(app, log, chrome, viewer, tries: int) -> dict:
    hold_every_tool(app)
    for view in app.tool_views.values():
        view["body"].visible = False
        view["gizmo"].visible = False
    tool = app.scene.instruments[0]
    app.session.set_parameter(f"instruments.{tool.name}.tip_temperature_c", TIP_TEMPERATURE_C)
    radius = tool.shape["radius_mm"]
    surface = app.scene.surface
    client = the_client(app, chrome, viewer)
    camera = (np.asarray(client.camera.position), np.asarray(client.camera.look_at), float(client.camera.fov))
    box = chrome.submit(lambda _: canvas_box(viewer.page)).result(timeout=30)
    size = (box["width"], box["height"])
    cast = chrome.submit(lambda _: start_cast(viewer)).result(timeout=30)
    rows, cols = np.nonzero(surface.mask)
    texels = surface.position_mm[rows, cols].astype(np.float64)
    reach = max(1, int(round(SQUARE_MM / 2 / float(np.sqrt(np.median(surface.texel_area_mm2[surface.mask]))))))  # texels

    def texture_square(rgb, row, col):  # the same square on the composite texture (rows of the texture = rows here)
        return rgb[max(row - reach, 0):row + reach + 1, max(col - reach, 0):col + reach + 1].reshape(-1, 3).astype(np.float32).mean(axis=0)
    results = []
    for x_mm, y_mm in SPOTS_XY_MM[:tries]:
        index = int(np.argmin(np.linalg.norm(texels[:, :2] - [x_mm, y_mm], axis=1)))
        point, (row, col) = texels[index], (rows[index], cols[index])
        normal = surface.normal[row, col].astype(np.float64)
        pixels = browser.project(np.stack([point, point + [SQUARE_MM / 2, 0, 0], point + [0, SQUARE_MM / 2, 0]]), *camera, size)
        half = max(3, int(round(max(np.linalg.norm(pixels[1] - pixels[0]), np.linalg.norm(pixels[2] - pixels[0])))))
        centre = pixels[0] + [box["x"], box["y"]]
        run_while(app, chrome.submit(lambda _: pump(viewer, 1.5)))
        # the page draws only when something changed, so the screencast may be silent now: a screenshot instead
        image = run_while(app, chrome.submit(lambda _: browser.decode(viewer.page.screenshot(type="png", timeout=60_000))))
        before = browser.region(image.astype(np.float32), centre, half).reshape(-1, 3).mean(axis=0)
        texel_before = texture_square(log[-1][4], row, col)
        seen = {}

        def changed():
            if "texture" in seen and "sent" not in seen:  # the first update since the change that published tiles
                sent = [t for t, tiles_sent, _, _, _ in list(log) if t >= seen["texture"] and tiles_sent > 0]
                if sent:
                    seen["sent"] = min(sent)
            if "texture" not in seen:
                for t, _, _, _, rgb in list(log):
                    if t >= seen["t0"]:
                        if np.abs(texture_square(rgb, row, col) - texel_before).max() > CHANGE_LEVELS:
                            seen["texture"] = t
                            break
            for t, data in frames_after(cast, seen.get("checked", seen["t0"])):
                seen["checked"] = t + 1e-9
                now = browser.region(decode(data), centre, half).reshape(-1, 3).mean(axis=0)
                if np.abs(now - before).max() > CHANGE_LEVELS:
                    seen["visible"] = t
                    return True
            return False

        seen["t0"] = time.monotonic()
        app.session.take_over(tool.name, point + normal * (radius - PRESS_MM), -normal)
        app.session.set_energized(tool.name, True)
        stop = threading.Event()
        job = chrome.submit(lambda _: pump(viewer, 20.0, stop))
        app.run(until=lambda: changed() or job.done(), timeout_s=25)
        stop.set()
        job.result(timeout=30)
        app.session.take_over(tool.name, point + normal * 15.0, -normal)  # lifted off
        app.session.set_energized(tool.name, False)
        results.append({"spot_mm": [x_mm, y_mm], "visible_s": seen.get("visible", float("nan")) - seen["t0"],
                        "texture_s": seen.get("texture", float("nan")) - seen["t0"], "sent_s": seen.get("sent", float("nan")) - seen["t0"]})
        print(f"  spot {x_mm:+.0f},{y_mm:+.0f} mm: texture changed after {results[-1]['texture_s']:.2f} s, tiles published after "
              f"{results[-1]['sent_s']:.2f} s, visible in the browser after {results[-1]['visible_s']:.2f} s", flush=True)
    chrome.submit(lambda _: cast.stop()).result(timeout=30)
    visible = [r["visible_s"] for r in results if np.isfinite(r["visible_s"])]
    texture = [r["texture_s"] for r in results if np.isfinite(r["texture_s"])]
    sent = [r["sent_s"] for r in results if np.isfinite(r["sent_s"])]
    return {"tries": results,
            "median_visible_s": statistics.median(visible) if visible else None,
            "range_visible_s": [min(visible), max(visible)] if visible else None,
            "median_texture_s": statistics.median(texture) if texture else None,
            "median_sent_s": statistics.median(sent) if sent else None}


def measure(size: int, args, chrome) -> dict:
    app, log, totals = open_lab(size, args.arch, args.simple_lighting)
    try:
        url = f"http://127.0.0.1:{app.server.get_port()}/" + ("?fixedDpr=0.5" if args.half_resolution else "")
        viewer = run_while(app, chrome.submit(lambda b: browser.Viewer(b, url, viewport=VIEWPORT)), timeout_s=180)
        run_while(app, chrome.submit(lambda _: pump(viewer, 5.0)))  # the first tiles and the environment map
        print(f"{size}²: stream while the demo runs {args.seconds} s ...", flush=True)
        stream = measure_stream(app, totals, chrome, viewer, args.seconds)
        print(f"{size}²: tool move to visible burn, {args.tries} spots ...", flush=True)
        latency = measure_latency(app, log, chrome, viewer, args.tries)
        chrome.submit(lambda _: viewer.close()).result(timeout=30)
        return {"texture_size": size, "half_resolution": args.half_resolution, "simple_lighting": args.simple_lighting, "load_average_1min": os.getloadavg()[0],
                "stream": stream, "latency": latency}
    finally:
        app.close()


def screenshot(path: Path, args, chrome) -> None:
    """The default scene paused mid-stroke (--shot-at-s): the hot ball on the tissue, its burn track behind it, the
    spatula's burn, the panel with the stats beside."""
    app, _, _ = open_lab(None, args.arch)
    try:
        url = f"http://127.0.0.1:{app.server.get_port()}/"
        viewer = run_while(app, chrome.submit(lambda b: browser.Viewer(b, url, viewport={"width": 1280, "height": 800})), timeout_s=180)
        client = the_client(app, chrome, viewer)
        look_at = np.array(SHOT_LOOK_AT_MM)
        client.camera.look_at = tuple(look_at)
        client.camera.position = tuple(look_at + np.array(SHOT_FROM))
        app.session.reset()
        run_while(app, chrome.submit(lambda _: pump(viewer, 0.5)), until=lambda: app.scene.time_s >= args.shot_at_s, timeout_s=120)
        app.set_running(False)

        def shot(_):
            page = viewer.page
            page.evaluate(HIDE_NOTICE_JS)  # the "software WebGL" notice, which only this machine gets
            # folded, so that the stats show below (a click waits for the page to draw it still: slow in software WebGL)
            page.get_by_text("Instruments", exact=True).click(timeout=300_000)
            pump(viewer, 6.0)  # every tile of the paused texture arrives
            return page.screenshot(type="png", timeout=300_000)

        png = run_while(app, chrome.submit(shot), timeout_s=900)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(png)
        print(f"saved {path} (scene paused at t = {app.scene.time_s:.2f} s)")
        chrome.submit(lambda _: viewer.close()).result(timeout=30)
    finally:
        app.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 256])
    parser.add_argument("--seconds", type=float, default=10.0, help="wall seconds of streaming to measure")
    parser.add_argument("--tries", type=int, default=5, help="spots for the latency (at most %d)" % len(SPOTS_XY_MM))
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "measure_lab")
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--simple-lighting", action="store_true", help="the lab's simple lighting (no environment light, no shadows)")
    parser.add_argument("--half-resolution", action="store_true", help="draw the canvas at half resolution (?fixedDpr=0.5, as the tests)")
    parser.add_argument("--screenshot", type=Path, help="only save a screenshot of the lab to this PNG")
    parser.add_argument("--shot-at-s", type=float, default=4.3, help="scene time of the screenshot")
    args = parser.parse_args()
    if not browser.have_chromium():
        print(f"error: needs Debian chromium at {browser.CHROMIUM}", file=sys.stderr)
        return 2
    from sims.core import backend

    backend.init(args.arch)  # on this (main) thread, which then runs the lab's loop
    chrome = browser.BrowserThread()
    try:
        if args.screenshot:
            screenshot(args.screenshot, args, chrome)
            return 0
        results = [measure(size, args, chrome) for size in args.sizes]
    finally:
        chrome.close()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print("\n| texels | updates/s with tiles | tiles per update | kB per update | kB/s | browser frames/s (changed) | steps/s | move to visible burn: median (range) | texture changed, tiles published (medians) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        s, lat = r["stream"], r["latency"]
        rng = lat["range_visible_s"] or [float("nan")] * 2
        print(f"| {r['texture_size']}² | {s['updates_with_tiles_per_s']:.1f} | {s['tiles_per_update']:.2f} | {s['bytes_per_update'] / 1000:.1f} | "
              f"{s['bytes_per_s'] / 1000:.0f} | {s['browser_frames_per_s']:.1f} ({s['browser_changed_frames_per_s']:.1f}) | {s['steps_per_s']:.0f} | "
              f"{lat['median_visible_s'] or float('nan'):.2f} s ({rng[0]:.2f}-{rng[1]:.2f}) | {lat['median_texture_s'] or float('nan'):.2f} s, {lat['median_sent_s'] or float('nan'):.2f} s |")
    print(f"load average (1 min) at the end of each size: {[round(r['load_average_1min'], 1) for r in results]}")
    print(f"\nwrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
