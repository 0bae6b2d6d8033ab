"""The run command: outputs, determinism, and one clear line for every class of bad input."""
import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from lab.__main__ import main
from sims.scene.config import REPO_ROOT

DEFAULT_SCENE = REPO_ROOT / "scenes" / "default.yaml"

SMALL_SCENE = {
    "name": "small",
    "mesh": "meshes/patch.obj",
    "texture_size": 64,
    "models": ["cautery"],
    "duration_s": 0.5,
    "instruments": [{
        "name": "ball", "shape": {"type": "ball", "radius_mm": 2.0}, "tip_temperature_c": 250,
        "position_mm": [0.0, 0.0, 1.5], "energized": True,
    }],
}


def write_scene(tmp_path: Path, scene=None, text: str | None = None) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(scene or SMALL_SCENE))
    return path


def run_cli(capsys, *args):
    code = main(["run", *map(str, args), "--quiet"])
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines()


def bad(scene_changes=None, delete=None):
    scene = json.loads(json.dumps(SMALL_SCENE))
    for dotted, value in (scene_changes or {}).items():
        node, *path = [scene] + dotted.split(".")
        for part in path[:-1]:
            node = node[int(part)] if isinstance(node, list) else node[part]
        node[int(path[-1]) if isinstance(node, list) else path[-1]] = value
    for key in delete or ():
        scene.pop(key)
    return scene


BAD_SCENES = {
    "unknown top-level key": (bad({"texture_sise": 64}), "texture_sise", "did you mean 'texture_size'"),
    "unknown nested key": (bad({"tissue": {"conductivty_w_mk": 0.5}}), "tissue.conductivty_w_mk", "unknown key"),
    "wrong type": (bad({"texture_size": "big"}), "texture_size", "expected a number"),
    "wrong container": (bad({"instruments": {"name": "ball"}}), "instruments", "expected a list"),
    "out of range": (bad({"tissue": {"conductivity_w_mk": 50.0}}), "tissue.conductivity_w_mk", "outside"),
    "not finite": (bad({"time_step_s": float("nan")}), "time_step_s", "finite"),
    "infinite vector": (bad({"instruments.0.position_mm": [0.0, float("inf"), 0.0]}), "instruments.0.position_mm", "finite"),
    "unknown model": (bad({"models": ["cautery", "smoke"]}), "models.1", "unknown value 'smoke'"),
    "model listed twice": (bad({"models": ["cautery", "cautery"]}), "models.1", "cautery is listed twice"),
    "unknown shape": (bad({"instruments.0.shape.type": "scalpel"}), "instruments.0.shape.type", "unknown value"),
    "missing required key": (bad(delete=["mesh"]), "mesh", "missing required key"),
    "missing mesh file": (bad({"mesh": "meshes/nowhere.obj"}), "mesh", "file not found"),
    "keyframes out of order": (bad({"instruments.0.path": [{"t_s": 1.0}, {"t_s": 0.5}]}), "instruments.0.path.1.t_s", "must increase"),
    "zero direction": (bad({"instruments.0.direction": [0, 0, 0]}), "instruments.0.direction", "zero vector"),
}


@pytest.mark.parametrize("case", list(BAD_SCENES), ids=list(BAD_SCENES))
def test_bad_scene_exits_2_with_one_line(tmp_path, capsys, case):
    scene, key, message = BAD_SCENES[case]
    path = write_scene(tmp_path, scene)
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: {path}: {key}: "), lines[0]
    assert message in lines[0]
    assert not (tmp_path / "out" / "state.npz").exists()


def test_yaml_syntax_error_names_the_line(tmp_path, capsys):
    path = write_scene(tmp_path, text="name: x\nmesh: meshes/patch.obj\ntissue: {preset: liver\n")
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {path}: line ") and "YAML syntax error" in lines[0]


def test_unreadable_mesh_file(tmp_path, capsys):
    (tmp_path / "broken.obj").write_bytes(b"\x00\x01 garbage \xff" * 10)
    path = write_scene(tmp_path, bad({"mesh": str(tmp_path / "broken.obj")}))
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {path}: mesh: ")


def test_open_instrument_mesh_is_refused(tmp_path, capsys):
    import trimesh

    box = trimesh.creation.box()
    open_box = trimesh.Trimesh(box.vertices, box.faces[2:])  # one side removed: no inside
    open_box.export(tmp_path / "sheet.obj")
    path = write_scene(tmp_path, bad({"instruments.0.shape": {"type": "mesh", "file": str(tmp_path / "sheet.obj")}}))
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {path}: instruments.0.shape.file: ") and "closed" in lines[0]


@pytest.mark.parametrize("override, key", [
    ("tissue.conductivity_w_mk=abc", "tissue.conductivity_w_mk"),
    ("instruments.5.tip_temperature_c=300", "instruments.5"),
    ("cautery.contact_distanse_mm=1", "cautery.contact_distanse_mm"),
    ("nokey", "nokey"),
])
def test_bad_override(tmp_path, capsys, override, key):
    path = write_scene(tmp_path)
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out", "--set", override)
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {path}: {key}"), lines[0]


def test_missing_scene_file(tmp_path, capsys):
    code, lines = run_cli(capsys, tmp_path / "nope.yaml", "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1 and "scene file not found" in lines[0]


def test_no_traceback_from_a_real_process(tmp_path):
    path = write_scene(tmp_path, bad({"tissue": {"conductivity_w_mk": -1.0}}))
    result = subprocess.run([sys.executable, "-m", "lab", "run", str(path), "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=REPO_ROOT)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()]
    assert "Traceback" not in result.stderr and "tissue.conductivity_w_mk" in result.stderr


def test_override_changes_the_run(tmp_path, capsys):
    path = write_scene(tmp_path)
    assert run_cli(capsys, path, "--out", tmp_path / "hot")[0] == 0
    assert run_cli(capsys, path, "--out", tmp_path / "cool", "--set", "instruments.0.tip_temperature_c=60")[0] == 0
    hot = json.loads((tmp_path / "hot" / "metrics.json").read_text())["cautery"]["max_temperature_c"]
    cool = json.loads((tmp_path / "cool" / "metrics.json").read_text())["cautery"]["max_temperature_c"]
    assert hot > 100.0 and 37.0 <= cool <= 60.0


def test_default_scene_writes_every_output_and_is_deterministic(tmp_path, capsys):
    outputs = []
    for run in ("a", "b"):
        out = tmp_path / run
        code, _ = run_cli(capsys, DEFAULT_SCENE, "--out", out, "--frames-every", "2", "--set", "texture_size=256")
        assert code == 0
        outputs.append(out)
    out = outputs[0]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("scene", "duration_s", "steps", "wall_s", "models", "finite", "cautery"):
        assert key in metrics
    assert metrics["finite"] is True and metrics["steps"] == 800
    assert metrics["cautery"]["coagulated_area_mm2"] > 20.0  # the scripted strokes really touch the patch
    assert metrics["cautery"]["charred_area_mm2"] > 0.0
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{i:05d}.png" for i in range(5)]
    from PIL import Image

    assert Image.open(out / "final.png").size == (256, 256)
    with np.load(out / "state.npz") as state:
        assert state["temperature_c"].shape == (256, 256) and state["texel_position_mm"].shape == (256, 256, 3)
        assert set(state.files) >= {"temperature_c", "damage_omega", "char", "texel_position_mm", "texel_mask"}
    assert (outputs[0] / "state.npz").read_bytes() == (outputs[1] / "state.npz").read_bytes()


def test_arch_auto_runs_without_a_gpu_and_gpu_says_why(tmp_path):
    """A fresh process: auto falls back to the CPU without crashing; gpu either runs on one or exits 2."""
    path = write_scene(tmp_path)
    auto = subprocess.run([sys.executable, "-m", "lab", "run", str(path), "--out", str(tmp_path / "auto"), "--arch", "auto"], capture_output=True, text=True, cwd=REPO_ROOT)
    assert auto.returncode == 0, auto.stderr
    assert json.loads((tmp_path / "auto" / "metrics.json").read_text())["arch"] in ("x64", "arm64", "cuda", "vulkan")
    gpu = subprocess.run([sys.executable, "-m", "lab", "run", str(path), "--out", str(tmp_path / "gpu"), "--arch", "gpu"], capture_output=True, text=True, cwd=REPO_ROOT)
    if gpu.returncode == 0:
        assert json.loads((tmp_path / "gpu" / "metrics.json").read_text())["arch"] in ("cuda", "vulkan")
    else:
        assert gpu.returncode == 2 and gpu.stderr.strip().splitlines() == [f"error: {path}: --arch: --arch gpu: no CUDA or Vulkan device found (use --arch auto or cpu)"]


def test_a_restarted_runtime_stays_on_its_device_and_starts_empty():
    """backend.restart() (the benches between scenes): the same device again, and fields made before it are gone."""
    import taichi as ti

    from sims.core import backend

    arch = backend.init("cpu")
    for _ in range(3):  # each field made after a launch is one more SNode tree of the runtime
        ti.field(ti.f32, 4).fill(1.0)
    trees = ti.lang.impl.get_runtime().prog.get_snode_tree_size()
    backend.restart()
    assert backend.started_arch() == arch
    after = ti.field(ti.f32, 4)
    after.fill(2.0)
    assert after.to_numpy().tolist() == [2.0] * 4 and ti.lang.impl.get_runtime().prog.get_snode_tree_size() < trees


def test_a_kernel_compiled_again_points_its_mistake_at_its_own_line():
    """Taichi's source-position text is remembered by place (sims.core.backend): a kernel compiled again for another field
    still marks its own line and name, and a kernel whose mistake sits at the same place in its body (same length of
    name, same columns) gets its own line, not the other's."""
    import taichi as ti

    from sims.core import backend

    backend.init("cpu")

    @ti.kernel
    def add_unknown(a: ti.template()):
        a[None] += unknown_amount  # noqa: F821

    @ti.kernel
    def scale_unknown(a: ti.template()):
        a[None] *= unknown_factor  # noqa: F821

    messages = []
    for kernel in (add_unknown, scale_unknown, add_unknown):
        with pytest.raises(ti.TaichiNameError) as error:
            kernel(ti.field(ti.f32, shape=()))
        messages.append(str(error.value))
    assert "a[None] += unknown_amount" in messages[0] and "^^^^^^^^^^^^^^" in messages[0]
    assert "a[None] *= unknown_factor" in messages[1] and "unknown_amount" not in messages[1]
    assert messages[2] == messages[0]


def test_non_finite_state_stops_the_run_naming_field_and_step(tmp_path, monkeypatch, capsys):
    from sims.scene.assembly import Scene

    original_step = Scene.step

    def poisoned_step(scene):
        original_step(scene)
        if scene.steps == 20:
            field = scene.cautery.temperature_c()
            field[10, 10] = np.nan
            scene.cautery.set_temperature(field)

    monkeypatch.setattr(Scene, "step", poisoned_step)
    path = write_scene(tmp_path)
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 3 and len(lines) == 1
    assert "temperature_c became non-finite at step 50" in lines[0]


# --- hostile and careless input (issue 38 point 8): one line, exit 2, at bounded cost -------------------------

def run_limited(*args, env=None) -> subprocess.CompletedProcess:
    """`python -m lab run ARGS --quiet` in a process held to 2 GB of address space (the inputs below once took 2-4 GB)."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    return subprocess.run([sys.executable, "-m", "lab", "run", *map(str, args), "--quiet"], capture_output=True, text=True,
                          cwd=REPO_ROOT, timeout=120, preexec_fn=limit, env=env)


def one_line(result: subprocess.CompletedProcess) -> str:
    """The one line a refused run printed on stderr (it exited 2, without a traceback)."""
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr[-2000:]
    return result.stderr.strip()


def yaml_bomb(levels: int = 9) -> str:
    """A YAML flow list of about 300 bytes whose aliases stand for 9**levels strings ("billion laughs")."""
    items = ["&a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    items += [f"&a{n} [" + ", ".join([f"*a{n - 1}"] * 9) + "]" for n in range(1, levels)]
    return "[" + ", ".join(items) + "]"


@pytest.mark.parametrize("where", ["name", "gravity_mm_s2", "--set"])
def test_yaml_bomb_is_refused_in_one_line(tmp_path, where):
    """Before: the validators put the whole value's repr in their message (4 GB in 40 s)."""
    if where == "--set":
        path, extra = write_scene(tmp_path), ["--set", f"name={yaml_bomb()}"]
    else:
        path, extra = write_scene(tmp_path, text=yaml.safe_dump(bad(delete=[where] if where == "name" else [])) + f"{where}: {yaml_bomb()}\n"), []
    line = one_line(run_limited(path, "--out", tmp_path / "out", *extra))
    assert "its aliases expand it to more than" in line and not (tmp_path / "out").exists()


@pytest.mark.parametrize("text, key, message", [
    ("gravity_mm_s2: " + "[" * 2000 + "]" * 2000, "line", "nested more than 32 levels deep"),  # was a RecursionError
    ("texture_size: " + "9" * 5000, "line", "cannot read this value"),  # was a ValueError (int of over 4300 digits)
    ("texture_size: " + "9" * 4000, "texture_size", "is outside [16, 2048]"),  # was an OverflowError (math.isfinite)
    ("texture_size: " + "x" * 100_000, "texture_size", "expected a number"),  # was quoted whole: a 100 kB line
], ids=["deep", "int of 5000 digits", "int of 4000 digits", "100 kB string"])
def test_malformed_values_are_refused_in_one_short_line(tmp_path, capsys, text, key, message):
    head = yaml.safe_dump(bad(delete=["texture_size"]))
    key = f"line {head.count(chr(10)) + 1}" if key == "line" else key  # the line of `text`
    path = write_scene(tmp_path, text=head + text + "\n")
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1 and len(lines[0]) < len(str(path)) + 200, lines
    assert lines[0].startswith(f"error: {path}: {key}: ") and message in lines[0]


def test_an_exponent_without_a_dot_is_a_number(tmp_path):
    """YAML 1.1 reads 1e-3 as text (it was refused as "got str '1e-3'"); YAML 1.2 and every user read a number."""
    from sims.scene.config import load_scene_config

    path = write_scene(tmp_path, text=yaml.safe_dump(bad(delete=["duration_s"])) + "duration_s: 5E-1\n")
    config = load_scene_config(path, ["time_step_s=1e-3", "instruments.0.tip_temperature_c=2.5e2"])
    assert (config["time_step_s"], config["duration_s"], config["instruments"][0]["tip_temperature_c"]) == (0.001, 0.5, 250.0)
    assert load_scene_config(path, ["name=1e3x"])["name"] == "1e3x"


def test_set_into_a_list_the_scene_lacks_says_so(tmp_path, capsys):
    """Was "expected a list, got dict" (the override made a mapping {"0": ...})."""
    code, lines = run_cli(capsys, write_scene(tmp_path), "--out", tmp_path / "out", "--set", "bleed_points.0.name=x")
    assert code == 2 and len(lines) == 1
    assert lines[0].endswith("bleed_points: --set: the scene has no bleed_points, so no item '0' to set"), lines


@pytest.mark.parametrize("special", ["fifo", "/dev/zero"])
def test_a_mesh_that_is_not_a_regular_file_is_refused_unread(tmp_path, capsys, special):
    """Was "file not found"; a FIFO is never opened (that would wait for a writer)."""
    if special == "fifo":
        os.mkfifo(tmp_path / "fifo")
        special = str(tmp_path / "fifo")
    code, lines = run_cli(capsys, write_scene(tmp_path), "--out", tmp_path / "out", "--set", f"mesh={special}")
    assert code == 2 and lines == [f"error: {tmp_path / 'scene.yaml'}: mesh: not a regular file: {special}"]


@pytest.mark.parametrize("option", ["--duration", "--frames-every"])
def test_seconds_beyond_a_scene_duration_are_refused_in_one_line(tmp_path, option):
    """--duration 1e308 ended in an OverflowError traceback, exit 1 (a scene's duration_s is capped at 3600 s)."""
    line = one_line(run_limited(write_scene(tmp_path), "--out", tmp_path / "out", option, "1e308"))
    assert line.startswith(f"error: python -m lab run: argument {option}: expected seconds in [0, 3600]")
