"""examples/: every script runs as a user runs it (a fresh `python examples/NAME.py`, on the CPU), exits 0 and prints
its key figures, and those figures are finite and physically sensible. Every script in the folder is run here."""
import math
import os
import re
import subprocess
import sys

import pytest
from PIL import Image

from sims.scene.config import REPO_ROOT

EXAMPLES = REPO_ROOT / "examples"
TIMEOUT_S = 120  # each takes 4-12 s on 2 cores with a warm kernel cache; a cold cache compiles for up to a minute
NUMBER = r"([-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan|inf))"


def run_example(name: str, *args, cwd=REPO_ROOT) -> str:
    """stdout of `python examples/<name>.py --arch cpu ARGS` run in cwd; fails unless it exits 0. The repository is on
    PYTHONPATH as an editable install puts it (a checkout the suite runs in need not be installed)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")])))
    result = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), "--arch", "cpu", *map(str, args)], cwd=cwd,
                            env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert result.returncode == 0, f"{name} exited {result.returncode}:\n{result.stdout}\n{result.stderr[-3000:]}"
    return result.stdout


def figures(pattern: str, text: str) -> list[float]:
    """The numbers that pattern's NUMBER groups match in the first line matching it (NUMBER matches nan and inf too,
    so a non-finite figure fails its check rather than the search)."""
    match = re.search(pattern.replace("NUMBER", NUMBER), text)
    assert match, f"no line matching {pattern!r} in:\n{text}"
    values = [float(group) for group in match.groups()]
    assert all(math.isfinite(value) for value in values), f"not finite: {match.group(0)}"
    return values


def test_every_example_has_a_short_docstring_and_a_test():
    """Each script opens with a 2-6 line docstring that says how to run it, and a test below runs it."""
    tested = {name.removeprefix("test_") for name in globals() if name.startswith("test_")}
    for path in sorted(EXAMPLES.glob("*.py")):
        text = path.read_text()
        assert text.startswith('"""'), f"{path.name}: no docstring first"
        docstring = text[3:text.index('"""', 3)].strip("\n").splitlines()
        assert 2 <= len(docstring) <= 6, f"{path.name}: a docstring of {len(docstring)} lines"
        assert f"Run: python examples/{path.name}" in text, f"{path.name}: the docstring does not say how to run it"
        assert path.stem in tested, f"{path.name}: no test_{path.stem} in this file"


def test_burn_depth():
    out = run_example("burn_depth")
    burns = {}
    for tip_c in (120, 250):
        depth, area = figures(rf"tip +{tip_c} C: coagulation depth NUMBER mm, coagulated area NUMBER mm\^2", out)
        assert 0.1 < depth < 3.0, f"{tip_c} C: {depth} mm deep after 2 s"  # a few tenths of a mm to a mm in 2 s
        assert 1.0 < area < 50.0, f"{tip_c} C: {area} mm^2 under a 1.5 mm ball"  # the ball's contact disk is ~5 mm^2
        burns[tip_c] = depth, area
    assert burns[250][0] > burns[120][0] and burns[250][1] > burns[120][1], f"the hotter tip burned less: {burns}"


def test_bleed_accounting(tmp_path):
    out = run_example("bleed_accounting", "--out", tmp_path / "run")
    assert (tmp_path / "run" / "metrics.json").is_file() and (tmp_path / "run" / "final.png").is_file()
    spawned, on_surface, suctioned, left, dried = (
        figures(rf"{name} +NUMBER ml", out)[0]
        for name in ("spawned", "on the surface", "suctioned", "left the tissue", "dried"))
    assert spawned == pytest.approx(0.04 * 4.0, rel=0.02), "the vessel bleeds 0.04 ml/s for 4 s"
    assert min(on_surface, suctioned, left, dried) >= 0.0
    assert suctioned > 0.005, "the sucker took no blood"
    assert on_surface + suctioned + left + dried == pytest.approx(spawned, abs=2e-5), "the balance does not close"


def test_drill_session(tmp_path):
    """Run from another folder, which it leaves empty (it writes nothing)."""
    out = run_example("drill_session", cwd=tmp_path)
    assert list(tmp_path.iterdir()) == []
    assert "refused: tip_temperature_c: must be finite" in out
    reports = [figures(r"t = +NUMBER s .* vessel NUMBER ml/s, .* burn NUMBER mm deep on NUMBER mm\^2", line)
               for line in out.splitlines() if line.startswith("t = ")]
    assert len(reports) == 5, out
    (t0, rate0, depth0, _), (t_end, rate_end, depth_end, area_end) = reports[0], reports[-1]
    assert (t0, t_end) == (2.0, 4.5)
    assert rate0 == pytest.approx(0.04) and depth0 == 0.0, "the vessel bled at its rate before the ball came"
    assert 0.0 <= rate_end < 0.004, "the ball held on the vessel at 110 C for 1.4 s left it bleeding"
    assert 0.1 < depth_end < 3.0 and 0.5 < area_end < 50.0


def test_scene_in_python(tmp_path):
    out = run_example("scene_in_python", "--out", tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["bump.obj", "final.png", "scene.yaml"]
    with Image.open(tmp_path / "final.png") as image:
        assert image.size == (256, 256) and image.mode == "RGB"
    depth, area = figures(r"burn: NUMBER mm deep, coagulated area NUMBER mm\^2", out)
    assert 0.1 < depth < 3.0 and 1.0 < area < 50.0
    on_surface, blood_area, spawned = figures(r"blood: NUMBER ml on NUMBER mm\^2, of NUMBER ml spawned", out)
    assert spawned == pytest.approx(0.03 * 1.5, rel=0.02), "the cut bleeds 0.03 ml/s for 1.5 s"
    assert 0.5 * spawned < on_surface <= spawned and 10.0 < blood_area < 600.0  # the patch is 600 mm^2


def test_bench_section():
    out = run_example("bench_section")
    assert "## Damage: Omega timing against time step" in out and "| contact heating 37 -> 250 C |" in out
    worst = figures(r"worst error of the time to Omega = 1: NUMBER %", out)[0]
    assert 0.0 <= worst < 2.0, "the Arrhenius integration is off by more than the bench reports (under 0.5 %)"
