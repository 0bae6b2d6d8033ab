"""Texel maps: UV use or xatlas atlas, mesh formats, degenerate triangles, vertex checks."""
import re

import numpy as np
import pytest
import trimesh

from lab.reference.meshes import plane_mesh
from sims.scene.config import REPO_ROOT
from sims.surface.texels import MeshError, build_surface, load_mesh


def assert_finite_maps(surface):
    for name in ("position_mm", "normal", "tangent_u", "tangent_v", "texel_area_mm2"):
        assert np.isfinite(getattr(surface, name)).all(), name


def test_plane_uses_its_uvs_and_measures_millimetres():
    surface = build_surface(plane_mesh(60.0, 40.0), 256)
    assert surface.uv_source == "mesh"
    assert surface.mask.all()
    assert surface.area_mm2 == pytest.approx(2400.0, rel=1e-3)
    assert np.linalg.norm(surface.tangent_u[100, 100]) == pytest.approx(60.0 / 256, rel=1e-4)
    assert np.linalg.norm(surface.tangent_v[100, 100]) == pytest.approx(40.0 / 256, rel=1e-4)
    # image orientation: row 0 is v = 1 (top, +y), column 0 is u = 0 (-x)
    assert surface.position_mm[0, 0, 0] < -29 and surface.position_mm[0, 0, 1] > 19
    assert np.allclose(surface.normal[surface.mask], [0, 0, 1], atol=1e-5)


@pytest.mark.parametrize("repeats", [3, 8])
def test_tiled_uvs_get_an_xatlas_atlas(repeats):
    """UVs of a repeating texture overlap (3) or collapse whole triangles to a point (8): both need an atlas."""
    mesh = plane_mesh(20.0, 20.0, cells=8)
    mesh.visual = trimesh.visual.TextureVisuals(uv=(mesh.visual.uv * repeats) % 1.0)
    surface = build_surface(mesh, 128)
    assert surface.uv_source == "xatlas"
    assert surface.area_mm2 == pytest.approx(400.0, rel=0.05)
    assert_finite_maps(surface)


@pytest.mark.parametrize("extension", ["obj", "ply", "glb", "stl"])
def test_mesh_formats(tmp_path, extension):
    path = tmp_path / f"sphere.{extension}"
    trimesh.creation.icosphere(subdivisions=2, radius=10.0).export(path)
    surface = build_surface(load_mesh(path), 128)
    assert surface.uv_source == "xatlas"  # no UVs in these files
    assert surface.area_mm2 == pytest.approx(4 * np.pi * 100, rel=0.08)
    assert_finite_maps(surface)


def test_degenerate_triangles_are_skipped_without_nan():
    mesh = plane_mesh(10.0, 10.0, cells=2)
    vertices = np.vstack([mesh.vertices, [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 3, 0], [4, 4, 1], [5, 5, 2]]])
    uv = np.vstack([mesh.visual.uv, [[0.1, 0.1], [0.2, 0.1], [0.2, 0.2], [0.5, 0.5], [0.5, 0.5], [0.5, 0.5]]])
    n = len(mesh.vertices)
    faces = np.vstack([mesh.faces, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5]]])  # zero area in 3D; zero area in UV
    surface = build_surface(trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv), process=False), 64)
    assert surface.skipped_triangles == 2
    assert_finite_maps(surface)
    assert surface.area_mm2 == pytest.approx(100.0, rel=0.01)


def test_organ_mesh_keeps_its_multi_chart_uvs():
    surface = build_surface(load_mesh(REPO_ROOT / "static/meshes/liver_lobe.obj"), 256)
    assert surface.uv_source == "mesh"
    assert 0.2 < surface.mask.mean() < 0.95  # several charts with gutters between them
    assert surface.area_mm2 == pytest.approx(load_mesh(REPO_ROOT / "static/meshes/liver_lobe.obj").area, rel=0.05)
    assert_finite_maps(surface)


def test_unreadable_mesh_raises_mesh_error(tmp_path):
    path = tmp_path / "broken.obj"
    path.write_text("this is not a mesh\n")
    with pytest.raises(MeshError):
        build_surface(load_mesh(path), 32)


@pytest.mark.parametrize("x0, message", [(np.nan, "1 of 42 vertices are not finite"), (1e39, "1e+39 mm found")])
def test_vertices_not_finite_or_far_out_raise_before_xatlas(x0, message):
    """A mesh without UVs goes to xatlas, which never returned on a vertex at 1e39 and unwrapped one at NaN."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    vertices = sphere.vertices.copy()
    vertices[0, 0] = x0
    with pytest.raises(MeshError, match=re.escape(message)):
        build_surface(trimesh.Trimesh(vertices, sphere.faces, process=False), 32)


def test_a_sliver_triangle_is_skipped():
    """A triangle 10 mm long and 1e-3 mm wide with a full-size UV triangle: its texels would be 1e4 times longer
    than wide (and ask 44,610 heat substeps per step); it is skipped, the plane keeps all its texels."""
    plane = plane_mesh(20.0, 20.0, cells=8)
    n = len(plane.vertices)
    vertices = np.vstack([plane.vertices, [[30.0, 0.0, 0.0], [40.0, 0.0, 0.0], [35.0, 1e-3, 0.0]]])
    uv = np.vstack([plane.visual.uv * 0.9, [[0.92, 0.1], [0.98, 0.1], [0.95, 0.16]]])
    mesh = trimesh.Trimesh(vertices, np.vstack([plane.faces, [[n, n + 1, n + 2]]]), visual=trimesh.visual.TextureVisuals(uv=uv), process=False)
    surface = build_surface(mesh, 64)
    alone = build_surface(trimesh.Trimesh(plane.vertices, plane.faces, visual=trimesh.visual.TextureVisuals(uv=plane.visual.uv * 0.9), process=False), 64)
    assert surface.uv_source == "mesh" and surface.skipped_triangles == 1
    assert np.array_equal(surface.mask, alone.mask) and surface.area_mm2 == alone.area_mm2


def test_uvs_stretched_beyond_the_aspect_limit_get_an_xatlas_atlas():
    """UVs squeezed 30:1 make texels 30 times longer than wide: the atlas replaces them."""
    mesh = plane_mesh(20.0, 20.0, cells=8)
    mesh.visual = trimesh.visual.TextureVisuals(uv=mesh.visual.uv * [1.0 / 30.0, 1.0])
    surface = build_surface(mesh, 64)
    assert surface.uv_source == "xatlas" and surface.area_mm2 == pytest.approx(400.0, rel=0.05)


def test_a_mesh_in_metres_gets_a_size_warning():
    assert build_surface(plane_mesh(0.06, 0.04), 32).size_warning == \
        "mesh is 0.0721 mm across: is it in metres? lengths are in millimetres"
    assert build_surface(plane_mesh(60.0, 40.0), 32).size_warning is None
