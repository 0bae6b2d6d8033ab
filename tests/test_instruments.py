"""Instrument signed distance, paths, and the burn mark taking the instrument's silhouette."""
import numpy as np
import pytest
import taichi as ti
import trimesh

from lab.reference.meshes import plane_mesh
from sims.heat.cautery import Cautery
from sims.scene.assembly import Scene
from sims.scene.config import REPO_ROOT, load_scene_config
from sims.scene.instruments import Instrument, InstrumentFields, local_frame
from sims.surface.texels import build_surface
from testing.helpers import cautery_values, tissue_values


def make_instrument(shape: dict, position=(0, 0, 0), direction=(0, 0, -1), roll=0.0, energized=True, path=()):
    full = {"radius_mm": 1.0, "length_mm": 10.0, "width_mm": 3.0, "thickness_mm": 0.5, "file": None, "sdf_resolution": 40, **shape}
    return Instrument.from_config({
        "name": shape["type"], "shape": full, "position_mm": list(position), "direction": list(direction),
        "roll_deg": roll, "energized": energized, "tip_temperature_c": 250.0, "path": list(path),
    })


def distances(fields: InstrumentFields, points: np.ndarray) -> np.ndarray:
    points_nd = ti.Vector.ndarray(3, ti.f32, len(points))
    points_nd.from_numpy(points.astype(np.float32))
    out = ti.ndarray(ti.f32, len(points))

    @ti.kernel
    def evaluate(p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1), d: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(p.shape[0]):
            d[i] = fields.distance(0, p[i])

    evaluate(points_nd, out)
    return out.to_numpy()


def test_local_frame_is_a_rotation_with_z_back_along_the_shaft():
    for direction in ([0, 0, -1], [1, 0, 0], [0.3, -0.2, -0.9]):
        frame = local_frame(direction, 30.0)
        assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        assert np.allclose(frame[2], -np.array(direction) / np.linalg.norm(direction))


def test_analytic_distances():
    rng = np.random.default_rng(0)
    points = rng.uniform(-8, 8, (500, 3))
    ball = distances(InstrumentFields([make_instrument({"type": "ball", "radius_mm": 2.0}, position=(1, 0, 0))]), points)
    assert np.allclose(ball, np.linalg.norm(points - [1, 0, 0], axis=1) - 2.0, atol=1e-4)
    # vertical capsule pointing down: the shaft goes up from the tip at the origin
    capsule = distances(InstrumentFields([make_instrument({"type": "capsule", "radius_mm": 1.0, "length_mm": 5.0})]), points)
    height = np.clip(points[:, 2], 0.0, 5.0)
    expected = np.linalg.norm(points - np.stack([0 * height, 0 * height, height], axis=1), axis=1) - 1.0
    assert np.allclose(capsule, expected, atol=1e-4)


def test_spatula_box_distance_inside_and_outside():
    tool = make_instrument({"type": "spatula", "width_mm": 4.0, "thickness_mm": 1.0, "length_mm": 10.0}, direction=(1, 0, 0))
    fields = InstrumentFields([tool])
    # pointing along +x, the blade spans x in [-10, 0], width along y, thickness along z
    d = distances(fields, np.array([[-5.0, 0, 0], [-5.0, 0, 1.5], [-5.0, 3.0, 0], [2.0, 0, 0]]))
    assert d == pytest.approx([-0.5, 1.0, 1.0, 2.0], abs=1e-4)


def test_mesh_sdf_matches_analytic_sphere(tmp_path):
    path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=3.0).export(path)
    fields = InstrumentFields([make_instrument({"type": "mesh", "file": path, "sdf_resolution": 16}, position=(0, 0, 0))])
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    near = directions * rng.uniform(1.5, 6.0, (400, 1))  # up to 3 mm outside: inside the grid
    error = distances(fields, near) - (np.linalg.norm(near, axis=1) - 3.0)
    assert np.abs(error).max() < 0.1
    far = directions * rng.uniform(8.0, 30.0, (400, 1))  # beyond the grid: an upper bound, sign right
    estimate, exact = distances(fields, far), np.linalg.norm(far, axis=1) - 3.0
    assert (estimate > exact - 0.1).all() and (estimate < exact + 3.0).all()


def test_path_interpolates_and_energized_holds():
    tool = make_instrument({"type": "ball"}, position=(0, 0, 5), energized=False, path=[
        {"t_s": 1.0, "position_mm": [0, 0, 0], "direction": None, "roll_deg": None, "energized": True, "tip_temperature_c": None},
        {"t_s": 3.0, "position_mm": [10, 0, 0], "direction": None, "roll_deg": None, "energized": None, "tip_temperature_c": 300.0},
    ])
    assert tool.pose_at(0.0).position_mm == pytest.approx([0, 0, 0]) and not tool.pose_at(0.5).energized
    assert tool.pose_at(2.0).position_mm == pytest.approx([5, 0, 0]) and tool.pose_at(2.0).energized
    assert tool.pose_at(9.0).position_mm == pytest.approx([10, 0, 0])
    assert tool.pose_at(9.0).tip_temperature_c == pytest.approx(300.0)


def footprint_extent(mask: np.ndarray, positions: np.ndarray):
    """Extent (mm) along x and y of the texels in mask."""
    points = positions[mask]
    return np.ptp(points[:, 0]), np.ptp(points[:, 1])


def press_flat(instrument, steps=40):
    """Burn a 30 x 20 mm plane with the instrument; return (surface, coagulated mask)."""
    surface = build_surface(plane_mesh(30.0, 20.0), 256)
    cautery = Cautery(surface, tissue_values(), cautery_values(contact_distance_mm=0.1), InstrumentFields([instrument]))
    for _ in range(steps):
        cautery.step(0.01)
    return surface, cautery.damage_omega() >= 1.0


SPATULA = {"type": "spatula", "width_mm": 3.0, "thickness_mm": 0.6, "length_mm": 12.0}


def test_burn_mark_takes_the_spatula_silhouette():
    """A spatula pressed flat (axis along x, flat face down) leaves a coagulated region shaped like its footprint."""
    spatula = make_instrument(SPATULA, position=(6, 0, 0.3), direction=(1, 0, 0))
    surface, burned = press_flat(spatula)
    footprint_aspect = SPATULA["length_mm"] / SPATULA["width_mm"]
    bx, by = footprint_extent(burned, surface.position_mm)
    assert abs((bx / by) / footprint_aspect - 1) < 0.15


def test_mesh_instrument_burns_like_the_same_analytic_shape(tmp_path):
    """The same blade as a mesh (distance grid) and as an analytic box: the burn marks overlap."""
    path = tmp_path / "blade.obj"
    box = trimesh.creation.box(extents=[SPATULA["width_mm"], SPATULA["thickness_mm"], SPATULA["length_mm"]])
    box.apply_translation([0, 0, SPATULA["length_mm"] / 2])
    box.export(path)
    mesh_tool = make_instrument({"type": "mesh", "file": path, "sdf_resolution": 48}, position=(6, 0, 0.3), direction=(1, 0, 0))
    _, burned_mesh = press_flat(mesh_tool)
    _, burned_box = press_flat(make_instrument(SPATULA, position=(6, 0, 0.3), direction=(1, 0, 0)))
    overlap = (burned_mesh & burned_box).sum() / (burned_mesh | burned_box).sum()
    assert burned_box.sum() > 1000 and overlap > 0.9


def test_a_spatula_rests_flat_on_the_tissue_below_it():
    """The default scene's spatula lies along the tissue (its axis never meets it): rested, it goes straight down until
    its blade's lowest point is 0.2 mm in, its face on the tissue; its gap is measured the same way, and off the
    tissue there is nothing to rest on."""
    scene = Scene(load_scene_config(REPO_ROOT / "scenes" / "default.yaml", ["models=[]", "texture_size=64"]))
    tool = scene.instrument("spatula")
    start = tool.pose_at(0.0).position_mm
    assert scene.tool_clearance_mm("spatula") == pytest.approx(3.9, abs=0.1), "the script holds it 4 mm above the tissue"
    assert scene.rest_on_tissue("spatula", start + [0.0, 0.0, 10.0], 0.2) == pytest.approx(14.1, abs=0.1)
    assert scene.tool_clearance_mm("spatula") == pytest.approx(-0.2, abs=1e-3)
    pose = tool.pose_at(0.0)
    assert pose.position_mm[:2] == pytest.approx(start[:2]) and pose.direction == pytest.approx(tool.base.direction / np.linalg.norm(tool.base.direction))
    face = [scene.tissue_distance_mm(point + [0.0, 0.0, 5.0], [0.0, 0.0, -1.0]) - 5.0 for point in tool.contact_points_mm(pose)]
    assert len(face) > 20 and max(face) < 0.0, f"the blade's face is not on the tissue: {np.round(face, 2)} mm"
    assert scene.rest_on_tissue("spatula", [80.0, 0.0, 10.0], 0.2) is None and scene.tool_clearance_mm("spatula") is None
