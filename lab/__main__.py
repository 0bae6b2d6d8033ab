"""CLI: python -m lab serve [SCENE] | run SCENE --out DIR [...] | bench [--quick] [--only SECTION ...] --out DIR. Exit codes: 0 done, 2 bad input, 3 non-finite simulation."""
import sys

from lab import interrupts

if __name__ == "__main__":
    interrupts.install()  # first: a Ctrl-C during the imports below is reported by main(), in one line

import argparse
from pathlib import Path

from sims.core.backend import ARCH_CHOICES, ArchUnavailable
from sims.core.quoting import quote
from sims.scene.config import REPO_ROOT, ConfigError, load_scene_config
from sims.scene.params import SIMULATION

DEFAULT_SCENE = REPO_ROOT / "scenes" / "default.yaml"
MAX_RUN_S = SIMULATION["duration_s"].max  # --duration and --frames-every are capped as a scene's duration_s is


class _Parser(argparse.ArgumentParser):
    """Command-line errors in one line and exit 2, as every other bad input (argparse prints its usage first)."""

    def error(self, message):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def _seconds(text: str) -> float:
    """Simulated seconds in [0, MAX_RUN_S] (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {quote(text)}") from None
    if not 0 <= value <= MAX_RUN_S:  # NaN fails too
        raise argparse.ArgumentTypeError(f"expected seconds in [0, {MAX_RUN_S:g}] (as a scene's duration_s), got {quote(text)}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m lab", description="Surgical surface-effects lab: cautery burn marks in texture space.")
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="open the browser lab on a scene (default scenes/default.yaml)")
    serve.add_argument("scene", nargs="?", default=str(DEFAULT_SCENE), help="scene YAML file")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    serve.add_argument("--port", type=int, default=8080)
    serve.add_argument("--arch", choices=ARCH_CHOICES, default="auto", help="Taichi device: auto (GPU if present, else CPU), cpu or gpu")
    serve.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scene key, as for run (kept over rebuilds)")
    serve.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                       help="a web origin besides the lab's own whose pages may connect, e.g. https://lab.example.org behind a reverse proxy")
    run = commands.add_parser("run", help="run a scene headless and write metrics.json, final.png, state.npz")
    run.add_argument("scene", help="scene YAML file")
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--duration", type=_seconds, help="simulated seconds (default: the scene's duration_s)")
    run.add_argument("--frames-every", type=_seconds, metavar="S", help="also write frames/frame_NNNNN.png every S simulated seconds")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scene key, e.g. tissue.conductivity_w_mk=0.6 or instruments.0.tip_temperature_c=300")
    run.add_argument("--arch", choices=ARCH_CHOICES, default="auto", help="Taichi device: auto (GPU if present, else CPU), cpu or gpu")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    bench = commands.add_parser("bench", help="measure speed next to error and write DIR/report.md and DIR/results.json")
    bench.add_argument("--quick", action="store_true", help="fewer sizes and steps (about 3 minutes on 2 cores; the full run takes under 30)")
    # not lab.bench.SECTIONS here: importing lab.bench starts Taichi (2.7 s) before any command's arguments are checked
    bench.add_argument("--only", nargs="+", metavar="SECTION", help="run only these sections (a name it does not know lists them)")
    bench.add_argument("--out", required=True, help="output folder")
    bench.add_argument("--arch", choices=ARCH_CHOICES, default="auto", help="Taichi device")
    return parser


def main(argv=None) -> int:
    try:
        interrupts.arm()
        args = build_parser().parse_args(argv)
        interrupts.check()  # one that an import swallowed
    except KeyboardInterrupt:
        print("interrupted while starting; nothing done", file=sys.stderr)
        return 130
    command = {"serve": _serve, "run": _run, "bench": _bench}[args.command]
    where = getattr(args, "scene", None) or "bench"
    try:
        return command(args)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ArchUnavailable as exc:
        print(f"error: {where}: --arch: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # the run command says more where it can (_run)
        print(f"interrupted ({args.command})", file=sys.stderr)
        return 130


def _run(args) -> int:
    """Exit codes as in the module docstring, and 130 after Ctrl-C (one line on stderr; --out left as it was)."""
    try:
        config = load_scene_config(args.scene, args.set)  # before Taichi is imported (2 s): a bad file is told at once
        from lab import runner
        from sims.scene.assembly import Scene

        scene = Scene(config, arch=args.arch)
        interrupts.check()  # one that an import swallowed (trimesh, Taichi)
    except KeyboardInterrupt:
        print(f"interrupted while building the scene; {args.out} left as it was", file=sys.stderr)
        return 130
    try:
        metrics = runner.run(scene, args.out, args.duration, args.frames_every, progress=not args.quiet)
    except runner.RunInterrupted as exc:
        print(exc, file=sys.stderr)
        return 130
    except runner.SimulationDiverged as exc:
        print(f"error: {args.scene}: simulation: {exc}", file=sys.stderr)
        return 3
    except OSError as exc:
        print(f"error: {args.out}: --out: cannot write outputs: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"{metrics['scene']}: {metrics['steps']} steps in {metrics['wall_s']:.2f} s on {metrics['arch']} -> {args.out}")
    return 0


def _serve(args) -> int:
    from lab.web import app

    try:
        app.serve(args.scene, args.host, args.port, args.arch, overrides=args.set, allowed_origins=args.allow_origin)
    except OSError as exc:
        print(f"error: --port {args.port}: cannot serve on {args.host}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0


def _bench(args) -> int:
    from lab import bench

    unknown = [name for name in args.only or () if name not in bench.SECTIONS]
    if unknown:
        print(f"error: --only: unknown section(s) {', '.join(unknown)}; choose from {', '.join(bench.SECTIONS)}", file=sys.stderr)
        return 2
    bench.run(args.out, quick=args.quick, arch=args.arch, sections=args.only or bench.SECTIONS)
    print((Path(args.out) / "report.md").read_text())
    return 0


def exit_now(code: int) -> None:
    """End the process with `code` once its work is done, without the interpreter's teardown.

    Python's exit frees every module and object one by one, and Taichi's runtime and JIT with them: 0.2-0.3 s of a
    5 s idle run's 3.3 s, for nothing a user keeps. So the streams are flushed, the exit handlers run, Taichi's
    runtime is finalized (that is what writes newly compiled kernels into its offline cache) and the process ends."""
    import atexit
    import os

    from sims.core import backend

    interrupts.arm(False)  # done: a Ctrl-C now changes nothing, and must not print a traceback while Python exits
    backend.shutdown()
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    exit_now(main())
