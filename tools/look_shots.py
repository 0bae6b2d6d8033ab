"""Screenshots of the lab's look in Debian chromium, for the docs (not part of the test suite).

    python tools/look_shots.py --scene scenes/bleeding.yaml --at 6 --out docs/look/bleeding [--repo DIR]

`python -m lab serve`'s LabApp runs the scene to --at simulated seconds and pauses; the browser (Playwright, software
WebGL through SwiftShader, 1280 x 800) then shows it from each camera of --views (azimuths in degrees about the look-at
point, all at the same elevation and distance), and the canvas of each is saved as OUT_az<deg>.png. The instruments'
gizmos and the panel are left out of the picture. --repo runs another checkout of the lab (e.g. an older commit, for a
before and after) with this script.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--at", type=float, default=4.0, help="simulated seconds before the pictures")
    parser.add_argument("--out", type=Path, required=True, help="path prefix of the PNGs")
    parser.add_argument("--views", type=float, nargs="+", default=[-20.0, 25.0], help="camera azimuths, degrees")
    parser.add_argument("--look-at", type=float, nargs=3, default=None, help="mm (default: the mesh's centre)")
    parser.add_argument("--distance", type=float, default=None, help="camera distance, mm (default: 0.9 x the mesh's size)")
    parser.add_argument("--elevation", type=float, default=50.0, help="degrees above the tangent plane")
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout of the lab to run")
    args = parser.parse_args()
    sys.path.insert(0, str(args.repo.resolve()))
    sys.path.insert(1, str(REPO))
    import lab
    from lab.web.app import LabApp
    from sims.core import backend
    from testing import browser
    from tools.measure_lab import HIDE_NOTICE_JS, canvas_box, pump, run_while, the_client

    print(f"the lab from {Path(lab.__file__).parent.parent}", flush=True)
    backend.init("cpu")
    chrome = browser.BrowserThread()
    app = LabApp(args.repo.resolve() / args.scene, "127.0.0.1", browser.free_port(), "cpu")
    try:
        viewer = run_while(app, chrome.submit(lambda b: browser.Viewer(b, f"http://127.0.0.1:{app.server.get_port()}/",
                                                                         viewport={"width": 1280, "height": 800})), timeout_s=300)
        client = the_client(app, chrome, viewer)
        for view in app.tool_views.values():
            view["gizmo"].visible = False
        for view in getattr(app, "point_views", {}).values():
            view[0].visible = False
        app.session.reset()
        run_while(app, chrome.submit(lambda _: pump(viewer, 0.5)), until=lambda: app.scene.time_s >= args.at, timeout_s=600)
        app.set_running(False)
        vertices = app.scene.surface.vertices_mm
        centre = np.array(args.look_at) if args.look_at else (vertices.min(axis=0) + vertices.max(axis=0)) / 2
        distance = args.distance or 0.9 * float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        for azimuth in args.views:
            a, e = np.radians(azimuth), np.radians(args.elevation)
            offset = distance * np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
            client.camera.position = tuple(float(v) for v in centre + offset)  # position first: it keeps the orientation
            client.camera.look_at = tuple(float(v) for v in centre)

            def shot(_):
                page = viewer.page
                page.evaluate(HIDE_NOTICE_JS)
                pump(viewer, 8.0)  # every tile of the paused texture and the new view drawn
                box = canvas_box(page)
                panel = 330  # viser's control panel on the right
                return page.screenshot(type="png", timeout=300_000,
                                       clip={"x": box["x"], "y": box["y"], "width": box["width"] - panel, "height": box["height"]})

            png = run_while(app, chrome.submit(shot), timeout_s=900)
            path = args.out.parent / f"{args.out.name}_az{azimuth:+.0f}.png"
            path.write_bytes(png)
            print(f"saved {path} (t = {app.scene.time_s:.2f} s, azimuth {azimuth:+.0f} deg)", flush=True)
        chrome.submit(lambda _: viewer.close()).result(timeout=30)
    finally:
        app.close()
        chrome.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
