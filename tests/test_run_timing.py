"""A headless run's timings and start-up: the first step (kernels loaded or compiled) apart from the steps after it;
what a run imports; texel maps kept on disk."""
import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from lab import runner
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT
from tests.test_cli import SMALL_SCENE, write_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The small scene (0.01 s steps), built once: each run goes on from where the last one stopped."""
    return Scene.from_file(write_scene(tmp_path_factory.mktemp("scene")), arch="cpu")


def _metrics(scene, tmp_path, duration_s: float) -> dict:
    """metrics.json of a run of `scene` for duration_s, as written and as returned."""
    returned = runner.run(scene, tmp_path / "out", duration_s, progress=False)
    written = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert written == returned
    return written


def test_steps_per_s_leaves_out_the_first_step(scene, tmp_path):
    metrics = _metrics(scene, tmp_path, 0.2)
    assert metrics["steps"] == 20  # the scene's first run
    first, wall = metrics["first_step_s"], metrics["wall_s"]
    assert isinstance(first, float) and 0.0 < first < wall
    assert metrics["steps_per_s"] == pytest.approx(19 / (wall - first), rel=1e-9)


@pytest.mark.parametrize("duration_s, first_step", [(0.01, True), (0.0, False)])
def test_a_run_without_later_steps_has_no_rate(scene, tmp_path, duration_s, first_step):
    """One step: its time, and no rate (JSON null, where a bare division gave a rate or Infinity); none: neither."""
    metrics = _metrics(scene, tmp_path, duration_s)
    assert metrics["steps_per_s"] is None
    assert (metrics["first_step_s"] is not None) == first_step


def test_a_headless_run_imports_only_what_it_uses():
    """The CLI's parser lists the bench sections without importing them: a run imported the lab's session (and the
    bench's helpers) through that list."""
    code = ("import sys\nimport lab.__main__\nlab.__main__.build_parser()\nimport lab.runner, sims.scene.assembly\n"
            "print(sorted(name for name in ('lab.session', 'lab.web.app', 'lab.bench.common', 'viser', 'matplotlib') if name in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT, check=True)
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_texel_maps_are_built_once_per_mesh_and_size(tmp_path, monkeypatch):
    """A second build of the same mesh at the same size (and its coarser heat grid) reads the texel maps from the cache
    instead of rasterising again, and they are the same maps."""
    from lab.reference.meshes import plane_mesh
    from sims.surface import texels as surfaces

    monkeypatch.setenv("TISSUE_LAB_CACHE", str(tmp_path))
    size = 2 * surfaces.SURFACE_CACHE_MIN_SIZE  # the heat grid at half of it is kept too
    mesh = plane_mesh(24.0, 12.0)
    built = surfaces.build_surface(mesh, size)
    coarse = surfaces.surface_at(built, size // 2)
    monkeypatch.setattr(surfaces, "_rasterise", lambda *args: pytest.fail("rasterised again"))
    for fresh, again in ((built, surfaces.build_surface(mesh, size)), (coarse, surfaces.surface_at(built, size // 2))):
        for field in dataclasses.fields(fresh):
            a, b = getattr(fresh, field.name), getattr(again, field.name)
            assert type(a) is type(b) and np.array_equal(a, b) and np.asarray(a).dtype == np.asarray(b).dtype, field.name
    other = plane_mesh(24.0, 12.1)  # another mesh is built, not read
    with pytest.raises(pytest.fail.Exception, match="rasterised again"):
        surfaces.build_surface(other, size)


def test_a_scene_read_before_builds_without_trimesh_or_a_k_d_tree(tmp_path):
    """A second process building the same scene reads its mesh, texel maps, heat taps and seam links from the cache:
    it imports neither trimesh nor scipy.spatial (0.4-0.5 s of start-up), and builds the same scene."""
    # large enough to be kept on disk; a mesh with seams
    scene_file = write_scene(tmp_path, {**SMALL_SCENE, "mesh": "meshes/liver_lobe.obj", "texture_size": 512})
    code = ("import sys\nimport numpy as np\nfrom sims.scene.assembly import Scene\n"
            f"scene = Scene.from_file({str(scene_file)!r}, arch='cpu')\n"
            "print([name for name in ('trimesh', 'scipy.spatial') if name in sys.modules])\n"
            "print(float(np.asarray(scene.heat_display.resampler.weights_np, np.float64).sum()), scene.cautery.seam_links)")
    environment = {**os.environ, "TISSUE_LAB_CACHE": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT, check=True,
                           env=environment).stdout.strip().splitlines()[-2:] for _ in range(2)]
    assert runs[0][0] == "['trimesh', 'scipy.spatial']"  # the first parses and searches
    assert int(runs[0][1].split()[1]) > 0  # the lobe has seams: links were found, then read back
    assert runs[1][0] == "[]"
    assert runs[1][1] == runs[0][1]


def test_a_mesh_file_is_parsed_again_when_its_bytes_change(tmp_path, monkeypatch):
    """The parsed tissue mesh is kept by the file's bytes: the same file reads back the same arrays without trimesh,
    an edited one is parsed anew."""
    from lab.reference.meshes import plane_mesh
    from sims.surface import texels

    monkeypatch.setenv("TISSUE_LAB_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "plane.obj"
    plane_mesh(24.0, 12.0).export(path)
    first = texels.read_tissue_mesh(path)
    parse = texels._parse_mesh
    monkeypatch.setattr(texels, "_parse_mesh", lambda *args: pytest.fail("parsed again"))
    again = texels.read_tissue_mesh(path)
    for name in ("vertices", "faces", "uv"):
        a, b = getattr(first, name), getattr(again, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    plane_mesh(30.0, 12.0).export(path)
    monkeypatch.setattr(texels, "_parse_mesh", parse)
    assert np.ptp(texels.read_tissue_mesh(path).vertices[:, 0]) == pytest.approx(30.0)


def test_the_surface_cache_keeps_within_its_bytes(tmp_path):
    """Past its bytes, the least recently used entries go."""
    from sims.core.backend import prune_cache

    for index, age in enumerate((30, 10, 20)):
        path = tmp_path / f"{index}.npz"
        path.write_bytes(b"x" * 100)
        os.utime(path, (1e9 + age, 1e9 + age))
    prune_cache(tmp_path, 250)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["0.npz", "2.npz"]


def test_stage_textures_are_resampled_once_per_file_and_size(tmp_path, monkeypatch):
    """A stage image read again at the same size comes from the cache, the same values; a changed file is read anew."""
    from PIL import Image

    from sims.look import compose

    monkeypatch.setenv("TISSUE_LAB_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "stage.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (40, 40, 3), dtype=np.uint8)).save(path)
    first = compose.load_texture(path, 32, tile=2)
    read = compose._read_texture
    monkeypatch.setattr(compose, "_read_texture", lambda *args: pytest.fail("read again"))
    again = compose.load_texture(path, 32, tile=2)
    assert again.dtype == first.dtype == np.float32 and np.array_equal(again, first)
    Image.new("RGB", (40, 40), (255, 0, 0)).save(path)
    os.utime(path, ns=(1, 1))  # another modification time whatever the clock's resolution
    monkeypatch.setattr(compose, "_read_texture", read)
    assert np.array_equal(compose.load_texture(path, 32, tile=2)[0, 0], [1.0, 0.0, 0.0])


def test_the_start_up_table_has_every_stage(tmp_path):
    """The bench's start-up section: a row per stage in order, then their total."""
    from lab.bench import SECTIONS, startup

    seconds = {stage: 0.1 * (index + 1) for index, stage in enumerate(startup.STAGES)}
    results = {"runs": 2, "arch": "cpu", "texture_size": 512, "plane_mm": 24.0, "process_s": 5.6, "process_range_s": [5.5, 5.9],
               "stages_s": seconds}
    rows = [line for line in startup.render(results) if line.startswith("| ") and not line.startswith("| stage")]
    assert [row.split(" | ")[0][2:] for row in rows] == [*startup.STAGES, "total"]
    assert rows[-1] == f"| total | {sum(seconds.values()):.2f} | 100 % |"
    assert "startup" in SECTIONS and (tmp_path / startup.plot(results, tmp_path)[0]).stat().st_size > 10_000


def test_the_cli_ends_without_teardown_yet_keeps_its_kernels_output_and_exit_code(tmp_path):
    """lab.__main__.exit_now skips the interpreter's teardown (0.2-0.3 s of a short run) but still finalizes Taichi,
    which is what writes a newly compiled kernel into the offline cache, runs the exit handlers and flushes what was
    printed; the exit code is the one given."""
    code = ("import atexit, sys\nfrom lab.__main__ import exit_now\nfrom sims.core import backend\nbackend.init('cpu')\n"
            "import taichi as ti\nvalues = ti.field(ti.f32, 4)\n@ti.kernel\ndef double():\n"
            "    for i in values:\n        values[i] = 2.0 * i\ndouble()\n"
            "atexit.register(lambda: print('exit handler ran'))\nprint('printed', end='')\nsys.stderr.write('told')\nexit_now(3)\n")
    script = tmp_path / "script.py"  # a file: Taichi reads a kernel's source
    script.write_text(code)
    env = dict(os.environ, TISSUE_LAB_CACHE=str(tmp_path))
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=REPO_ROOT, env=env)
    assert result.returncode == 3
    assert "printed" in result.stdout and "exit handler ran" in result.stdout
    assert result.stderr.endswith("told")
    assert list((tmp_path / "taichi").glob("*.tic")), "the compiled kernel was not written to the cache"
