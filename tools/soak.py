"""Soak the browser lab: browsers joining and leaving for a long time, plus a client pressing Reset (not a test).

    python tools/soak.py [--minutes 30] [--scene scenes/hemostasis.yaml] [--out runs/soak] [--seed 1]

The real lab (lab.web.app.LabApp, `python -m lab serve`'s app) runs the scene in this process, its loop on the main
thread. Three Debian chromium pages (each its own chromium driven by Playwright on a thread of its own,
testing.browser.BrowserThread; software WebGL, canvas at half resolution, simple lighting unless --default-lighting) each join, stay a random 20-90 s, leave,
and join again 2-10 s later (seeded). A fourth client, testing/raw_client.py's RawClient (a websocket client that
speaks viser's protocol, answering the sync requests as a page does), presses "Run > Reset" every ~60 s, so the
scene's script plays again and the texture keeps changing.

Every --every seconds (30) a line: elapsed time, this process's RSS (VmRSS of /proc/self/status: the server, the
Playwright client and the raw client; chromium runs in processes of its own), per browser the texture tile nodes the
stream delivered to it per second while it was connected (server side: TextureStream.client_stats) and the frames it
drew per second (page side: frames in which WebGL drew anything), and the errors so far: page errors and console
errors, server exceptions (tracebacks written to stderr: the lab's loop prints one and pauses the scene, which this
script then resumes; viser prints one for a failed callback), failed joins, and resets the raw client could not send.
At the end: OUT/results.json and OUT/soak.png (memory and updates/s over time).
"""
from __future__ import annotations

import argparse
import json
import random
import re
import statistics
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from testing import browser  # noqa: E402

BROWSERS = ("A", "B", "C")
STAY_S = (20.0, 90.0)        # a browser stays this long (uniform, seeded)
AWAY_S = (2.0, 10.0)         # and comes back after this long
RESET_EVERY_S = 60.0         # the raw client presses Reset about this often (+-10 %)
VIEWPORT = {"width": 960, "height": 600}
JOIN_TIMEOUT_S = 180.0       # a join (page load, canvas, the server counting the client)
SAMPLE_S = 1.0               # stream counters are read this often


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class ErrorLog:
    """Counts tracebacks written to stderr (the lab's loop and viser's callback pool print theirs there), uncaught
    thread exceptions and warnings; keeps the exception lines (the last line of a traceback) and the warnings."""

    EXCEPTION_LINE = re.compile(r"^[\w.]*(Error|Exception|Interrupt)(: .*)?$")

    def __init__(self):
        self.count = 0
        self.warnings = 0
        self.first_lines: list[str] = []
        self._stderr = sys.stderr
        self._lock = threading.Lock()
        sys.stderr = self
        self._excepthook = threading.excepthook
        threading.excepthook = self._thread_exception

    def write(self, text: str) -> int:
        with self._lock:
            self.count += text.count("Traceback (most recent call last)")
            for line in text.splitlines():
                if "Warning: " in line:
                    self.warnings += 1
                if self.EXCEPTION_LINE.match(line.strip()) or "Warning: " in line:
                    self.first_lines.append(line.strip()[:300])
            del self.first_lines[:-100]
        return self._stderr.write(text)

    def flush(self) -> None:
        self._stderr.flush()

    def _thread_exception(self, args) -> None:
        with self._lock:
            self.count += 1
            self.first_lines.append(f"thread {args.thread.name if args.thread else '?'}: {args.exc_type.__name__}: {args.exc_value}")
        self._excepthook(args)

    def close(self) -> None:
        sys.stderr = self._stderr
        threading.excepthook = self._excepthook


class Slot:
    """One of the three browsers: its page while it is there, and what it did."""

    def __init__(self, name: str):
        self.name = name
        self.chrome = None            # its chromium (testing.browser.BrowserThread)
        self.viewer = None            # testing.browser.Viewer while joined (used on its browser thread only)
        self.client_id = None
        self.job = None               # a join or leave in progress (Future)
        self.next_at = 0.0            # when it joins or leaves next (monotonic s)
        self.joins = self.leaves = self.failed_joins = 0
        self.tiles_seen = 0           # client_stats(client_id)["tiles_sent"] at the last sample
        self.tiles = 0                # tile nodes delivered in the current report interval
        self.connected_s = 0.0        # seconds connected in the current report interval
        self.frames_seen = None       # the page's drawn-frame counter at its last read, and when (monotonic s)
        self.frames_read_at = 0.0
        self.page_errors = 0          # over every visit
        self.errors_seen = 0          # of the current visit, counted already
        self.error_texts: list[str] = []


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--scene", type=Path, default=REPO / "scenes" / "hemostasis.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="scene override, as `python -m lab serve --set` (repeatable)")
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "soak")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--every", type=float, default=30.0, help="seconds between report lines")
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--default-lighting", action="store_true", help="the lab's default lighting (environment map, shadows)")
    parser.add_argument("--full-resolution", action="store_true", help="draw the pages' canvas at full resolution")
    args = parser.parse_args()
    if not browser.have_chromium():
        print(f"error: needs Debian chromium at {browser.CHROMIUM}", file=sys.stderr)
        return 2
    from lab.web.app import LabApp
    from sims.core import backend
    from testing.raw_client import RawClient

    errors = ErrorLog()
    backend.init(args.arch)  # on this (main) thread, which then runs the lab's loop
    app = LabApp(args.scene, "127.0.0.1", browser.free_port(), args.arch, overrides=args.overrides)
    app.set_simple_lighting(not args.default_lighting)
    port = app.server.get_port()
    url = f"http://127.0.0.1:{port}/" + ("" if args.full_resolution else "?fixedDpr=0.5")
    rng = random.Random(args.seed)
    slots = [Slot(name) for name in BROWSERS]
    for slot in slots:
        slot.chrome = browser.BrowserThread()
    for index, slot in enumerate(slots):
        slot.next_at = time.monotonic() + 5.0 * index  # joins spread over the first seconds
    print(f"soak: {args.scene.name} ({app.scene.arch}, built in {app.session.build_seconds[-1][1]:.1f} s) at {url}, "
          f"{args.minutes:g} min, seed {args.seed}", flush=True)

    raw = RawClient(port)
    raw.send_camera()
    deadline = time.monotonic() + 60.0
    while not app.server.get_clients() and time.monotonic() < deadline:  # viser counts it on its camera message
        time.sleep(0.05)
    if len(app.server.get_clients()) != 1:
        print("error: the raw client did not connect", file=sys.stderr)
        return 1
    known: set[int] = set(app.server.get_clients())  # every client id seen so far (each page visit gets a new one)
    joining: Slot | None = None  # joins go one at a time, so that the new client id is the joining page's
    join_started = 0.0
    samples: list[dict] = []
    state = {"resets": 0, "reset_failures": 0, "loop_errors": 0, "notices": [], "joins_unmatched": 0}
    started = time.monotonic()
    end = started + args.minutes * 60.0
    next_reset = started + RESET_EVERY_S * rng.uniform(0.9, 1.1)
    next_sample = started + SAMPLE_S
    next_report = started + args.every
    report_jobs: dict | None = None  # browser name -> the read of its page's counters, while a report is gathered
    report_started = 0.0
    rss_start = rss_mb()
    last_time_s = 0.0
    samples.append({"elapsed_s": 0.0, "rss_mb": rss_start, "browsers": {}, "errors": 0})
    print(f"{'elapsed':>8} {'RSS MB':>8}  " + "  ".join(f"{s.name}: tiles/s frames/s" for s in slots) + "  errors", flush=True)

    class Contexts:
        """The browser, remembering the contexts opened through it (to close them when a join fails half way)."""

        def __init__(self, instance):
            self.instance, self.opened = instance, []

        def new_context(self, **kwargs):
            self.opened.append(self.instance.new_context(**kwargs))
            return self.opened[-1]

    def join(slot: Slot):
        def action(instance):
            contexts = Contexts(instance)
            try:
                viewer = browser.Viewer(contexts, url, viewport=VIEWPORT, count_frames=True)
            except BaseException:
                for context in contexts.opened:
                    context.close()
                raise
            viewer.page.on("console", lambda message: message.type == "error" and viewer.errors.append(f"console: {message.text}"))
            return viewer
        return action

    def leave(viewer):
        def action(_):
            texts = list(viewer.errors)  # the page's errors since its last read count too
            viewer.close()
            return texts
        return action

    def read_page(viewer):
        def action(_):
            return int(viewer.page.evaluate("window.__drawnFrames || 0")), list(viewer.errors)
        return action

    def tick() -> bool:
        nonlocal joining, join_started, next_reset, next_sample, next_report, report_jobs, report_started, last_time_s
        now = time.monotonic()
        clients = app.server.get_clients()
        # the lab's loop pauses the scene after an exception (and prints it): count it and go on
        notice = app.session.notice
        if notice.startswith("simulation stopped"):
            state["loop_errors"] += 1
            state["notices"].append(f"{now - started:.0f} s: {notice}")
            app.set_running(True)  # (also clears that notice)
        if app.scene.time_s + 1e-9 < last_time_s:
            state["resets"] += 1
        last_time_s = app.scene.time_s
        # joins and leaves
        for slot in slots:
            if slot.job is not None:
                if not slot.job.done():
                    continue
                try:
                    result = slot.job.result()
                except Exception as exc:
                    result = None
                    slot.error_texts.append(f"{'join' if slot.viewer is None else 'leave'} failed: {exc}"[:300])
                if slot.viewer is None:  # a join finished
                    if result is None:
                        slot.failed_joins += 1
                        joining = None
                        known.update(clients)  # a half-joined page's id must not be taken for the next one's
                        slot.next_at = now + rng.uniform(*AWAY_S)
                    else:
                        slot.viewer, slot.joins = result, slot.joins + 1
                        slot.errors_seen, slot.frames_seen, slot.frames_read_at = 0, 0, now  # its counter starts at 0
                        slot.next_at = now + rng.uniform(*STAY_S)
                else:  # a leave finished
                    new_errors = (result or [])[slot.errors_seen:]
                    slot.page_errors += len(new_errors)
                    slot.error_texts += [text[:300] for text in new_errors]
                    slot.viewer, slot.client_id, slot.leaves = None, None, slot.leaves + 1
                    slot.next_at = now + rng.uniform(*AWAY_S)
                slot.job = None
            if slot is joining and slot.viewer is not None and slot.client_id is None:
                fresh = set(clients) - known
                if fresh:
                    slot.client_id = min(fresh)
                    known.add(slot.client_id)
                    slot.tiles_seen = 0
                    joining = None
                elif now - join_started > JOIN_TIMEOUT_S:
                    state["joins_unmatched"] += 1
                    joining = None
            if slot.job is None and now >= slot.next_at and now < end:
                if slot.viewer is None and joining is None:
                    joining, join_started = slot, now
                    slot.job = slot.chrome.submit(join(slot))
                elif slot.viewer is not None and slot is not joining:
                    slot.tiles += app.stream.client_stats(slot.client_id)["tiles_sent"] - slot.tiles_seen if slot.client_id is not None else 0
                    slot.tiles_seen = 0
                    slot.job = slot.chrome.submit(leave(slot.viewer))
        # the reset client
        if now >= next_reset and now < end:
            try:
                if not raw.click_button("Reset"):
                    state["reset_failures"] += 1
            except Exception as exc:
                state["reset_failures"] += 1
                state["notices"].append(f"{now - started:.0f} s: reset failed: {exc}")
            raw.glbs.clear()  # it keeps every GLB it got; this process's memory is what is measured
            next_reset = now + RESET_EVERY_S * rng.uniform(0.9, 1.1)
        if len(raw.glbs) > 100:
            raw.glbs.clear()
        # stream counters per browser
        if now >= next_sample:
            span = now - (next_sample - SAMPLE_S)
            for slot in slots:
                if slot.client_id is not None and slot.client_id in clients and slot.job is None:
                    total = app.stream.client_stats(slot.client_id)["tiles_sent"]
                    slot.tiles += total - slot.tiles_seen
                    slot.tiles_seen = total
                    slot.connected_s += span
            next_sample = now + SAMPLE_S
        # a report line: the pages' counters are read on their browser threads first (at most 20 s)
        if report_jobs is None and (now >= next_report or now >= end):
            report_jobs = {slot.name: slot.chrome.submit(read_page(slot.viewer)) for slot in slots
                           if slot.viewer is not None and slot.job is None}
            report_started = now
        if report_jobs is not None and (all(job.done() for job in report_jobs.values()) or now - report_started > 20.0):
            pages = {}
            for name, job in report_jobs.items():
                if job.done() and job.exception() is None:
                    pages[name] = job.result()
                else:  # the page is slow or going away: its frames count next time
                    job.cancel()
            report_jobs = None
            line = {"elapsed_s": now - started, "rss_mb": rss_mb(), "scene_time_s": app.scene.time_s, "browsers": {}}
            for slot in slots:
                frames, texts = pages.get(slot.name, (None, []))
                frames_per_s = None
                if frames is not None and now - slot.frames_read_at > 1.0:
                    frames_per_s = (frames - slot.frames_seen) / (now - slot.frames_read_at)
                    slot.frames_seen, slot.frames_read_at = frames, now
                new_errors = texts[slot.errors_seen:]
                slot.errors_seen = len(texts)
                slot.page_errors += len(new_errors)
                slot.error_texts += [text[:300] for text in new_errors]
                connected = slot.connected_s
                line["browsers"][slot.name] = {
                    "connected_s": round(connected, 1),
                    "tiles_per_s": slot.tiles / connected if connected > 1.0 else None,
                    "frames_per_s": frames_per_s,
                    "page_errors": slot.page_errors, "joins": slot.joins,
                }
                slot.tiles, slot.connected_s = 0, 0.0
            total_errors = (errors.count + sum(slot.page_errors for slot in slots) + sum(slot.failed_joins for slot in slots)
                            + state["reset_failures"] + state["joins_unmatched"])
            line["errors"] = total_errors
            line["server_tracebacks"] = errors.count
            line["warnings"] = errors.warnings
            samples.append(line)

            def fmt(value, digits=1):
                return "   -" if value is None else f"{value:4.{digits}f}"
            print(f"{line['elapsed_s']:7.0f}s {line['rss_mb']:8.1f}  "
                  + "  ".join(f"{name}: {fmt(b['tiles_per_s'])} {fmt(b['frames_per_s'])}   " for name, b in line["browsers"].items())
                  + f"  {total_errors}", flush=True)
            next_report = now + args.every
            if now >= end:
                return True
        return False

    try:
        app.run(until=tick, timeout_s=args.minutes * 60.0 + 600.0)
        for slot in slots:  # the pages leave
            if slot.job is not None:
                try:
                    slot.job.result(timeout=JOIN_TIMEOUT_S)
                except Exception:
                    pass
            if slot.viewer is not None:
                try:
                    slot.chrome.submit(leave(slot.viewer)).result(timeout=60)
                except Exception:
                    pass
    finally:
        raw.close()
        for slot in slots:
            slot.chrome.close()
        app.close()
        errors.close()
    summary = summarize(samples, slots, state, errors, rss_start)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                                       "samples": samples}, indent=2))
    plot(samples, args.out / "soak.png")
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out / 'results.json'} and {args.out / 'soak.png'}")
    return 0


def summarize(samples, slots, state, errors, rss_start) -> dict:
    rss = [s["rss_mb"] for s in samples]
    per_browser = {}
    for slot in slots:
        rates = [s["browsers"][slot.name]["tiles_per_s"] for s in samples[1:]
                 if slot.name in s["browsers"] and s["browsers"][slot.name]["tiles_per_s"] is not None
                 and s["browsers"][slot.name]["connected_s"] >= 10.0]
        frames = [s["browsers"][slot.name]["frames_per_s"] for s in samples[1:]
                  if slot.name in s["browsers"] and s["browsers"][slot.name]["frames_per_s"] is not None]
        per_browser[slot.name] = {
            "joins": slot.joins, "leaves": slot.leaves, "failed_joins": slot.failed_joins, "page_errors": slot.page_errors,
            "tiles_per_s_min": min(rates) if rates else None, "tiles_per_s_median": statistics.median(rates) if rates else None,
            "frames_per_s_min": min(frames) if frames else None,
            "frames_per_s_median": statistics.median(frames) if frames else None,
            "errors": slot.error_texts[:20],
        }
    return {
        "rss_mb_start": rss_start, "rss_mb_end": rss[-1], "rss_mb_max": max(rss), "rss_growth_mb": rss[-1] - rss_start,
        "rss_mb_after_first_report": rss[1] if len(rss) > 1 else None,
        "browsers": per_browser, "resets_seen": state["resets"], "reset_failures": state["reset_failures"],
        "server_tracebacks": errors.count, "warnings": errors.warnings, "loop_pauses_after_an_error": state["loop_errors"],
        "joins_without_a_client": state["joins_unmatched"],
        "errors_total": samples[-1].get("errors", 0), "notices": state["notices"][:50], "server_error_lines": errors.first_lines[:50],
    }


def plot(samples, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    minutes = [s["elapsed_s"] / 60.0 for s in samples]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    top.plot(minutes, [s["rss_mb"] for s in samples], "k.-")
    top.set_ylabel("server RSS (MB)")
    top.grid(alpha=0.3)
    for name in BROWSERS:
        points = [(m, s["browsers"][name]["tiles_per_s"]) for m, s in zip(minutes, samples)
                  if name in s.get("browsers", {}) and s["browsers"][name]["tiles_per_s"] is not None]
        if points:
            bottom.plot(*zip(*points), ".-", label=f"browser {name}")
    bottom.set_ylabel("tile nodes delivered / s\n(while connected)")
    bottom.set_xlabel("minutes")
    bottom.grid(alpha=0.3)
    bottom.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
