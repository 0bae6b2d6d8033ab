"""Benchmarks: speed next to error. `python -m lab bench [--quick] [--only SECTION ...] --out DIR` writes
DIR/report.md, DIR/results.json and PNG plots. One module per section, each with run(quick) -> dict (JSON),
render(results) -> markdown lines and optionally plot(results, out_dir) -> PNG file names."""
import importlib
import json
import os
import time
from pathlib import Path

from sims.core import backend

# dambreak includes the SPlisHSPlasH peer where it installs. The CLI reads this list for every command, so the sections'
# imports wait for run(): `python -m lab run` imported lab.session and the bench's helpers through it
SECTIONS = ("heat", "heat_reference", "heat_layers", "damage", "bleeding", "dambreak", "bleeding_methods", "scenes", "activity", "startup")


def run(out_dir, quick: bool = False, arch: str = "auto", sections=SECTIONS) -> dict:
    """Run the named sections (all by default) and write the report; returns the results."""
    from tqdm import tqdm

    from lab.bench.common import cpu_ticks, device_description, stolen_share

    unknown = [name for name in sections if name not in SECTIONS]
    if unknown:
        raise ValueError(f"unknown bench section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = backend.init(arch)
    results = {"device": device_description(device), "quick": quick, "sections": list(sections)}
    started = time.perf_counter()
    bar = tqdm(sections, desc="bench", unit="section")
    for index, name in enumerate(bar):
        bar.set_postfix_str(name)
        if index:
            backend.restart()  # each section on a fresh runtime: one process's sections outgrow its 512 SNode trees
        module = importlib.import_module(f"lab.bench.{name}")
        section_start, ticks, load = time.perf_counter(), cpu_ticks(), os.getloadavg()[0]
        results[name] = module.run(quick)
        results[name]["load_before"] = load
        results[name]["wall_s"] = time.perf_counter() - section_start
        results[name]["cpu_stolen_share"] = stolen_share(ticks, cpu_ticks())
        results[name]["plots"] = module.plot(results[name], out)
    results["wall_s"] = time.perf_counter() - started
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "report.md").write_text(render(results))
    return results


def render(results: dict) -> str:
    device = results["device"]
    lines = [
        "# Speed and accuracy",
        "",
        f"Taken with Taichi {device['taichi']} on arch `{device['arch']}`, {device['processor']} ({device['machine']}), "
        f"{device['threads']} thread(s) of {device['cpu_count']} CPU(s), Python {device['python']}. "
        f"{'Quick run' if results['quick'] else 'Full run'}: {results['wall_s']:.0f} s.",
        "",
    ]
    for name in results["sections"]:
        module = importlib.import_module(f"lab.bench.{name}")
        lines += module.render(results[name])
        stolen, load = results[name].get("cpu_stolen_share"), results[name].get("load_before")
        if load is not None:  # other work on the machine when the section started (1-minute load average)
            lines += ["", f"Machine load before this section: {load:.2f} (1-minute load average; 1.0 is one core busy)."]
        if stolen is not None:  # a virtual machine's CPUs lent to other guests: wall times grow by about as much
            lines += ["", f"Machine load during this section: {100 * stolen:.0f} % of the CPU time went to other guests of the host (steal)."]
        lines += [f"![{plot}]({plot})" for plot in results[name].get("plots", [])]
        lines.append("")
    return "\n".join(lines) + "\n"
