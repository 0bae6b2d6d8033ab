"""The benchmark command: analytic references on known values, and a quick run with finite numbers."""
import json
import math

import numpy as np
import pytest

from sims import analytic, params


def test_gaussian_reference_keeps_its_integral_and_spreads():
    x, y = np.meshgrid(np.linspace(-30, 30, 601), np.linspace(-30, 30, 601))
    r2 = x**2 + y**2
    area = (60 / 600) ** 2
    start = analytic.gaussian_on_plane(r2, 10.0, 2.0, 0.5, 0.0)
    later = analytic.gaussian_on_plane(r2, 10.0, 2.0, 0.5, 4.0)
    assert start.max() == pytest.approx(10.0)
    assert (later * area).sum() == pytest.approx((start * area).sum(), rel=1e-6)
    assert (later * r2 * area).sum() / (later * area).sum() / 2 == pytest.approx(4.0 + 2 * 0.5 * 4.0, rel=1e-4)


def test_arrhenius_reference_matches_the_published_liver_times():
    liver = params.TISSUE_PRESETS["liver"]
    at = lambda celsius: analytic.arrhenius_time_to_omega(1.0, celsius, liver["arrhenius_ln_a"], liver["activation_energy_j_mol"])
    assert at(60.0) == pytest.approx(3.46, rel=0.02)  # DESIGN section 7: about 3.4 s
    assert at(70.0) == pytest.approx(0.23, rel=0.1)


def finite_numbers(node):
    if isinstance(node, dict):
        return all(finite_numbers(value) for value in node.values())
    if isinstance(node, list):
        return all(finite_numbers(value) for value in node)
    if isinstance(node, (int, float)) and not isinstance(node, bool):
        return math.isfinite(node)
    return True


def test_quick_bench_writes_finite_numbers(tmp_path):
    from lab import bench

    bench.run(tmp_path, quick=True, arch="cpu")
    results = json.loads((tmp_path / "results.json").read_text())
    for section in ("cautery", "bleeding_throughput", "bleeding_density"):
        assert results[section], section
    assert finite_numbers(results)
    assert "Speed and accuracy" in (tmp_path / "report.md").read_text()
