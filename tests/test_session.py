"""The lab session (lab.session) without a browser: what a trainer does through the GUI, done through the session's
public API, and everything a hostile client could send refused while the simulation goes on.

One session on the hemostasis scene at 64² texels for most tests (the drill: the sucker clears the field, the ball
electrode comes down on the vessel at 5 s and lifts at 7 s); the scene runs 4 times faster than real time.
"""
import math
import os
import shutil
import sys

import numpy as np
import pytest
import yaml

from lab.session import MAX_BLEED_POINTS, MAX_PENDING, REST_DEPTH_MM, LabSession
from sims.core.quoting import quote
from sims.scene.checked import Refused
from sims.scene.config import REPO_ROOT

HEMOSTASIS = REPO_ROOT / "scenes" / "hemostasis.yaml"
BALL = "ball_electrode"
TIP = f"instruments.{BALL}.tip_temperature_c"
HOSTILE_NUMBERS = [float("nan"), float("inf"), -float("inf"), "12", None, [1.0, 2.0], True]


@pytest.fixture(scope="module")
def session():
    lab = LabSession(HEMOSTASIS, "cpu", overrides=("texture_size=64",))
    lab.set_speed(4.0)
    return lab


def run_until(session, condition, timeout_s: float = 90.0) -> None:
    """Tick the session until condition() holds (the session paces itself at its speed x real time)."""
    import time

    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{getattr(condition, '__name__', 'condition')} did not hold in {timeout_s} s"
        session.tick()


def restart(session) -> None:
    session.reset()
    session.tick()
    assert session.scene.time_s < 0.1


def vessel_rate(session) -> float:
    return session.scene.bleed_rates()["vessel"]


# --- a slider changes its parameter and nothing else -----------------------------------------------

def test_the_drill_replays_at_another_tip_temperature_and_the_electrode_follows_its_script(session):
    """Hemostasis at 400 C stops the bleeding; the same drill replayed at 60 C does not (the tissue under a 60 C
    electrode needs seconds to coagulate). The slider never takes the electrode out of its script."""
    results = {}
    for tip_c in (400.0, 60.0):
        restart(session)
        session.set_parameter(TIP, tip_c)
        run_until(session, lambda: session.scene.time_s >= 5.5)
        tool = session.scene.instrument(BALL)
        pose, scripted = tool.pose_at(session.scene.time_s), tool.scripted_pose_at(session.scene.time_s)
        assert session.scene.held_tools() == [], "a slider took the tool over"
        assert np.allclose(pose.position_mm, scripted.position_mm) and pose.energized
        assert pose.tip_temperature_c == tip_c
        assert session.scene.tool_clearance_mm(BALL) < 0.0, "the electrode did not come down onto the vessel"
        run_until(session, lambda: session.scene.time_s >= 7.5)
        results[tip_c] = vessel_rate(session) / 0.04
        assert session.script_ended
    assert results[400.0] < 0.2, f"400 C left {results[400.0]:.0%} of the bleeding"
    assert results[60.0] > 0.8, f"60 C stopped {1 - results[60.0]:.0%} of the bleeding"


def test_reset_keeps_the_sliders_and_gives_every_tool_back_to_its_script(session):
    restart(session)
    session.set_parameter("tissue.conductivity_w_mk", 0.8)
    session.set_parameter(TIP, 123.0)
    session.take_over(BALL, [0.0, 0.0, 15.0])
    session.set_energized("sucker", True)
    session.tick()
    assert session.scene.held_tools() == ["sucker", BALL]
    session.reset()
    session.tick()
    assert session.scene.held_tools() == [] and session.scene.time_s < 0.1
    assert session.scene.config["tissue"]["conductivity_w_mk"] == 0.8
    assert session.scene.instrument(BALL).pose_at(0.0).tip_temperature_c == 123.0
    session.take_over(BALL, [0.0, 0.0, 15.0])
    session.tick()
    session.release(BALL)
    session.tick()
    assert session.scene.held_tools() == []


def test_a_session_that_waits_for_a_viewer_stays_at_t_0_until_one_joins(session):
    session.waiting_for_viewer = True
    restart(session)
    for _ in range(50):
        session.tick()
    assert session.scene.time_s == 0.0
    session.viewer_joined()
    run_until(session, lambda: session.scene.time_s > 0.1)


def test_replay_is_offered_once_the_script_has_ended(session):
    restart(session)
    assert not session.script_ended and session.scene.script_end_s() == pytest.approx(7.0)
    run_until(session, lambda: session.scene.time_s > 7.05)
    assert session.script_ended
    restart(session)
    assert not session.script_ended


# --- touch the tissue ------------------------------------------------------------------------------

def test_a_tool_resting_on_the_tissue_keeps_its_contact_depth_while_dragged(session):
    restart(session)
    session.set_resting(BALL, True)
    for x, y in [(-10.0, -5.0), (0.0, 0.0), (12.0, 8.0)]:
        session.take_over(BALL, [x, y, 25.0])
        session.tick()
        clearance = session.scene.tool_clearance_mm(BALL)
        assert clearance == pytest.approx(-REST_DEPTH_MM, abs=0.02), f"at ({x}, {y}): {clearance} mm"
        position = session.scene.instrument(BALL).pose_at(session.scene.time_s).position_mm
        assert position[:2] == pytest.approx([x, y]), "resting moves the tool along its axis only"
    session.set_resting(BALL, False)
    session.take_over(BALL, [0.0, 0.0, 25.0])
    session.tick()
    assert session.scene.tool_clearance_mm(BALL) > 15.0
    session.release(BALL)


def test_ticking_touch_the_tissue_lowers_the_tool_at_once(session):
    """No drag needed: the next tick rests the tool where it is, its tip REST_DEPTH_MM in; switched on and off before a
    tick, the tool stays with its script."""
    restart(session)
    session.set_resting(BALL, True)
    session.set_resting(BALL, False)
    session.tick()
    assert session.scene.held_tools() == []
    above = session.scene.instrument(BALL).pose_at(session.scene.time_s).position_mm
    assert session.scene.tool_clearance_mm(BALL) > 1.0, "the drill starts with the electrode above the tissue"
    session.set_resting(BALL, True)
    session.tick()
    assert session.scene.tool_clearance_mm(BALL) == pytest.approx(-REST_DEPTH_MM, abs=0.02)
    position = session.scene.instrument(BALL).pose_at(session.scene.time_s).position_mm
    assert position[:2] == pytest.approx(above[:2], abs=0.05) and position[2] < above[2] - 1.0
    session.set_resting(BALL, False)
    session.release(BALL)


# --- values from outside ---------------------------------------------------------------------------

def test_values_that_are_not_finite_numbers_are_refused_and_the_simulation_goes_on(session):
    restart(session)
    for value in HOSTILE_NUMBERS:
        for key in ("tissue.conductivity_w_mk", TIP, "time_step_s", "bleed_points.vessel.rate_ml_s", "texture_size"):
            with pytest.raises(Refused):
                session.set_parameter(key, value)
    vectors = [[math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [1e39, 0.0, 0.0], "abc", [1.0, 2.0], None]
    for vector in vectors:
        with pytest.raises(Refused):
            session.take_over(BALL, vector)
        with pytest.raises(Refused):
            session.add_bleed_point(vector)
        with pytest.raises(Refused):
            session.move_bleed_point("vessel", vector)
        with pytest.raises(Refused):
            session.add_bleed_point_at_click(vector, [0.0, 0.0, -1.0])
        if vector != [1e39, 0.0, 0.0]:  # a long direction is still a direction
            with pytest.raises(Refused):
                session.add_bleed_point_at_click([0.0, 0.0, 50.0], vector)
    for bad in ([0.0, 0.0, 0.0], [math.nan, 0.0, -1.0]):
        with pytest.raises(Refused):
            session.take_over(BALL, [0.0, 0.0, 10.0], direction=bad)
    with pytest.raises(Refused):
        session.take_over(BALL, [0.0, 0.0, 10.0], roll_deg=math.nan)
    for bad in ("no such tool", None, 3):
        with pytest.raises(Refused):
            session.set_energized(bad, True)
    with pytest.raises(Refused):
        session.set_energized(BALL, "yes")
    for name in ("best", "", None, 1, "fast "):
        with pytest.raises(Refused):
            session.set_quality(name)
    with pytest.raises(Refused):
        session.set_parameter("tissue.no_such_key", 1.0)
    assert session.set_parameter("tissue.conductivity_w_mk", 50.0) == 5.0, "a value out of range is put inside"
    assert session.set_speed(99.0) == 4.0
    with pytest.raises(Refused):
        session.set_speed(math.nan)
    steps = session.scene.steps
    run_until(session, lambda: session.scene.steps > steps + 20)
    assert session.scene.non_finite_field() is None and session.broken is None
    assert session.scene.held_tools() == []
    session.set_parameter("tissue.conductivity_w_mk", 0.52)


def test_a_live_change_past_the_heat_substep_cap_is_put_back(session, monkeypatch):
    import sims.heat.cautery

    restart(session)
    before = session.scene.config["tissue"]["conductivity_w_mk"]
    overrides = dict(session.overrides)
    monkeypatch.setattr(sims.heat.cautery, "MAX_SUBSTEPS", session.scene.cautery.explicit_substeps(0.01) - 1)  # a cap already reached
    session.set_parameter("tissue.conductivity_w_mk", 5.0)
    session.tick()
    assert session.scene.config["tissue"]["conductivity_w_mk"] == before and "substeps" in session.notice
    assert session.overrides == overrides
    monkeypatch.undo()
    steps = session.scene.steps
    run_until(session, lambda: session.scene.steps > steps + 5)


def test_no_file_outside_the_scenes_folder_is_opened_for_a_scene_switch(session, tmp_path):
    fifo = tmp_path / "scene.yaml"
    os.mkfifo(fifo)
    outside = ["/etc/passwd", "../../../etc/hostname", "scenes/../../../../etc/hostname", "scenes/../README.md",
               str(fifo), "/dev/zero", str(REPO_ROOT / "scenes" / ".." / "pyproject.toml"), "scenes/missing.yaml", "", 7, None]
    opened = []

    def audit(event, args):
        if event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
            opened.append(os.fspath(args[0]))

    sys.addaudithook(audit)  # (stays for the process; it only records while `watching`)
    messages = set()
    del opened[:]
    for name in outside:
        with pytest.raises(Refused) as caught:
            session.switch_scene(name)
        messages.add(str(caught.value).replace(quote(name), "NAME"))  # (quoted in 40 characters at most)
    watched = list(opened)
    assert not [path for path in watched if "etc" in path or "dev/zero" in path or str(tmp_path) in path or path.endswith(".toml")], watched
    assert len(messages) == 1, f"the answers tell files apart: {messages}"  # existing and missing files alike
    assert session.scene.name == "hemostasis"


# --- caps ------------------------------------------------------------------------------------------

def test_bleed_points_and_waiting_commands_are_capped(session):
    restart(session)
    added = refused = 0
    for index in range(40):
        try:
            session.add_bleed_point([-15.0 + index * 0.5, -5.0, 3.0])
            added += 1
        except Refused:
            refused += 1
        session.tick()
    assert len(session.scene.bleed_points) == MAX_BLEED_POINTS and refused == 40 - added > 0
    with pytest.raises(Refused):
        for _ in range(MAX_PENDING + 1):
            session.reset()
    session.tick()
    for _ in range(len(session.scene.bleed_points) - 1):
        session.remove_bleed_point()
    session.tick()
    assert [point.name for point in session.scene.bleed_points] == ["vessel"]


def test_every_change_waits_as_a_named_command_with_its_values(session):
    """What a front end asks waits in the queue as a lab.commands type holding the checked values (a reader follows a
    click to the scene by name); a slider dragged through many values waits once."""
    from lab import commands

    restart(session)
    tip_c = session.scene.parameter_value(TIP)
    session.set_energized(BALL, True)
    session.release(BALL)
    for value in (100.0, 150.0, 200.0):
        session.set_parameter(TIP, value)
    session.add_bleed_point([-15.0, -5.0, 3.0])
    session.single_step()
    session.reset()
    waiting = []
    while not session._commands.empty():
        waiting.append(session._commands.get_nowait())
    assert [type(command).__name__ for command in waiting] == ["SetEnergized", "Release", "SetParameters", "AddBleedPoint",
                                                              "SingleStep", "Reset"]
    assert all(isinstance(command, commands.Command) for command in waiting)
    assert waiting[0] == commands.SetEnergized(BALL, True) and waiting[1] == commands.Release(BALL)
    assert session._pending_parameters == {TIP: 200.0}
    for command in waiting:
        command.apply(session)
    assert session.scene.parameter_value(TIP) == 200.0 and session.single_steps == 1
    assert session.scene.bleed_points[-1].name != "vessel"
    session.remove_bleed_point()
    session.set_parameter(TIP, tip_c)
    session.tick()
    assert [point.name for point in session.scene.bleed_points] == ["vessel"] and session.scene.parameter_value(TIP) == tip_c


def test_a_field_that_becomes_non_finite_stops_the_scene_and_is_named(session):
    restart(session)
    cautery = session.scene.cautery
    for field in (cautery.temperature, cautery.surface_temperature):  # what a diverging model would leave
        field.fill(math.nan)
    run_until(session, lambda: session.broken is not None, timeout_s=30)
    assert session.broken == "temperature_c" and "temperature_c" in session.notice
    steps = session.scene.steps
    for _ in range(20):
        session.tick()
    assert session.scene.steps == steps, "a broken scene keeps stepping"
    session.reset()
    session.tick()
    assert session.broken is None and session.scene.non_finite_field() is None
    run_until(session, lambda: session.scene.steps > steps + 3, timeout_s=30)


# --- sessions of their own (last: a new session starts a fresh Taichi runtime, which ends the module's) -------

def test_unknown_quality_leaves_scene_switches_working(tmp_path):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for name in ("default.yaml", "bleeding.yaml"):
        shutil.copy(REPO_ROOT / "scenes" / name, scenes / name)
    lab = LabSession(scenes / "default.yaml", "cpu", overrides=("texture_size=32",), scenes_dir=scenes)
    with pytest.raises(Refused):
        lab.set_quality("ultra")
    lab.set_quality("fast")
    lab.switch_scene("scenes/bleeding.yaml")
    lab.tick()
    assert lab.scene.name == "liver_bleeding" and lab.builds == 2 and lab.notice == ""
    assert lab.quality == "fast" and lab.scene.surface.mask.shape == (256, 256)


def test_there_is_always_a_valid_scene(tmp_path, monkeypatch):
    """The running scene's file made invalid on disk, then a switch to a scene whose mesh fails and one whose build
    fails after the old runtime is gone: the session keeps (or rebuilds from memory) the last good scene and steps."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    shutil.copy(REPO_ROOT / "scenes" / "default.yaml", scenes / "a.yaml")
    (tmp_path / "broken.obj").write_text("v 0 0 0\nthis is not a mesh\n")
    (scenes / "b.yaml").write_text(yaml.safe_dump({"name": "b", "mesh": str(tmp_path / "broken.obj")}))
    shutil.copy(REPO_ROOT / "scenes" / "bleeding.yaml", scenes / "c.yaml")
    lab = LabSession(scenes / "a.yaml", "cpu", overrides=("texture_size=32",), scenes_dir=scenes)
    (scenes / "a.yaml").write_text("name: [this is not\n")
    lab.switch_scene("scenes/b.yaml")
    lab.tick()
    assert lab.scene.name == "liver_cautery" and "broken.obj" in lab.notice
    lab.back_to_scene_file()  # a.yaml is invalid on disk now
    lab.tick()
    assert lab.scene.name == "liver_cautery" and "a.yaml" in lab.notice

    import lab.session as session_module

    real_scene = session_module.Scene
    calls = []

    def failing_once(config, arch, inputs):
        calls.append(config["name"])
        if len(calls) == 1:
            from sims.scene.config import ConfigError

            raise ConfigError(config["scene_file"], "mesh", "the build failed after the old scene was dropped")
        return real_scene(config, arch, inputs)

    monkeypatch.setattr(session_module, "Scene", failing_once)
    lab.switch_scene("scenes/c.yaml")
    lab.tick()
    assert calls == ["liver_bleeding", "liver_cautery"], "the last good scene is rebuilt from memory"
    assert lab.scene.name == "liver_cautery" and "not switched" in lab.notice
    steps = lab.scene.steps
    run_until(lab, lambda: lab.scene.steps > steps + 5, timeout_s=30)


@pytest.mark.parametrize("scene_file", sorted(path.name for path in (REPO_ROOT / "scenes").glob("*.yaml")))
def test_every_tool_a_scene_shows_starts_in_view(scene_file):
    """Every tool's body, at t = 0, inside a 1280 x 720 browser view from the lab's initial camera (viser's 75 degree
    field of view), left of the GUI panel (the right 360 px) - the spare sucker of a bleeding scene included."""
    from lab.web.app import initial_view, instrument_mesh
    from sims.scene.instruments import local_frame
    from testing.browser import project

    lab = LabSession(REPO_ROOT / "scenes" / scene_file, "cpu", overrides=("texture_size=32",))
    camera, look_at = initial_view(lab.scene.surface)
    assert lab.scene.instruments, "a scene without tools"
    for tool in lab.scene.instruments:
        pose = tool.pose_at(0.0)
        body = instrument_mesh(tool.shape).vertices @ local_frame(pose.direction, pose.roll_deg) + pose.position_mm
        xy = project(body, camera, look_at, math.radians(75.0), (1280, 720))
        assert xy[:, 0].min() >= 0 and xy[:, 0].max() <= 1280 - 360 and xy[:, 1].min() >= 0 and xy[:, 1].max() <= 720, (
            f"{tool.name} spans x {xy[:, 0].min():.0f}..{xy[:, 0].max():.0f}, y {xy[:, 1].min():.0f}..{xy[:, 1].max():.0f} px")
