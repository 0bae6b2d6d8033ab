"""The scene parameter table of docs/guide/scenes.md, made from the parameter specs in sims/scene/params.py.

    python tools/param_table.py           print the table (markdown)
    python tools/param_table.py --write   put it between the markers in docs/guide/scenes.md
    python tools/param_table.py --check   exit 1, with one line, when the file's table is not the generated one

Imports only sims.scene.params (no Taichi), so it runs in a fraction of a second.
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run as `python tools/param_table.py` from a clone that is not installed
    sys.path.insert(0, str(REPO_ROOT))

from sims.scene import params  # noqa: E402

DOC = REPO_ROOT / "docs" / "guide" / "scenes.md"
BEGIN = "<!-- params:begin -->"
END = "<!-- params:end -->"

# (heading, scene key prefix, table name in sims.scene.params). N: an item's index in its list (--set
# instruments.0.tip_temperature_c=300); the lab's sliders and LabSession name tools and points instead
# (instruments.<tool>.tip_temperature_c). The prefixes are those of the scene schema (sims/scene/config.py).
GROUPS = (
    ("Simulation", "", "SIMULATION"),
    ("Tissue (`tissue.preset` sets them all; a value given here wins)", "tissue.", "TISSUE"),
    ("Cautery", "cautery.", "CAUTERY"),
    ("Instruments", "instruments.N.", "INSTRUMENT"),
    ("Instrument shapes (the keys of the shape's type)", "instruments.N.shape.", "SHAPE"),
    ("Suction (an instrument's `suction:`)", "instruments.N.suction.", "SUCTION"),
    ("Bleeding, height field (`bleeding.method: height_field`, the default)", "bleeding.", "HEIGHT_FIELD"),
    ("Bleeding, particles (`bleeding.method: particles`)", "bleeding.", "BLEEDING"),
    ("Look", "look.", "LOOK"),
    ("Bleed points", "bleed_points.N.", "BLEED_POINT"),
)

# Units as a reader writes them (the specs keep ASCII).
_UNIT_WORDS = {"": "-", "x": "×", "x lattice": "× lattice density", "x rest": "× rest density", "C": "°C"}
_POWERS = {"^2": "²", "^3": "³"}


def unit_text(unit: str) -> str:
    """A spec's unit as users read it: °C, kg/m³, W/(m² K), ×."""
    if unit in _UNIT_WORDS:
        return _UNIT_WORDS[unit]
    text = re.sub(r"(?<![A-Za-z])C(?![A-Za-z])", "°C", unit)  # "1/(s C)" -> "1/(s °C)"
    for ascii_power, superscript in _POWERS.items():
        text = text.replace(ascii_power, superscript)
    return text


def help_text(text: str) -> str:
    """A spec's help for a table cell: powers as superscripts, no pipe characters."""
    for ascii_power, superscript in _POWERS.items():
        text = text.replace(ascii_power, superscript)
    return text.replace("|", "/")


def number_text(value: float) -> str:
    """1079, 0.0036, 100,000, 1e-4: short and exact enough to read (the specs hold the exact values)."""
    if value == int(value) and abs(value) < 1e7:
        return f"{int(value):,}" if abs(value) >= 10_000 else str(int(value))
    text = f"{value:.4g}"
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}e{int(exponent)}" if e else text


def default_text(spec: params.ParamSpec) -> str:
    if spec.unit == "ln(1/s)":  # the log of a rate that overflows float32: give the rate as well
        return f"{number_text(spec.default)} (A = {number_text(float(f'{math.exp(spec.default):.3g}'))} 1/s)"
    return number_text(spec.default)


def range_text(spec: params.ParamSpec) -> str:
    text = f"{number_text(spec.min)}{' to ' if spec.min < 0 else '–'}{number_text(spec.max)}"
    return text + ", whole numbers" if spec.integer else text


def spec_tables() -> dict[str, dict[str, params.ParamSpec]]:
    """Every table of ParamSpecs in sims.scene.params, by its name there."""
    return {name: value for name, value in vars(params).items()
            if isinstance(value, dict) and value and all(isinstance(spec, params.ParamSpec) for spec in value.values())}


def table_markdown() -> str:
    """The markdown of every scene key's parameter: key, unit, default, range, help, grouped as GROUPS says.
    Raises RuntimeError when sims.scene.params has a table GROUPS does not place (so the docs cannot fall behind)."""
    tables = spec_tables()
    unplaced = sorted(set(tables) - {table for _, _, table in GROUPS})
    if unplaced:
        raise RuntimeError(f"tools/param_table.py: GROUPS places no scene key prefix for sims.scene.params.{', '.join(unplaced)}")
    lines = []
    for heading, prefix, table in GROUPS:
        lines += [f"**{heading}**", "", "| key | unit | default | range | what it does |", "|---|---|---|---|---|"]
        for name, spec in tables[table].items():
            lines.append(f"| `{prefix}{name}` | {unit_text(spec.unit)} | {default_text(spec)} | {range_text(spec)} | "
                         f"{help_text(spec.help)} |")
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


def _span(text: str) -> tuple[int, int]:
    """Start and end of the text between the markers; ValueError when they are missing or out of order."""
    begin, end = text.find(BEGIN), text.find(END)
    if begin < 0 or end < 0 or end < begin:
        raise ValueError(f"{BEGIN} ... {END} not found in order")
    return begin + len(BEGIN), end


def table_in(text: str) -> str:
    """The table between the markers of a document's text (without the blank lines around it)."""
    start, end = _span(text)
    return text[start:end].strip("\n") + "\n"


def with_table(text: str, table: str) -> str:
    """The document's text with `table` between its markers, a blank line on either side."""
    start, end = _span(text)
    return text[:start] + "\n\n" + table.strip("\n") + "\n\n" + text[end:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    action = parser.add_mutually_exclusive_group()
    action.add_argument("--write", action="store_true", help=f"replace the table in {DOC.relative_to(REPO_ROOT)}")
    action.add_argument("--check", action="store_true", help="exit 1 when the table there differs from the generated one")
    args = parser.parse_args(argv)
    table = table_markdown()
    if not (args.write or args.check):
        sys.stdout.write(table)
        return 0
    where = DOC.relative_to(REPO_ROOT)
    try:
        text = DOC.read_text(encoding="utf-8")
        current = table_in(text)
    except (OSError, ValueError) as exc:
        print(f"error: {where}: {exc}", file=sys.stderr)
        return 2
    if args.check:
        if current != table:
            print(f"{where}: the parameter table differs from sims/scene/params.py; run python tools/param_table.py --write")
            return 1
        return 0
    if current != table:
        DOC.write_text(with_table(text, table), encoding="utf-8")
        print(f"{where}: parameter table written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
