"""Instruments: shapes with signed distance (analytic primitives; mesh -> SDF grid), poses, scripted paths.

Local frame of an instrument: origin at `position_mm`, local z points back along the shaft
(opposite to `direction`, which points from the handle to the tip), local y is the part of
world z (or world y for a vertical tool) perpendicular to the shaft, then rolled by `roll_deg`.
- ball: sphere of radius r centred at the origin
- capsule: segment from the origin to (0, 0, length) with radius r
- spatula: flat blade, box of width (x) x thickness (y) x length (z) from z = 0 to z = length
- mesh: a closed mesh given in local coordinates (mm), distance sampled trilinearly from a grid
Signed distance is negative inside the instrument.
"""
import functools
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from sims.core import field_io
from sims.core.backend import cache_dir, read_cached_npz, save_cached_npz
from sims.scene import keyframes

GRID_PADDING_MM = 3.0  # matches the largest contact distance (sims.scene.params)
SHAPE_CODES = {"ball": 0, "capsule": 1, "spatula": 2, "mesh": 3}
POSE_WIDTH = 14  # floats per instrument pose uploaded at once (InstrumentFields.set_poses)
CONTACT_SPACING_MM = 2.0  # a flat tool's contact points (Instrument.contact_points_mm) lie at most this far apart
MAX_CONTACT_SAMPLES = 16  # ... and at most this many along its width and its length


def local_frame(direction, roll_deg: float) -> np.ndarray:
    """(3, 3) rotation whose rows are the local x, y, z axes in world coordinates."""
    z = -np.asarray(direction, np.float64)
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    y = up - z * (up @ z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    angle = math.radians(roll_deg)
    x, y = math.cos(angle) * x + math.sin(angle) * y, -math.sin(angle) * x + math.cos(angle) * y
    return np.stack([x, y, z])


@functools.lru_cache(maxsize=256)
def _frame(direction: tuple, roll_deg: float) -> np.ndarray:
    """local_frame, remembered: a scripted tool keeps its direction and roll for many steps."""
    return local_frame(direction, roll_deg)


@dataclass
class Pose:
    position_mm: np.ndarray
    direction: np.ndarray
    roll_deg: float
    energized: bool
    tip_temperature_c: float


@dataclass
class HandPlacement:
    """Where a hand holds a tool it took over from the script: position (mm), direction and roll (deg)."""

    position_mm: np.ndarray
    direction: np.ndarray
    roll_deg: float


@dataclass
class Instrument:
    """A validated scene instrument (see sims.scene.config) and its scripted path.

    A hand (the browser, a script) can take the tool's placement over (`hand`) and switch it on or off
    (`energized_by_hand`); everything else, the tip temperature included, stays a parameter of the tool, so a
    scripted tool keeps following its path when a slider changes. `release` gives the tool back to its script."""

    name: str
    shape: dict
    base: Pose
    path: list = field(default_factory=list)
    suction: dict | None = None  # {radius_mm, rate_ml_s}: a sucker; removes blood while on, never heats
    hand: HandPlacement | None = None      # placement set by a hand, used instead of the path's
    energized_by_hand: bool | None = None  # on/off set by a hand, used instead of the path's

    @classmethod
    def from_config(cls, item: dict) -> "Instrument":
        base = Pose(np.array(item["position_mm"]), np.array(item["direction"]), item["roll_deg"], item["energized"], item["tip_temperature_c"])
        return cls(item["name"], item["shape"], base, item["path"], item.get("suction"))

    @property
    def held(self) -> bool:
        """True while a hand places or switches the tool (it does not follow its script)."""
        return self.hand is not None or self.energized_by_hand is not None

    def release(self) -> None:
        """Back to the script: the path's placement and switching from now on."""
        self.hand, self.energized_by_hand = None, None

    def scripted_pose_at(self, t_s: float, placement: bool = True) -> Pose:
        """The path's pose at time t: keyframe values interpolated linearly (energized holds its last value);
        placement False: the base position, direction and roll (a hand places the tool: not worth interpolating)."""
        base = self.base
        position, direction, roll = base.position_mm, base.direction, base.roll_deg
        if placement:
            position = keyframes.interpolate(self.path, "position_mm", t_s, position)
            direction = keyframes.interpolate(self.path, "direction", t_s, direction)
            roll = keyframes.interpolate(self.path, "roll_deg", t_s, roll)
        return Pose(
            np.asarray(position, np.float64), np.asarray(direction, np.float64), float(roll),
            bool(keyframes.hold(self.path, "energized", t_s, base.energized)),
            float(keyframes.interpolate(self.path, "tip_temperature_c", t_s, base.tip_temperature_c)),
        )

    def pose_at(self, t_s: float) -> Pose:
        """Pose at time t: the script's, with the hand's placement and switch where a hand set them."""
        pose = self.scripted_pose_at(t_s, placement=self.hand is None)
        if self.hand is not None:
            pose.position_mm, pose.direction, pose.roll_deg = self.hand.position_mm, self.hand.direction, self.hand.roll_deg
        if self.energized_by_hand is not None:
            pose.energized = self.energized_by_hand
        return pose

    def script_end_s(self) -> float:
        """Time of the last keyframe (0 without a path)."""
        return max((frame["t_s"] for frame in self.path), default=0.0)

    @property
    def flat(self) -> bool:
        """A flat tool (a spatula) rests on the face of its blade: it is lowered, and its gap to the tissue measured,
        straight down (world -z), not along its axis, which lies along the tissue."""
        return self.shape["type"] == "spatula"

    def lowered_along(self, pose: Pose) -> np.ndarray:
        """The unit direction (3,) the tool is lowered along onto the tissue: its axis, or straight down for a flat tool."""
        if self.flat:
            return np.array([0.0, 0.0, -1.0])
        return np.asarray(pose.direction, np.float64) / np.linalg.norm(pose.direction)

    def contact_points_mm(self, pose: Pose) -> np.ndarray:
        """Points on the tool (N, 3) mm, world, that first meet the tissue it is lowered onto (lowered_along): an axial
        tool's tip; a grid over a flat tool's lower blade face, its lowest corner included and the points at most
        CONTACT_SPACING_MM apart (for tissue curved under the blade)."""
        position = np.asarray(pose.position_mm, np.float64)
        if not self.flat:
            return (position + self.lowered_along(pose) * self.tip_offset_mm())[None]
        frame = _frame(tuple(np.asarray(pose.direction, np.float64).tolist()), float(pose.roll_deg))
        width, thickness, length = (float(self.shape[key]) for key in ("width_mm", "thickness_mm", "length_mm"))
        x, z = np.meshgrid(*(np.linspace(lo, hi, min(MAX_CONTACT_SAMPLES, 2 + int((hi - lo) / CONTACT_SPACING_MM)))
                             for lo, hi in ((-width / 2, width / 2), (0.0, length))))
        lower_face = -thickness / 2 if frame[1, 2] >= 0 else thickness / 2  # the face whose normal points down
        return position + np.stack([x.ravel(), np.full(x.size, lower_face), z.ravel()], axis=1) @ frame

    def tip_offset_mm(self) -> float:
        """Distance from the tool's origin to its tip along `direction`, mm (where it first touches what it points at)."""
        kind = self.shape["type"]
        if kind in ("ball", "capsule"):
            return float(self.shape["radius_mm"])
        if kind == "spatula":
            return 0.0
        import trimesh

        return float(max(0.0, -trimesh.load(str(self.shape["file"]), force="mesh").vertices[:, 2].min()))


# --- mesh instruments: signed distance grid --------------------------------------------------

@ti.func
def _closest_on_triangle(p, a, b, c):
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab.dot(ap), ac.dot(ap)
    result = a
    bp = p - b
    d3, d4 = ab.dot(bp), ac.dot(bp)
    cp = p - c
    d5, d6 = ab.dot(cp), ac.dot(cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    if d1 <= 0 and d2 <= 0:
        result = a
    elif d3 >= 0 and d4 <= d3:
        result = b
    elif vc <= 0 and d1 >= 0 and d3 <= 0:
        result = a + ab * (d1 / (d1 - d3))
    elif d6 >= 0 and d5 <= d6:
        result = c
    elif vb <= 0 and d2 >= 0 and d6 <= 0:
        result = a + ac * (d2 / (d2 - d6))
    elif va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        result = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    else:
        denom = 1.0 / (va + vb + vc)
        result = a + ab * (vb * denom) + ac * (vc * denom)
    return result


@ti.kernel
def _sdf_grid(tris: ti.types.ndarray(), origin: ti.types.ndarray(), spacing: ti.f32, out: ti.types.ndarray()):
    """Brute-force signed distance at grid nodes: nearest triangle, sign from the winding number."""
    for i, j, k in ti.ndrange(out.shape[0], out.shape[1], out.shape[2]):
        p = ti.Vector([origin[0] + i * spacing, origin[1] + j * spacing, origin[2] + k * spacing])
        best = 1e30
        winding = 0.0
        for f in range(tris.shape[0]):
            a = ti.Vector([tris[f, 0, 0], tris[f, 0, 1], tris[f, 0, 2]])
            b = ti.Vector([tris[f, 1, 0], tris[f, 1, 1], tris[f, 1, 2]])
            c = ti.Vector([tris[f, 2, 0], tris[f, 2, 1], tris[f, 2, 2]])
            best = ti.min(best, (p - _closest_on_triangle(p, a, b, c)).norm_sqr())
            ra, rb, rc = a - p, b - p, c - p
            la, lb, lc = ra.norm(), rb.norm(), rc.norm()
            numer = ra.dot(rb.cross(rc))
            denom = la * lb * lc + ra.dot(rb) * lc + ra.dot(rc) * lb + rb.dot(rc) * la
            winding += 2.0 * ti.atan2(numer, denom)
        sign = -1.0 if winding / (4.0 * math.pi) > 0.5 else 1.0
        out[i, j, k] = sign * ti.sqrt(best)


def mesh_sdf_grid(path, resolution: int):
    """Signed distance grid of a closed mesh in its own frame (cached on disk).

    Returns (grid (R0, R1, R2) float32 mm, origin (3,) mm, spacing mm). The grid pads the bounding
    box by GRID_PADDING_MM plus 3 cells, so every distance up to the largest contact distance is
    sampled from the grid; farther out the box-projection estimate is an upper bound.
    """
    import io

    import trimesh

    from sims.surface.texels import read_mesh_file

    data, kind = read_mesh_file(path)  # the checks of sims.surface.texels.load_mesh (size, a regular file) before reading it
    key = hashlib.sha1(data + f"{resolution}:{GRID_PADDING_MM}".encode()).hexdigest()
    cached = cache_dir() / "sdf" / f"{key}.npz"
    saved = read_cached_npz(cached, "grid", "origin", "spacing")
    if saved is not None:
        return saved[0], saved[1], float(saved[2])
    mesh = trimesh.load(io.BytesIO(data), file_type=kind, force="mesh")
    lo, hi = mesh.bounds
    spacing = float((hi - lo).max() / resolution)
    pad = GRID_PADDING_MM + 3 * spacing
    origin = lo - pad
    counts = np.ceil((hi - lo + 2 * pad) / spacing).astype(int) + 1
    grid = np.zeros(tuple(counts), np.float32)
    _sdf_grid(np.ascontiguousarray(mesh.triangles, np.float32), origin.astype(np.float32), spacing, grid)
    save_cached_npz(cached, grid=grid, origin=origin, spacing=spacing)
    return grid, origin, spacing


# --- Taichi side -------------------------------------------------------------------------------

@ti.data_oriented
class InstrumentFields:
    """Per-instrument pose and shape in Taichi fields, and their signed distance as a ti.func."""

    def __init__(self, instruments: list):
        self.instruments = list(instruments)
        count = max(len(instruments), 1)
        self.count = len(instruments)
        self.shape_code = ti.field(ti.i32, count)
        self.dims = ti.Vector.field(4, ti.f32, count)        # radius, length, width, thickness (mm)
        self.position = ti.Vector.field(3, ti.f32, count)    # mm
        self.rotation = ti.Matrix.field(3, 3, ti.f32, count)  # rows: local axes in world coordinates
        self.tip_temperature = ti.field(ti.f32, count)       # C
        self.energized = ti.field(ti.i32, count)
        self.extent = ti.field(ti.f32, count)                # mm, radius of a ball about the origin holding the shape
        grids = [None] * len(instruments)
        for index, instrument in enumerate(instruments):
            shape = instrument.shape
            if shape["type"] == "mesh":
                grids[index] = mesh_sdf_grid(shape["file"], shape["sdf_resolution"])
        dims = [g[0].shape for g in grids if g is not None] or [(2, 2, 2)]
        cells = tuple(max(d[axis] for d in dims) for axis in range(3))
        self.sdf = ti.field(ti.f32, (count,) + cells)
        self.sdf_origin = ti.Vector.field(3, ti.f32, count)
        self.sdf_spacing = ti.field(ti.f32, count)
        self.sdf_cells = ti.Vector.field(3, ti.i32, count)
        sdf = np.full((count,) + cells, 1e3, np.float32)
        origin, spacing, cell_counts = np.zeros((count, 3), np.float32), np.ones(count, np.float32), np.full((count, 3), 2, np.int32)
        codes, dims_arr, extent = np.zeros(count, np.int32), np.zeros((count, 4), np.float32), np.zeros(count, np.float32)
        for index, instrument in enumerate(instruments):
            shape = instrument.shape
            codes[index] = SHAPE_CODES[shape["type"]]
            dims_arr[index] = shape["radius_mm"], shape["length_mm"], shape["width_mm"], shape["thickness_mm"]
            radius, length, width, thickness = dims_arr[index]
            extent[index] = {"ball": radius, "capsule": length + radius, "spatula": np.linalg.norm([width / 2, thickness / 2, length])}.get(shape["type"], 0.0)
            if grids[index] is not None:
                grid, origin[index], spacing[index] = grids[index]
                sdf[(index,) + tuple(slice(0, n) for n in grid.shape)] = grid
                cell_counts[index] = grid.shape
                corners = origin[index] + np.array(np.meshgrid(*[[0, n - 1] for n in grid.shape])).reshape(3, -1).T * spacing[index]
                extent[index] = np.linalg.norm(corners, axis=1).max()
        field_io.load([(self.shape_code, codes), (self.dims, dims_arr), (self.sdf, sdf), (self.sdf_origin, origin),
                       (self.sdf_spacing, spacing), (self.sdf_cells, cell_counts), (self.extent, extent)])
        self.poses = []
        self._uploaded = None  # the packed poses last uploaded (set_poses)
        self.set_time(0.0)

    def set_time(self, t_s: float) -> None:
        """Move every instrument to its scripted pose at time t."""
        self.set_poses([instrument.pose_at(t_s) for instrument in self.instruments])

    def set_poses(self, poses: list) -> None:
        """Upload the poses (one per instrument) in one kernel launch, none when nothing changed since the last."""
        count = max(len(poses), 1)
        packed = np.zeros((count, POSE_WIDTH), np.float32)
        packed[:, 3:12] = np.eye(3, dtype=np.float32).reshape(9)
        for index, pose in enumerate(poses):
            packed[index, 0:3] = pose.position_mm
            packed[index, 3:12] = _frame(tuple(np.asarray(pose.direction, np.float64).tolist()), float(pose.roll_deg)).reshape(9)
            packed[index, 12] = pose.tip_temperature_c
            packed[index, 13] = pose.energized
        if self._uploaded is None or not np.array_equal(packed, self._uploaded):
            self._upload(packed)
            self._uploaded = packed
        self.poses = poses
        self.any_energized = bool(packed[:, 13].any())

    @ti.kernel
    def _upload(self, packed: ti.types.ndarray()):
        """packed (count, POSE_WIDTH): position (3), rotation rows (9), tip temperature, energized. A handful of
        instruments: on the launching thread (a parallel loop's start costs more, sims.core.backend.serial)."""
        ti.loop_config(serialize=True)
        for k in range(packed.shape[0]):
            for i in ti.static(range(3)):
                self.position[k][i] = packed[k, i]
                for j in ti.static(range(3)):
                    self.rotation[k][i, j] = packed[k, 3 + 3 * i + j]
            self.tip_temperature[k] = packed[k, 12]
            self.energized[k] = ti.cast(packed[k, 13], ti.i32)

    @ti.func
    def distance(self, k, world):
        """Signed distance (mm) from world point to instrument k."""
        p = self.rotation[k] @ (world - self.position[k])
        r, length, width, thickness = self.dims[k][0], self.dims[k][1], self.dims[k][2], self.dims[k][3]
        code = self.shape_code[k]
        d = 0.0
        if code == 0:
            d = p.norm() - r
        elif code == 1:
            h = ti.min(ti.max(p.z, 0.0), length)
            d = (p - ti.Vector([0.0, 0.0, h])).norm() - r
        elif code == 2:
            q = ti.abs(p - ti.Vector([0.0, 0.0, 0.5 * length])) - ti.Vector([0.5 * width, 0.5 * thickness, 0.5 * length])
            d = ti.max(q, 0.0).norm() + ti.min(ti.max(q.x, q.y, q.z), 0.0)
        else:
            d = self._grid_distance(k, p)
        return d

    @ti.func
    def _grid_distance(self, k, p):
        """Trilinear SDF lookup; outside the grid, distance to the grid box plus the value at the box."""
        cells = self.sdf_cells[k]
        g = (p - self.sdf_origin[k]) / self.sdf_spacing[k]
        upper = ti.cast(cells - 1, ti.f32)
        clamped = ti.min(ti.max(g, 0.0), upper)
        outside = (g - clamped).norm() * self.sdf_spacing[k]
        base = ti.min(ti.cast(ti.floor(clamped), ti.i32), cells - 2)
        w = clamped - ti.cast(base, ti.f32)
        value = 0.0
        for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
            weight = (w.x if dx else 1.0 - w.x) * (w.y if dy else 1.0 - w.y) * (w.z if dz else 1.0 - w.z)
            value += weight * self.sdf[k, base.x + dx, base.y + dy, base.z + dz]
        return value + outside
