"""The benchmark command: analytic references on known values, and a quick run with finite numbers."""
import importlib.util
import json
import math

import numpy as np
import pytest

from lab.reference import analytic
from sims.scene import params


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
    assert at(60.0) == pytest.approx(3.46, rel=0.02)  # docs/model/heat.md "Damage": 3.46 s
    assert at(70.0) == pytest.approx(0.23, rel=0.1)


def finite_numbers(node):
    if isinstance(node, dict):
        return all(finite_numbers(value) for value in node.values())
    if isinstance(node, list):
        return all(finite_numbers(value) for value in node)
    if isinstance(node, (int, float)) and not isinstance(node, bool):
        return math.isfinite(node)
    return True


def test_arrhenius_under_relaxation_reduces_to_constant_temperature_and_is_monotone():
    liver = params.TISSUE_PRESETS["liver"]
    ln_a, ea = liver["arrhenius_ln_a"], liver["activation_energy_j_mol"]
    constant = analytic.arrhenius_time_to_omega(1.0, 70.0, ln_a, ea)
    assert analytic.arrhenius_time_under_relaxation(1.0, 70.0, 70.0, 2.0, ln_a, ea) == pytest.approx(constant, rel=1e-8)
    # heating from 37 C toward 70 C takes longer than sitting at 70 C, and a faster approach takes less time
    slow = analytic.arrhenius_time_under_relaxation(1.0, 37.0, 70.0, 1.0, ln_a, ea)
    fast = analytic.arrhenius_time_under_relaxation(1.0, 37.0, 70.0, 10.0, ln_a, ea)
    assert constant < fast < slow
    # Omega(t) is additive over time and increasing
    omega = analytic.arrhenius_omega_under_relaxation(np.array([0.5, 1.0, 2.0]), 37.0, 80.0, 1.0, ln_a, ea)
    assert np.all(np.diff(omega) > 0)
    assert analytic.arrhenius_omega_under_relaxation(1.0, 37.0, 80.0, 1.0, ln_a, ea) == pytest.approx(omega[1], rel=1e-9)


def test_arrhenius_threshold_counts_only_the_time_above_it():
    """Heating from 37 C toward 80 C crosses 43 C at t* = ln((80 - 37) / (80 - 43)) / rate: with the threshold, Omega(t)
    is the plain integral from t* on, i.e. Omega_plain(t) - Omega_plain(t*)."""
    liver = params.TISSUE_PRESETS["liver"]
    ln_a, ea, rate = liver["arrhenius_ln_a"], liver["activation_energy_j_mol"], 1.5
    crossing = math.log((80.0 - 37.0) / (80.0 - 43.0)) / rate
    times = np.array([0.05, crossing, 0.5, 1.0, 3.0])
    plain = analytic.arrhenius_omega_under_relaxation(times, 37.0, 80.0, rate, ln_a, ea)
    plain_at_crossing = analytic.arrhenius_omega_under_relaxation(crossing, 37.0, 80.0, rate, ln_a, ea)
    above = analytic.arrhenius_omega_under_relaxation(times, 37.0, 80.0, rate, ln_a, ea, threshold_c=43.0)
    assert above[0] == 0.0 and above[1] == 0.0
    assert above[2:] == pytest.approx(plain[2:] - plain_at_crossing, rel=1e-8)
    # cooling from 80 C toward 37 C: damage stops for good once T falls below 43 C
    cooled = math.log((80.0 - 37.0) / (43.0 - 37.0)) / rate
    late = analytic.arrhenius_omega_under_relaxation(np.array([cooled, 5.0]), 80.0, 37.0, rate, ln_a, ea, threshold_c=43.0)
    assert late[1] == pytest.approx(late[0], rel=1e-12) and late[0] > 0
    assert analytic.arrhenius_time_to_omega(1.0, 40.0, ln_a, ea, threshold_c=43.0) == math.inf
    assert analytic.arrhenius_time_to_omega(1.0, 60.0, ln_a, ea, threshold_c=43.0) == analytic.arrhenius_time_to_omega(1.0, 60.0, ln_a, ea)


def test_pareto_front_keeps_only_runs_nothing_beats():
    from lab.bench.heat import pareto

    rows = [{"ms_per_simulated_s": c, "max_error_rel": e, "id": i} for i, (c, e) in enumerate([(1, 0.5), (2, 0.6), (3, 0.1), (4, 0.1), (5, 0.01)])]
    assert [row["id"] for row in pareto(rows)] == [0, 2, 4]


def test_quick_bench_writes_finite_numbers_and_plots_for_every_section(tmp_path):
    from lab import bench

    bench.run(tmp_path, quick=True, arch="cpu")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["sections"] == list(bench.SECTIONS)
    for section in bench.SECTIONS:
        assert results[section], section
        for plot in results[section]["plots"]:
            assert (tmp_path / plot).stat().st_size > 10_000, plot
    assert results["heat"]["plane"] and results["damage"]["cases"] and results["bleeding"]["throughput"] and results["scenes"]["scenes"]
    scenes = {row["scene"]: row for row in results["scenes"]["scenes"]}
    assert set(scenes) == {"default.yaml", "bleeding.yaml", "hemostasis.yaml"}
    assert scenes["bleeding.yaml"]["ms_per_simulated_s"]["cautery"] == 0.0  # a model the scene does not name costs nothing
    assert scenes["default.yaml"]["ms_per_simulated_s"]["bleeding"] == 0.0
    assert scenes["hemostasis.yaml"]["ms_per_simulated_s"]["cautery"] > 0.0 and scenes["hemostasis.yaml"]["ms_per_simulated_s"]["bleeding"] > 0.0
    assert finite_numbers(results)
    if importlib.util.find_spec("pysplishsplash") is not None:  # CI installs the peer extra: its dam break runs beside ours
        peer = results["dambreak"]["peer"]
        assert peer["available"] and peer["runs"], peer.get("reason")
    activity = {row["case"]: row for row in results["activity"]["rows"]}
    assert set(activity) == {"idle", "one tool", "two tools", "one bleed point", "four bleed points"}
    assert activity["idle"]["hot_tiles_awake"] == 0 and activity["two tools"]["hot_tiles_awake"] > 0
    assert activity["idle"]["blood_ml"] == 0.0 < activity["four bleed points"]["blood_ml"]
    assert 0.0 < results["activity"]["idle_lab"]["cpu_share"]
    methods = {(row["case"], row["method"]): row for row in results["bleeding_methods"]["cases"]}
    hollow = {m["quantity"]: m["error_rel"] for m in methods[("hollow", "height_field")]["measures"]}
    assert all(abs(error) < 0.05 for error in hollow.values()), "the height field pools as a level pool"
    assert abs(methods[("incline", "height_field")]["measures"][0]["error_rel"]) < 0.05, "Nusselt's film"
    assert all(point["ms_per_simulated_s"] > 0 for run in results["bleeding_methods"]["growth"] for point in run["points"])
    sphere = results["heat"]["sphere"]
    assert {row["scheme"] for row in sphere} == {"explicit", "implicit"} and all(row["seam_links"] > 0 for row in sphere)
    assert all(abs(row["rate_error_rel"]) < 0.02 for row in sphere), "heat across UV seams: the sphere's l = 1 mode"
    report = (tmp_path / "report.md").read_text()
    assert "Speed and accuracy" in report and results["device"]["arch"] in report
    assert "![heat_pareto.png](heat_pareto.png)" in report
