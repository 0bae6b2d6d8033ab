"""One bench section run from Python: lab.bench.damage, quick (the simulated time to Omega = 1 against the exact
Arrhenius integral); prints its markdown table as `python -m lab bench` reports it, and the worst error (%). Each
section is a module of lab.bench with run(quick) -> dict (JSON) and render(results) -> markdown lines.

Run: python examples/bench_section.py [--section NAME] [--full] [--arch cpu|gpu|auto]
(damage, quick: about 10 s on 2 CPU cores once the kernels are cached; other sections take minutes)
"""
import argparse
import importlib
import json
import time

from lab.bench import SECTIONS
from sims.core import backend


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--section", default="damage", choices=SECTIONS)
    parser.add_argument("--full", action="store_true", help="the full section instead of the quick one")
    parser.add_argument("--arch", default="auto", choices=backend.ARCH_CHOICES)
    args = parser.parse_args()
    arch = backend.init(args.arch)  # a section builds its models on the running Taichi runtime (as lab.bench.run)
    section = importlib.import_module(f"lab.bench.{args.section}")
    started = time.perf_counter()
    results = section.run(quick=not args.full)
    print("\n".join(section.render(results)))
    print(f"\n{args.section} ({'full' if args.full else 'quick'}) on {arch}: {time.perf_counter() - started:.1f} s, "
          f"{len(json.dumps(results))} bytes of JSON results")
    if args.section == "damage":
        worst = max((abs(run["error_rel"]), case["name"], run["dt_s"])
                    for case in results["cases"] for run in case["runs"])
        print(f"worst error of the time to Omega = 1: {100 * worst[0]:.3f} % ({worst[1]}, dt {worst[2]:g} s)")


if __name__ == "__main__":
    main()
