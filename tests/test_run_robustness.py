"""Headless runs against bad geometry, absurd substep counts, Ctrl-C, failed writes and a corrupt atlas cache."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from lab.__main__ import main
from lab.reference.meshes import plane_mesh
from sims.heat.cautery import MAX_SUBSTEPS
from sims.scene.config import REPO_ROOT
from sims.surface.texels import MAX_MESH_BYTES, MAX_MESH_ELEMENTS
from testing.helpers import interruptible
from tests.test_cli import bad, one_line, run_cli, run_limited, write_scene


def write_obj(path: Path, vertices, faces, uv=None) -> Path:
    """A plain OBJ (1-based faces; `vt` and v/vt faces when uv is given), written exactly as given."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    if uv is not None:
        lines += [f"vt {u!r} {v!r}" for u, v in np.asarray(uv, np.float64).tolist()]
    for face in np.asarray(faces) + 1:
        lines.append("f " + " ".join(f"{i}/{i}" if uv is not None else str(i) for i in face))
    path.write_text("\n".join(lines) + "\n")
    return path


def mesh_scene(tmp_path: Path, mesh_path: Path, **changes) -> Path:
    return write_scene(tmp_path, bad({"mesh": str(mesh_path), **changes}))


def outputs(folder: Path) -> dict:
    """Every file under folder: relative path -> bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def leftovers(out: Path) -> list[str]:
    """Temporary folders of runs into `out` still beside it."""
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


def sphere_obj(tmp_path: Path, x0) -> Path:
    """An icosphere of radius 5 mm without UVs (so it goes to xatlas), its first vertex at x = x0."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    vertices = sphere.vertices.copy()
    vertices[0, 0] = x0
    return write_obj(tmp_path / "sphere.obj", vertices, sphere.faces)


def test_vertex_at_1e39_is_refused_at_once_in_a_real_process(tmp_path):
    """Before the check xatlas never returned on this mesh (float32 infinity)."""
    path = mesh_scene(tmp_path, sphere_obj(tmp_path, 1e39))
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "lab", "run", str(path), "--out", str(tmp_path / "out"), "--quiet"],
                            capture_output=True, text=True, cwd=REPO_ROOT, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [result.stderr.strip()] and "Traceback" not in result.stderr
    assert result.stderr.startswith(f"error: {path}: mesh: {tmp_path / 'sphere.obj'}: ")
    assert "1e+39 mm found; meshes are in millimetres" in result.stderr
    assert time.perf_counter() - start < 60 and not (tmp_path / "out").exists()


def test_non_finite_vertex_is_refused_in_one_line(tmp_path, capsys):
    path = mesh_scene(tmp_path, sphere_obj(tmp_path, float("nan")))
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {path}: mesh: ") and "1 of 42 vertices are not finite" in lines[0]


def sliver_plane(tmp_path: Path, width_mm: float) -> Path:
    """A 20 x 20 mm plane (UVs in [0, 0.9]^2) plus one triangle 10 mm long and width_mm wide with its own
    full-size UV triangle in the free strip: texels width_mm / 10 as wide as long."""
    plane = plane_mesh(20.0, 20.0, cells=8)
    n = len(plane.vertices)
    vertices = np.vstack([plane.vertices, [[30.0, 0.0, 0.0], [40.0, 0.0, 0.0], [35.0, width_mm, 0.0]]])
    uv = np.vstack([plane.visual.uv * 0.9, [[0.92, 0.1], [0.98, 0.1], [0.95, 0.16]]])
    return write_obj(tmp_path / "sliver.obj", vertices, np.vstack([plane.faces, [[n, n + 1, n + 2]]]), uv)


def test_one_sliver_triangle_does_not_drive_the_substeps_up(tmp_path, capsys):
    """Before: 44,610 substeps per 0.01 s step at 64^2 (447 for a 1e-2 mm wide one); the plane alone needs 1."""
    path = mesh_scene(tmp_path, sliver_plane(tmp_path, 1e-3), duration_s=0.02)
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 0, lines
    substeps = json.loads((tmp_path / "out" / "metrics.json").read_text())["cautery"]["heat_substeps_per_step"]
    assert substeps == 1 <= MAX_SUBSTEPS


def test_more_substeps_than_the_cap_is_refused_in_one_line(tmp_path, capsys):
    """A 2 mm plane with heat on 64^2 texels (0.03 mm), k = 5 W/(m K), dt = 0.05 s: about 500 explicit substeps per
    step (the implicit scheme runs such texels: test_mesh_in_metres_warns_with_its_size)."""
    mesh = write_obj(tmp_path / "small.obj", *(lambda m: (m.vertices, m.faces, m.visual.uv))(plane_mesh(2.0, 2.0)))
    path = mesh_scene(tmp_path, mesh, duration_s=0.1, time_step_s=0.05, tissue={"preset": "liver", "conductivity_w_mk": 5.0})
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out", "--set", "cautery.heat_grid_divisor=1")
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"error: {path}: cautery.scheme: the explicit heat scheme needs ")
    assert f"over the cap of {MAX_SUBSTEPS}" in lines[0] and "use cautery.scheme=implicit" in lines[0]
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path / "out")


def test_mesh_in_metres_warns_with_its_size(tmp_path, capsys):
    """The patch's 60 x 40 mm written in metres; the implicit scheme runs it (the explicit one is refused, as above)."""
    plane = plane_mesh(0.06, 0.04)
    path = mesh_scene(tmp_path, write_obj(tmp_path / "metres.obj", plane.vertices, plane.faces, plane.visual.uv),
                      duration_s=0.02, cautery={"scheme": "implicit"})
    code, lines = run_cli(capsys, path, "--out", tmp_path / "out")
    assert code == 0
    assert lines == [f"warning: {path}: mesh: mesh is 0.0721 mm across: is it in metres? lengths are in millimetres"]
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["cautery"]["heat_substeps_per_step"] == 1


def _atlas_of_a_sphere(tmp_path):
    """(faces, uv) of a sphere's surface, in the order of its cache entry's names."""
    from sims.surface.texels import build_surface

    surface = build_surface(trimesh.creation.icosphere(subdivisions=1, radius=5.0), 32)
    return surface.faces, surface.uv


def _sdf_of_a_sphere(tmp_path):
    """(grid, origin) of a ball's signed distances, in the order of its cache entry's names."""
    from sims.scene.instruments import mesh_sdf_grid

    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=1, radius=2.0).export(path)
    return mesh_sdf_grid(path, 8)[:2]


@pytest.mark.parametrize("folder, compute, names", [("atlas", _atlas_of_a_sphere, ("faces", "uv")),
                                                    ("sdf", _sdf_of_a_sphere, ("grid", "origin"))])
def test_truncated_cache_entry_is_recomputed(tmp_path, monkeypatch, folder, compute, names):
    """Both on-disk caches (xatlas atlases, instrument SDFs) read through sims.core.backend.read_cached_npz."""
    monkeypatch.setenv("TISSUE_LAB_CACHE", str(tmp_path / "cache"))
    first = compute(tmp_path)
    [entry] = (tmp_path / "cache" / folder).iterdir()
    entry.write_bytes(entry.read_bytes()[:100])  # what a run killed while writing used to leave
    again = compute(tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(again, first))
    assert [p.name for p in (tmp_path / "cache" / folder).iterdir()] == [entry.name]
    with np.load(entry) as data:  # the entry written again holds what was computed
        assert all(np.array_equal(data[name].astype(value.dtype), value) for name, value in zip(names, first))


def test_a_failed_atlas_cache_write_leaves_no_entry(tmp_path, monkeypatch):
    from sims.surface.texels import build_surface

    monkeypatch.setenv("TISSUE_LAB_CACHE", str(tmp_path / "cache"))

    def failing_savez(file, **arrays):
        (open(file, "wb") if isinstance(file, (str, Path)) else file).write(b"PK\x03\x04 half an entry")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError):
        build_surface(trimesh.creation.icosphere(subdivisions=1, radius=5.0), 32)
    assert list((tmp_path / "cache" / "atlas").iterdir()) == []


@pytest.fixture(scope="module")
def previous_run(tmp_path_factory):
    """(scene file, the folder of a complete run of it): 32^2 texels, 1000 s long unless --duration says less."""
    folder = tmp_path_factory.mktemp("previous")
    path = write_scene(folder, bad({"texture_size": 32, "duration_s": 1000.0}))
    assert main(["run", str(path), "--out", str(folder / "out"), "--duration", "0.1", "--frames-every", "0.05", "--quiet"]) == 0
    return path, folder / "out"


def copy_of(previous_run, tmp_path: Path):
    """The scene file, a copy of the previous run's folder at tmp_path / "out", and that folder's files."""
    path, folder = previous_run
    out = tmp_path / "out"
    shutil.copytree(folder, out)
    return path, out, outputs(out)


def test_a_failed_write_leaves_the_previous_outputs(tmp_path, capsys, monkeypatch, previous_run):
    from lab import runner

    path, out, before = copy_of(previous_run, tmp_path)

    def no_space(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(runner, "save_npz_atomic", no_space)  # after frames and final.png are written
    code, lines = run_cli(capsys, path, "--out", out, "--duration", "0.2", "--frames-every", "0.05")
    assert code == 2 and lines == [f"error: {out}: --out: cannot write outputs: No space left on device"]
    assert outputs(out) == before and not leftovers(out)


def test_ctrl_c_in_process_exits_130_and_keeps_the_previous_outputs(tmp_path, capsys, monkeypatch, previous_run):
    from sims.scene.assembly import Scene

    path, out, before = copy_of(previous_run, tmp_path)
    original_step = Scene.step

    def interrupted_step(scene):
        if scene.steps == 3:
            raise KeyboardInterrupt
        original_step(scene)

    monkeypatch.setattr(Scene, "step", interrupted_step)
    code, lines = run_cli(capsys, path, "--out", out, "--frames-every", "0.01")
    assert code == 130 and lines == [f"interrupted at t = 0.03 s; previous outputs in {out} kept"]
    assert outputs(out) == before and not leftovers(out)


def test_new_output_folder_with_foreign_files_is_refused(tmp_path, capsys):
    path, out = write_scene(tmp_path), tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, lines = run_cli(capsys, path, "--out", out)
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {out}: --out: cannot write outputs: holds files a run does not write (notes.txt)")
    assert [p.name for p in out.iterdir()] == ["notes.txt"] and not leftovers(out)


def test_sigint_to_a_real_run_exits_130_and_keeps_the_previous_outputs(tmp_path, previous_run):
    path, out, before = copy_of(previous_run, tmp_path)
    process = subprocess.Popen([sys.executable, "-m", "lab", "run", str(path), "--out", str(out), "--frames-every", "0.05", "--quiet"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO_ROOT, preexec_fn=interruptible)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".out.*/frames/frame_00001.png")):  # stepping has started
            assert process.poll() is None and time.monotonic() < deadline, "the run ended or never started stepping"
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.kill(process.pid, signal.SIGKILL)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1].endswith(f"s; previous outputs in {out} kept")
    assert outputs(out) == before and not leftovers(out)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
def test_an_oversized_mesh_file_is_refused_before_it_is_read(tmp_path, suffix):
    """A 1 GB sparse file: .ply passed 4 GB of memory, .obj and .stl peaked at 2.2 GB before their error."""
    mesh = tmp_path / f"huge{suffix}"
    with open(mesh, "wb") as handle:
        handle.truncate(1 << 30)
    line = one_line(run_limited(mesh_scene(tmp_path, mesh), "--out", tmp_path / "out"))
    assert line.endswith(f"mesh: {mesh}: {1 << 30} bytes; a mesh file is at most {MAX_MESH_BYTES} bytes")


def test_a_mesh_header_declaring_too_many_faces_is_refused(tmp_path, capsys):
    """The PLY header's counts are read before trimesh allocates for them."""
    mesh = tmp_path / "liar.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1000000000\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    code, lines = run_cli(capsys, mesh_scene(tmp_path, mesh), "--out", tmp_path / "out")
    assert code == 2 and len(lines) == 1 and lines[0].endswith(f"1000000000 face elements; a mesh has at most {MAX_MESH_ELEMENTS}")


SIGINT_DURING_IMPORT = """import os, signal, sys
class _Hook:
    def find_spec(self, name, path=None, target=None):
        if name == os.environ["SIGINT_AT_IMPORT"]:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
sys.meta_path.insert(0, _Hook())
"""


@pytest.mark.parametrize("module, line", [
    ("yaml", "interrupted while starting; nothing done"),  # the CLI module's own imports: was a traceback
    ("taichi", "interrupted while building the scene; {out} left as it was"),  # was a traceback
    ("trimesh.voxel", "interrupted while building the scene; {out} left as it was"),  # trimesh swallowed it: was lost
])
def test_ctrl_c_while_the_cli_starts_is_one_line_and_never_lost(tmp_path, module, line):
    """Ctrl-C as the import of `module` begins (a sitecustomize hook sends the SIGINT)."""
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(SIGINT_DURING_IMPORT)
    env = {**os.environ, "SIGINT_AT_IMPORT": module, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path / "hook"), os.environ.get("PYTHONPATH")])),
           "TISSUE_LAB_CACHE": str(tmp_path / "cache")}  # empty: the mesh is parsed (trimesh imported) as on a first run
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "-m", "lab", "run", str(write_scene(tmp_path)), "--out", str(out), "--quiet"], capture_output=True,
                            text=True, cwd=REPO_ROOT, timeout=120, env=env, preexec_fn=interruptible)
    assert (result.returncode, result.stderr) == (130, line.format(out=out) + "\n")
    assert not out.exists() and not leftovers(out)


def test_a_killed_run_leaves_nothing_that_the_next_run_keeps(tmp_path, capsys, previous_run):
    """SIGKILL cannot be caught: the temporary folder stays until the next run into the same --out removes it (its
    name holds the dead run's process id); a live run's folder is left alone."""
    path, out, before = copy_of(previous_run, tmp_path)
    process = subprocess.Popen([sys.executable, "-m", "lab", "run", str(path), "--out", str(out), "--frames-every", "0.05", "--quiet"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO_ROOT)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".out.*/frames/frame_00001.png")):  # stepping has started
            assert process.poll() is None and time.monotonic() < deadline, "the run ended or never started stepping"
            time.sleep(0.05)
    finally:
        process.kill()
        process.wait()
    [stale] = leftovers(out)
    alive = tmp_path / stale.replace(f"run{process.pid}.", f"run{os.getpid()}.")  # as a run still going would have it
    alive.mkdir()
    code, _ = run_cli(capsys, path, "--out", out, "--duration", "0.02")
    assert code == 0 and leftovers(out) == [alive.name]
