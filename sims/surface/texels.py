"""TissueSurface: a triangle mesh in millimetres rasterised into texel maps of its UV space.

All (H, W) arrays are in image orientation, the same as the PNGs written: row 0 is the top of the
image (v = 1), column 0 is u = 0. Texel (row r, col c) has its centre at
u = (c + 0.5) / W, v = 1 - (r + 0.5) / H. "Grid coordinates" x = u W (columns) and y = (1 - v) H (rows).
"""

import io
import os
import re
import stat
from dataclasses import dataclass, fields
from importlib import metadata
from pathlib import Path

import numpy as np
import taichi as ti

from sims.core.backend import cache_key, cached_arrays, source_digest, started_arch
from sims.core.quoting import quote

UV_OVERLAP_TOLERANCE = 1e-3  # fraction of covered texels two triangles may both claim before UVs count as overlapping
MAX_COORDINATE_MM = 1e5  # a vertex farther out than this (100 m) is a unit or export error, not tissue
SMALL_MESH_MM = 1.0      # a tissue mesh whose bounding box diagonal is shorter than this is probably in metres
# Mesh files are refused before trimesh parses them when larger than this (parsing an OBJ takes about twice its size
# again: a 1 GB one peaked at 2.2 GB before its error) or declaring more vertices or faces (PLY header, binary STL
# count, OBJ lines). 4 million faces with UVs fit in the byte bound; the meshes here have 10^4-10^5.
MAX_MESH_BYTES = 256 << 20
MAX_MESH_ELEMENTS = 4_000_000
MESH_TYPES = ("obj", "ply", "stl", "glb", "off")  # by suffix; never archives (zip, tar: trimesh would unpack them)
_PLY_ELEMENT = re.compile(rb"^element\s+(\S+)\s+(\d+)", re.MULTILINE)
_BARY_EPS = 1e-5
SURFACE_CACHE_MIN_SIZE = 256      # texel maps of smaller textures build in about the time an entry reads
SURFACE_CACHE_BYTES = 1 << 30     # cached texel maps on disk (a 512² surface: 15 MB, 1024²: 60 MB)
MESH_CACHE_BYTES = 256 << 20      # parsed tissue meshes on disk (the liver lobe: 0.6 MB)
ATLAS_CACHE_BYTES = 256 << 20     # xatlas charts on disk
_CODE_VERSION = source_digest(__file__)  # a change here builds the maps anew
# Triangle shape limits (per triangle, on its texels' sides in mm: the singular values of [dP/dx dP/dy]).
# The explicit heat substep count grows as 1 / (shortest texel side)^2, and a texel's conductance toward its
# neighbours as its longest side / its shortest side, so one sliver (1e-3 mm wide, 10 mm long) asked for
# 44,610 substeps per step at 64^2 texels. A triangle outside these limits is skipped (its texels masked):
_MIN_SIDE_FRACTION = 0.1  # shortest texel side at least this fraction of the median triangle's (100x the substeps at most)
_MAX_TEXEL_ASPECT = 20.0  # texels at most this many times longer than wide (the meshes here measure 2.1 at most)


class MeshError(ValueError):
    """A mesh that cannot be used (unreadable, empty, vertices not finite or absurdly far out, covering no texels)."""


@dataclass(frozen=True)
class MeshArrays:
    """A tissue mesh as the texel maps read it: vertices (V, 3) mm float64, faces (F, 3) int64, uv (V, 2) float64 or
    None (no per-vertex UVs)."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None

    @classmethod
    def of(cls, mesh) -> "MeshArrays":
        """The arrays of a trimesh.Trimesh."""
        return cls(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), mesh_uv(mesh))


@dataclass
class TissueSurface:
    """Texel maps of a mesh. Shapes: (H, W) scalars, (H, W, 3) vectors; H = W = size."""

    size: int
    position_mm: np.ndarray       # (H, W, 3) world position of the texel centre, mm
    normal: np.ndarray            # (H, W, 3) unit normal
    tangent_u: np.ndarray         # (H, W, 3) dP/du, mm per texel step in u
    tangent_v: np.ndarray         # (H, W, 3) dP/dv, mm per texel step in v
    texel_area_mm2: np.ndarray    # (H, W) surface area a texel covers, mm^2 (0 where masked)
    mask: np.ndarray              # (H, W) bool, texel lies on the surface
    fill_index: np.ndarray        # (H, W) int, flat index of the nearest valid texel (gutter fill for display)
    vertices_mm: np.ndarray       # (V, 3) mesh vertices used (split at UV seams)
    faces: np.ndarray             # (F, 3) triangle vertex indices
    uv: np.ndarray                # (V, 2) UVs in [0, 1], OBJ convention (v up)
    uv_source: str                # "mesh" when the file UVs were unique, else "xatlas"
    skipped_triangles: int        # triangles with zero area in UV or in 3D

    @property
    def metric(self) -> np.ndarray:
        """(H, W, 2, 2) first fundamental form in grid coordinates (x = columns, y = rows), mm^2 per texel^2."""
        ex, ey = self.tangent_u, -self.tangent_v
        g = np.empty(self.mask.shape + (2, 2), np.float32)
        g[..., 0, 0] = np.einsum("...i,...i", ex, ex)
        g[..., 0, 1] = g[..., 1, 0] = np.einsum("...i,...i", ex, ey)
        g[..., 1, 1] = np.einsum("...i,...i", ey, ey)
        return g

    @property
    def area_mm2(self) -> float:
        return float(self.texel_area_mm2.sum(dtype=np.float64))

    @property
    def size_warning(self) -> str | None:
        """A warning (one line) when the mesh is under SMALL_MESH_MM across, as a mesh in metres would be; else None.

        A warning, not an error: a small mesh is odd but usable. When its texels are too small for the explicit heat
        scheme the run is refused anyway (sims.heat.cautery.MAX_SUBSTEPS), and this line says why."""
        diagonal = float(np.linalg.norm(np.ptp(self.vertices_mm.astype(np.float64), axis=0)))
        if diagonal >= SMALL_MESH_MM:
            return None
        return f"mesh is {diagonal:.3g} mm across: is it in metres? lengths are in millimetres"


def read_mesh_file(path) -> tuple[bytes, str]:
    """(bytes, trimesh file type) of a mesh file of a type in MESH_TYPES, checked before anything parses it: a regular
    file (a FIFO or a device is refused unread) of at most MAX_MESH_BYTES and MAX_MESH_ELEMENTS. Raises MeshError."""
    kind = Path(path).suffix.lower().lstrip(".")
    if kind not in MESH_TYPES:
        raise MeshError(f"cannot read a mesh of type {quote(Path(path).suffix)}; use one of .{', .'.join(MESH_TYPES)}")
    try:
        with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as handle:  # non-blocking: a FIFO opens at once
            info = os.fstat(handle.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise MeshError("not a regular file")
            if info.st_size > MAX_MESH_BYTES:
                raise MeshError(f"{info.st_size} bytes; a mesh file is at most {MAX_MESH_BYTES} bytes")
            data = handle.read(MAX_MESH_BYTES + 1)
    except OSError as exc:
        raise MeshError(f"cannot read mesh: {exc.strerror or exc}") from None
    if len(data) > MAX_MESH_BYTES:
        raise MeshError(f"more than {MAX_MESH_BYTES} bytes; a mesh file is at most that")
    for what, count in _declared_elements(data, kind):
        if count > MAX_MESH_ELEMENTS:
            raise MeshError(f"{count} {what}; a mesh has at most {MAX_MESH_ELEMENTS}")
    return data, kind


def _declared_elements(data: bytes, kind: str) -> list[tuple[str, int]]:
    """(what, count) of the elements a mesh file declares where that is cheap to read: a PLY header's elements, a
    binary STL's triangle count, an OBJ's vertex and face lines."""
    if kind == "ply":
        header = data[: data.find(b"end_header")] if b"end_header" in data[:65536] else data[:65536]
        return [(f"{name.decode(errors='replace')[:20]} elements", int(count[:20])) for name, count in _PLY_ELEMENT.findall(header)]
    if kind == "stl" and data[:5].lower() != b"solid" and len(data) >= 84:
        return [("triangles", int.from_bytes(data[80:84], "little"))]
    if kind == "obj":
        return [("vertex lines", data.count(b"\nv ") + data.startswith(b"v ")), ("face lines", data.count(b"\nf ") + data.startswith(b"f "))]
    return []


def load_mesh(path):
    """Read a mesh (read_mesh_file: OBJ, PLY, GLB, STL, OFF) as a trimesh.Trimesh without merging UV seams. Raises
    MeshError."""
    return _parse_mesh(*read_mesh_file(path))


def read_tissue_mesh(path) -> MeshArrays:
    """load_mesh's arrays, kept on disk by the file's bytes: a run of a scene read before parses nothing and imports
    no trimesh (0.2-0.3 s of a headless run's start-up). Raises MeshError."""
    data, kind = read_mesh_file(path)

    def parse() -> dict:
        mesh = MeshArrays.of(_parse_mesh(data, kind))
        uv = np.zeros((0, 2)) if mesh.uv is None else mesh.uv
        return {"vertices": mesh.vertices, "faces": mesh.faces, "uv": uv, "has_uv": np.array(mesh.uv is not None)}

    key = cache_key(_CODE_VERSION, metadata.version("trimesh"), kind, np.frombuffer(data, np.uint8))
    stored = cached_arrays("meshes", key, ("vertices", "faces", "uv", "has_uv"), parse, MESH_CACHE_BYTES)
    mesh = MeshArrays(stored["vertices"], stored["faces"], stored["uv"] if bool(stored["has_uv"]) else None)
    check_vertices(mesh.vertices)
    return mesh


def _parse_mesh(data: bytes, kind: str):
    """A trimesh.Trimesh of a mesh file's bytes (read_mesh_file): trimesh reads no other file (an OBJ's mtllib and
    textures are not needed). Raises MeshError."""
    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=kind, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"cannot read mesh: {(str(exc).strip() or type(exc).__name__).splitlines()[0][:120]}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError("the file holds no triangles")
    check_vertices(mesh.vertices)
    return mesh


def check_vertices(vertices) -> None:
    """Raise MeshError unless every vertex (V, 3) is finite and within MAX_COORDINATE_MM of the origin on every axis.

    Checked before anything else uses the mesh: xatlas never returns on a vertex at 1e39 (float32 infinity)."""
    vertices = np.asarray(vertices, np.float64)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        first = ", ".join(f"{value:g}" for value in vertices[bad][0])
        raise MeshError(f"{int(bad.sum())} of {len(vertices)} vertices are not finite (the first at {first})")
    largest = float(np.abs(vertices).max(initial=0.0))
    if largest > MAX_COORDINATE_MM:
        raise MeshError(f"a vertex coordinate of {largest:.3g} mm found; meshes are in millimetres "
                        f"(at most {MAX_COORDINATE_MM:g} mm from the origin)")


def mesh_uv(mesh) -> np.ndarray | None:
    """The mesh's per-vertex UVs (V, 2), or None when it has none."""
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        return None
    return np.asarray(uv, np.float64)


def build_surface(mesh, size: int) -> TissueSurface:
    """Rasterise `mesh` (MeshArrays or a trimesh.Trimesh) into size x size texel maps, using its UVs when they are
    unique and the triangles they make the maps skip (_triangle_frames) hold at most UV_OVERLAP_TOLERANCE of the
    area, else an xatlas atlas. Kept on disk (_cached_surface). Raises MeshError (check_vertices; no texel covered)."""
    check_vertices(mesh.vertices)
    arrays = mesh if isinstance(mesh, MeshArrays) else MeshArrays.of(mesh)
    vertices, faces, uv = arrays.vertices, arrays.faces, arrays.uv
    return _cached_surface(size, lambda: _build_surface(vertices, faces, uv, size), vertices, faces, uv)


def _build_surface(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None, size: int) -> TissueSurface:
    """build_surface from the mesh's vertices (V, 3) mm, faces (F, 3) and UVs (V, 2) or None."""
    uv_source = "mesh"
    owner = None
    if uv is not None and np.isfinite(uv).all() and uv.min() >= -1e-6 and uv.max() <= 1 + 1e-6:
        owner, overlap = _rasterise(vertices, faces, uv, size)
        covered = max(int((owner >= 0).sum()), 1)
        if overlap / covered > UV_OVERLAP_TOLERANCE or _skipped_area_fraction(vertices, faces, uv, size) > UV_OVERLAP_TOLERANCE:
            owner = None
    if owner is None:
        vertices, faces, uv = atlas_uv(vertices, faces, size)
        uv_source = "xatlas"
        owner, _ = _rasterise(vertices, faces, uv, size)
    return _texel_maps(vertices, faces, uv, owner, size, uv_source)


def surface_at(surface: TissueSurface, size: int) -> TissueSurface:
    """The same triangles and UVs as `surface` rasterised into size x size texel maps (a coarser or finer grid of the
    same texture space: texel (r, c) of one lies at the same u, v as the matching grid coordinates of the other).
    Kept on disk (_cached_surface)."""
    vertices, faces, uv = (np.asarray(a, np.float64) for a in (surface.vertices_mm, surface.faces, surface.uv))
    faces = faces.astype(np.int64)

    def build():
        owner, _ = _rasterise(vertices, faces, uv, size)
        return _texel_maps(vertices, faces, uv, owner, size, surface.uv_source)

    return _cached_surface(size, build, vertices, faces, uv, surface.uv_source)


def _cached_surface(size: int, build, *inputs) -> TissueSurface:
    """build() (a TissueSurface of size^2 texels made from `inputs`: arrays and strings) or the same maps read back
    from cache_dir()/surfaces, keyed by the inputs, the size, this file's code, NumPy and Taichi versions and the
    device (the rasterising kernel runs there). A 512² plane's maps took 0.3-0.5 s to build, 0.02 s to read.
    Sizes under SURFACE_CACHE_MIN_SIZE are always built; entries past SURFACE_CACHE_BYTES go, least recently used first."""
    if size < SURFACE_CACHE_MIN_SIZE:
        return build()
    key = cache_key(_CODE_VERSION, np.__version__, ti.__version__, started_arch(), size, *inputs)
    names = tuple(field.name for field in fields(TissueSurface))
    values = cached_arrays("surfaces", key, names, lambda: vars(build()), SURFACE_CACHE_BYTES)
    return TissueSurface(**{**values, "size": int(values["size"]), "uv_source": str(values["uv_source"]),
                            "skipped_triangles": int(values["skipped_triangles"])})


def _skipped_area_fraction(vertices, faces, uv, size) -> float:
    """Fraction of the 3D surface area on triangles the texel maps skip (zero area in UV, too thin, too stretched)."""
    tri = vertices[faces]
    area_3d = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    valid = _triangle_frames(vertices, faces, uv, size)[3]
    return float(area_3d[~valid].sum() / max(area_3d.sum(), 1e-30))


def atlas_uv(vertices: np.ndarray, faces: np.ndarray, size: int):
    """Unique UVs from xatlas (cached on disk): (vertices (V', 3), faces (F, 3), uv (V', 2)).

    The cache entry is complete or absent (backend.cached_arrays); an entry that cannot be read all the same
    (truncated, corrupt) is deleted and the atlas computed again."""
    check_vertices(vertices)
    names = ("vertices", "faces", "uv")
    stored = cached_arrays("atlas", cache_key(vertices.astype(np.float64), faces.astype(np.int64), size), names,
                           lambda: dict(zip(names, _compute_atlas(vertices, faces, size))), ATLAS_CACHE_BYTES)
    return tuple(stored[name] for name in names)


def _compute_atlas(vertices: np.ndarray, faces: np.ndarray, size: int):
    """xatlas charts packed for a size x size texture: (vertices (V', 3), faces (F, 3), uv (V', 2))."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = 2
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    vmapping, indices, uv = atlas[0]
    return vertices[vmapping], indices.astype(np.int64), uv.astype(np.float64)


def _grid_coords(uv: np.ndarray, size: int) -> np.ndarray:
    """UV (.., 2) -> grid coordinates (x = u W, y = (1 - v) H)."""
    return np.stack([uv[..., 0] * size, (1.0 - uv[..., 1]) * size], axis=-1)


@ti.kernel
def _claim_texels(tri_xy: ti.types.ndarray(), owner: ti.types.ndarray(), strict: ti.types.ndarray(), eps: ti.f32):
    """Each texel centre inside a triangle (with tolerance) takes the lowest triangle id; count strict overlaps."""
    height, width = owner.shape[0], owner.shape[1]
    for f in range(tri_xy.shape[0]):
        a = ti.Vector([tri_xy[f, 0, 0], tri_xy[f, 0, 1]])
        b = ti.Vector([tri_xy[f, 1, 0], tri_xy[f, 1, 1]])
        c = ti.Vector([tri_xy[f, 2, 0], tri_xy[f, 2, 1]])
        area = (b - a).cross(c - a)
        x0 = ti.max(ti.cast(ti.floor(ti.min(a.x, b.x, c.x) - 0.5), ti.i32), 0)
        x1 = ti.min(ti.cast(ti.ceil(ti.max(a.x, b.x, c.x) - 0.5), ti.i32), width - 1)
        y0 = ti.max(ti.cast(ti.floor(ti.min(a.y, b.y, c.y) - 0.5), ti.i32), 0)
        y1 = ti.min(ti.cast(ti.ceil(ti.max(a.y, b.y, c.y) - 0.5), ti.i32), height - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                p = ti.Vector([x + 0.5, y + 0.5])
                w0 = (b - p).cross(c - p) / area
                w1 = (c - p).cross(a - p) / area
                w2 = 1.0 - w0 - w1
                lowest = ti.min(w0, w1, w2)
                if lowest >= -eps:
                    ti.atomic_min(owner[y, x], f)
                if lowest > eps:
                    ti.atomic_add(strict[y, x], 1)


def _triangle_frames(vertices, faces, uv, size):
    """Per triangle: grid coords (F, 3, 2), dP/dx and dP/dy (F, 3) in mm per texel, validity (F,).

    Valid: a UV area above 1e-9 texel^2 and texels within the shape limits (_MIN_SIDE_FRACTION, _MAX_TEXEL_ASPECT;
    a triangle with zero area in 3D has a zero shortest side)."""
    tri_xy = _grid_coords(uv[faces], size)
    tri_p = vertices[faces]
    d1, d2 = tri_xy[:, 1] - tri_xy[:, 0], tri_xy[:, 2] - tri_xy[:, 0]
    e1, e2 = tri_p[:, 1] - tri_p[:, 0], tri_p[:, 2] - tri_p[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    mapped = (np.abs(det) > 1e-9) & np.isfinite(det)
    safe = np.where(mapped, det, 1.0)
    # [e1 e2] = [Px Py] [[d1x d2x], [d1y d2y]]  ->  solve for Px, Py
    px = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe[:, None]
    py = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / safe[:, None]
    shortest, longest = _texel_sides(px, py)
    floor = _MIN_SIDE_FRACTION * (np.median(shortest[mapped]) if mapped.any() else 0.0)
    valid = mapped & (shortest > 0.0) & (shortest >= floor) & (longest <= _MAX_TEXEL_ASPECT * shortest)
    return tri_xy, px, py, valid


def _texel_sides(px: np.ndarray, py: np.ndarray):
    """Shortest and longest side (mm) of texels spanned by dP/dx, dP/dy (N, 3): the singular values of [px py]."""
    g11, g22, g12 = (px * px).sum(axis=1), (py * py).sum(axis=1), (px * py).sum(axis=1)
    trace, det = g11 + g22, np.maximum(g11 * g22 - g12**2, 0.0)
    longest = np.sqrt(0.5 * (trace + np.sqrt(np.maximum(trace**2 - 4.0 * det, 0.0))))
    return np.sqrt(det) / np.maximum(longest, 1e-300), longest


def _rasterise(vertices, faces, uv, size):
    """Owner triangle per texel (H, W) (-1 outside) and the number of texels two triangles both claim."""
    tri_xy, _, _, valid = _triangle_frames(vertices, faces, uv, size)
    ids = np.flatnonzero(valid)
    owner = np.full((size, size), len(ids), np.int32)
    strict = np.zeros((size, size), np.int32)
    if len(ids):
        _claim_texels(np.ascontiguousarray(tri_xy[ids], np.float32), owner, strict, _BARY_EPS)
    inside = owner < len(ids)
    owner_faces = np.full((size, size), -1, np.int64)
    owner_faces[inside] = ids[owner[inside]]
    return owner_faces, int((strict > 1).sum())


def welded_normal_sums(vertices, faces) -> np.ndarray:
    """Per vertex, the sum (V, 3) of the cross products of its triangles' edges (area-weighted normals), summed over
    all vertices at the same position, so UV seams do not split normals."""
    vertices = np.asarray(vertices, np.float64)
    _, weld = np.unique(vertices.round(6), axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    acc = np.zeros((weld.max() + 1, 3))
    for corner in range(3):
        np.add.at(acc, weld[faces[:, corner]], face_n)
    return acc[weld]


def _vertex_normals(vertices, faces):
    """Unit area-weighted normals (V, 3), smooth across UV seams."""
    normals = welded_normal_sums(vertices, faces)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)


def _scatter(values: np.ndarray, rows, cols, size: int) -> np.ndarray:
    """Per-texel values (N, ...) -> (H, W, ...) float32 grid, zero elsewhere."""
    out = np.zeros((size, size) + values.shape[1:], np.float32)
    out[rows, cols] = values
    return out


def _texel_maps(vertices, faces, uv, owner, size, uv_source) -> TissueSurface:
    tri_xy, px, py, valid = _triangle_frames(vertices, faces, uv, size)
    rows, cols = np.nonzero(owner >= 0)
    f = owner[rows, cols]
    p = np.stack([cols + 0.5, rows + 0.5], axis=1)
    a, b, c = tri_xy[f, 0], tri_xy[f, 1], tri_xy[f, 2]

    def cross2(u, w):
        return u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]

    area = cross2(b - a, c - a)
    w0, w1 = cross2(b - p, c - p) / area, cross2(c - p, a - p) / area
    bary = np.clip(np.stack([w0, w1, 1.0 - w0 - w1], axis=1), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    corners = faces[f]
    position = np.einsum("nk,nkd->nd", bary, vertices[corners])
    normal = np.einsum("nk,nkd->nd", bary, _vertex_normals(vertices, faces)[corners])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    face_normal = np.cross(vertices[corners[:, 1]] - vertices[corners[:, 0]], vertices[corners[:, 2]] - vertices[corners[:, 0]])
    face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-30)
    normal = np.where(length > 1e-6, normal / np.maximum(length, 1e-30), face_normal)
    texel_area = np.linalg.norm(np.cross(px[f], py[f]), axis=1)

    keep = np.isfinite(position).all(axis=1) & np.isfinite(normal).all(axis=1)
    rows, cols, f = rows[keep], cols[keep], f[keep]
    if len(rows) == 0:
        raise MeshError(f"the mesh covers no texel of a {size}x{size} texture")
    mask = np.zeros((size, size), bool)
    mask[rows, cols] = True
    from scipy import ndimage  # only where maps are built: a cached surface needs none of scipy.ndimage

    _, (near_r, near_c) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return TissueSurface(
        size=size,
        position_mm=_scatter(position[keep], rows, cols, size),
        normal=_scatter(normal[keep], rows, cols, size),
        tangent_u=_scatter(px[f], rows, cols, size),
        tangent_v=_scatter(-py[f], rows, cols, size),
        texel_area_mm2=_scatter(texel_area[keep], rows, cols, size),
        mask=mask,
        fill_index=(near_r * size + near_c).astype(np.int64),
        vertices_mm=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        uv=uv.astype(np.float32),
        uv_source=uv_source,
        skipped_triangles=int((~valid).sum()),
    )
