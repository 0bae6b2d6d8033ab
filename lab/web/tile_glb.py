"""One texture tile of the tissue mesh as a GLB: its quantized geometry with the normal ghosts, and its maps as a glTF
PBR material (lab.web.stream cuts the mesh into these tiles and decides when each is published).

Materials. Every tile is a glTF PBR material: the base colour (sRGB), and when `update` gets them a
tangent-space normal map (R = +u, G = up in the image = +v, B = out of the surface, 128 = 0; three.js
derives the tangents, none are sent) and a roughness map (a greyscale PNG: glTF reads roughness from
G and metalness from B, and metallicFactor 0 cancels the latter; roughnessFactor 1). A tile is
re-published when any of its crops changed, ranked by the largest change over the maps; of a
published tile only the maps whose crop changed are encoded again. The normal map goes at the
colour's resolution, the roughness at half of it (normal_divisor=1, roughness_divisor=2; half: 2 x 2
texel means over a crop box aligned to even texels, so neighbouring tiles average the same texels and
meet without a step), both as PNG at zlib level 3, the fastest level's best packing (level 6 was 3 %
smaller on the hemostasis scene's bleeding but took 1.6 times as long to encode: 67 against 42 ms per
update of 30 tiles). Measured on the default scene (liver patch, 512^2, 8 x 8 tiles) with the look's maps
(sims.scene.assembly.Scene.material_maps) in software WebGL at the lab's view and in a close-up: the
roughness at half resolution changed the picture by 0.3-0.5 levels on average (99th percentile 3),
not visibly; the normal map at half resolution visibly softened the tissue's fine wrinkles (0.9-1.8
levels on average, 99th percentile 11-15), so it stays at full. Bytes per tile: colour 6.6 kB,
normal 5.6 kB (6.5 at level 1, 1.7 at half resolution), roughness 0.7 kB (2.3 at full), geometry and
JSON 7.9 kB; at the lab's pace (10 updates/s, 2.3 tiles per update on average) 49 kB per update
(median 43), against 40 kB (median 35) for the colour alone before the maps and quantization.

Geometry (KHR_mesh_quantization, listed as required): positions are int16 grid integers of one
mesh-wide grid (Grid: node translation plus one uniform scale, so the normals three.js recomputes
keep their directions and every tile has the same transform), UVs normalized uint16 over the crop,
normals declared as an accessor of zeros without bytes (so three.js shades smoothly, not flat) and no
tangents. The normal ghosts (normal_ghosts) are computed in those integers, and their morph target
moves each ghost corner onto its vertex by an exact int16 delta. This cut a tile's geometry from 8.6
to 5.9 kB on the default scene.
"""
from __future__ import annotations

import json
import struct

import numpy as np

_LINEAR, _CLAMP = 9729, 33071  # glTF sampler constants
_SHORT, _UNSIGNED_SHORT, _UNSIGNED_INT, _FLOAT = 5122, 5123, 5125, 5126  # glTF component types
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
QUANTIZATION = "KHR_mesh_quantization"
INT16_LIMIT = 32767   # quantized positions and ghost corners stay in [-32767, 32767]
GRID_MARGIN = 1.1     # the grid's half range over the mesh's half extent at first: room for the ghosts' corners



class Grid:
    """The mesh-wide quantization grid: position = offset + quantum * integer, the integers int16. One grid for every
    tile, so a vertex shared by two tiles has the same integers in both and every tile node the same transform: their
    common edges rasterise identically (a per-tile grid would round a shared vertex two ways and open hairline cracks).
    The quantum comes from the mesh's extent: 0.34 um for a 20 mm mesh, 2.5 um for 150 mm."""

    def __init__(self, positions: np.ndarray, margin: float = GRID_MARGIN):
        low, high = positions.min(axis=0), positions.max(axis=0)
        self.offset = 0.5 * (low + high)
        self.quantum = max(float((high - low).max()) * 0.5 * margin / INT16_LIMIT, 1e-9)

    def quantize(self, positions: np.ndarray) -> np.ndarray:
        """(N, 3) int64 grid integers of positions (mm)."""
        return np.rint((np.asarray(positions, np.float64) - self.offset) / self.quantum).astype(np.int64)

    def coarser(self) -> "Grid":
        grid = object.__new__(Grid)
        grid.offset, grid.quantum = self.offset, self.quantum * 1.25
        return grid


def face_cross(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) cross products of the triangles' edges (twice the area times the unit normal), as three.js sums them.
    Exact for integer positions (int64 in, int64 out)."""
    tri = np.asarray(positions)[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def vertex_sums(positions: np.ndarray, faces: np.ndarray, weld: np.ndarray | None = None) -> np.ndarray:
    """Per vertex, the sum of its triangles' edge cross products (three.js computeVertexNormals before normalizing);
    with weld (a group id per vertex), summed over each vertex's group."""
    cross = face_cross(positions, faces)
    if weld is not None:
        faces = weld[faces]
    sums = np.zeros((int(weld.max(initial=-1)) + 1 if weld is not None else len(positions), 3), cross.dtype)
    for corner in range(3):
        np.add.at(sums, faces[:, corner], cross)
    return sums if weld is None else sums[weld]


# the integer corner offsets tried around the rounded ghost vectors: 27 for each of its two corners
NUDGES = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)


def normal_ghosts(positions: np.ndarray, faces: np.ndarray, target: np.ndarray):
    """Invisible triangles that make a tile's recomputed normals equal the whole mesh's; all in grid integers.

    The viser client recomputes the vertex normals of every GLB mesh from the mesh's own triangles
    (three.js computeVertexNormals: per vertex index, the sum of the adjacent triangles' edge cross
    products) and ignores any normals sent. A vertex on a tile border misses the triangles of the
    neighbouring tile (across a UV seam, those of its other copies too) and would shade differently
    from its neighbour. For each such vertex p we add one ghost triangle (p, p + a, p + b) with
    a x b about m, the missing sum (exact in integers here: positions are grid integers): a and b
    are L t1 and L t2 (t1 x t2 = m / |m|, L^2 = |m|) rounded to integers, then the pair among the
    27 x 27 integer neighbours of those whose cross product is closest to m. A morph target (weight 1)
    moves the two new corners back onto p, by integer deltas, so the ghost is drawn with zero area and
    never shows, while computeVertexNormals (which reads the un-morphed positions) counts it.
    positions: (n, 3) int64; target: (n, 3) int64 welded sums of the whole mesh for these vertices.
    Returns (new corners (2k, 3) int64, the vertex each copies its UV from (2k,), ghost faces (k, 3)
    indexed after the existing vertices, morph deltas of the new corners (2k, 3) int64)."""
    missing = target - vertex_sums(positions, faces)
    use = np.flatnonzero(np.any(missing != 0, axis=1))
    m = missing[use].astype(np.float64)
    size = np.linalg.norm(m, axis=1)
    n = m / size[:, None]
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    length = np.sqrt(size)[:, None]
    a0, b0 = np.rint(length * t1).astype(np.int64), np.rint(length * t2).astype(np.int64)
    best_a, best_b = a0.copy(), b0.copy()
    best = np.full(len(use), np.inf)
    for nudge in NUDGES:  # 27 choices of a, each against the 27 of b
        a = a0 + nudge
        b = b0[:, None, :] + NUDGES[None, :, :]
        error = np.linalg.norm((np.cross(a[:, None, :], b) - missing[use][:, None, :]).astype(np.float64), axis=2)
        pick = error.argmin(axis=1)
        better = error[np.arange(len(use)), pick] < best
        best[better] = error[better, pick[better]]
        best_a[better], best_b[better] = a[better], b[better, pick[better]]
    keep = np.any(np.cross(best_a, best_b) != 0, axis=1)  # a ghost that would add nothing is left out
    use, best_a, best_b = use[keep], best_a[keep], best_b[keep]
    p = positions[use]
    extra = np.stack([p + best_a, p + best_b], axis=1).reshape(-1, 3)
    base = len(positions) + 2 * np.arange(len(use))
    ghost_faces = np.stack([use, base, base + 1], axis=1)
    source = np.repeat(use, 2)
    delta = positions[source] - extra
    return extra, source, ghost_faces, delta


def pad4(data: bytes, fill: bytes = b"\x00") -> bytes:
    return data + fill * (-len(data) % 4)


class TileGeometry:
    """One tile's triangles, its crop box in a (H, W) texture, and the GLB bytes except the images.

    Geometry under KHR_mesh_quantization (docs/model/streaming.md, "What a tile's GLB holds"): POSITION as int16 (not normalized; a 4th short pads each
    vertex to 8 bytes, glTF's 4-byte alignment of vertex attributes) under the node's translation and uniform scale
    (the mesh-wide Grid), TEXCOORD_0 as normalized uint16 over the crop; NORMAL as zeros without bytes (the viser client
    recomputes the normals; without the attribute three.js would flat-shade) and no TANGENT (three.js derives the
    normal map's tangents). The normal ghosts' morph target is a sparse int16 accessor in grid
    units: a ghost corner plus its delta is its vertex exactly.
    maps: the texture maps the tile carries, in the order of its images: "color", then "normal" and "roughness" if sent.
    even: align the crop box to even texels (the normal and roughness maps go at half resolution)."""

    def __init__(self, positions, uv, faces, morph_ids, morph_delta, grid: Grid, shape, margin: int, roughness: float,
                 maps=("color",), even: bool = False):
        height, width = shape
        x = uv[:, 0].astype(np.float64) * width
        y = (1.0 - uv[:, 1].astype(np.float64)) * height  # image rows: row 0 is v = 1
        self.c0 = max(int(np.floor(x.min())) - margin, 0)
        self.c1 = min(int(np.ceil(x.max())) + margin, width)
        self.r0 = max(int(np.floor(y.min())) - margin, 0)
        self.r1 = min(int(np.ceil(y.max())) + margin, height)
        if even:  # may reach one texel past an odd-sized image: update pads the maps by their edge texels then
            self.c0, self.r0 = self.c0 - self.c0 % 2, self.r0 - self.r0 % 2
            self.c1, self.r1 = self.c1 + self.c1 % 2, self.r1 + self.r1 % 2
        self.maps = tuple(maps)
        # glTF texture coordinates: (0, 0) is the top-left texel corner of the image
        st = np.stack([(x - self.c0) / (self.c1 - self.c0), (y - self.r0) / (self.r1 - self.r0)], axis=1)
        st = np.clip(np.rint(st * 65535.0), 0, 65535).astype(np.uint16)
        index_type, index_dtype = (_UNSIGNED_SHORT, np.uint16) if len(positions) < 65536 else (_UNSIGNED_INT, np.uint32)
        chunks, views, accessors = [], [], []
        offset = 0

        def view(data: bytes, target=None, stride=None):
            nonlocal offset
            entry = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
            if stride is not None:
                entry["byteStride"] = stride
            if target is not None:
                entry["target"] = target
            views.append(entry)
            chunks.append(pad4(data))
            offset += len(chunks[-1])
            return len(views) - 1

        positions = np.asarray(positions, np.int64)
        padded = np.zeros((len(positions), 4), np.int16)
        padded[:, :3] = positions
        attributes = {}
        accessors.append({"bufferView": view(padded.tobytes(), _ARRAY_BUFFER, stride=8), "componentType": _SHORT,
                          "count": len(positions), "type": "VEC3",
                          "min": positions.min(axis=0).tolist(), "max": positions.max(axis=0).tolist()})
        attributes["POSITION"] = len(accessors) - 1
        accessors.append({"bufferView": view(st.tobytes(), _ARRAY_BUFFER), "componentType": _UNSIGNED_SHORT,
                          "normalized": True, "count": len(st), "type": "VEC2"})
        attributes["TEXCOORD_0"] = len(accessors) - 1
        # NORMAL with no bufferView: zeros, and no bytes. three.js's glTF loader flat-shades a primitive without normals
        # (each triangle lit by its own plane: the mesh's facets show in every sharp highlight, such as wet blood's);
        # with the attribute present it shades smoothly, and the viser client recomputes its values from the triangles
        # (the ghosts above make those the whole mesh's)
        accessors.append({"componentType": _FLOAT, "count": len(positions), "type": "VEC3"})
        attributes["NORMAL"] = len(accessors) - 1
        accessors.append({"bufferView": view(np.ascontiguousarray(faces, index_dtype).tobytes(), _ELEMENT_ARRAY_BUFFER),
                          "componentType": index_type, "count": int(np.size(faces)), "type": "SCALAR"})
        indices = len(accessors) - 1
        primitive = {"attributes": attributes, "indices": indices, "material": 0}
        mesh = {"primitives": [primitive]}
        if len(morph_ids):
            # a sparse morph target: zero everywhere except the ghost corners (see normal_ghosts); int16 grid units,
            # the same transform as POSITION (KHR_mesh_quantization allows SHORT morph displacements)
            delta = np.asarray(morph_delta, np.int64)
            accessors.append({"componentType": _SHORT, "count": len(positions), "type": "VEC3",
                              "min": np.minimum(delta.min(axis=0), 0).tolist(), "max": np.maximum(delta.max(axis=0), 0).tolist(),
                              "sparse": {"count": len(morph_ids),
                                         "indices": {"bufferView": view(np.ascontiguousarray(morph_ids, index_dtype).tobytes()), "componentType": index_type},
                                         "values": {"bufferView": view(delta.astype(np.int16).tobytes())}}})
            primitive["targets"] = [{"POSITION": len(accessors) - 1}]
            mesh["weights"] = [1.0]
        self._geometry = b"".join(chunks)
        material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": roughness}}
        if "normal" in self.maps:
            material["normalTexture"] = {"index": self.maps.index("normal")}
        if "roughness" in self.maps:
            # glTF reads roughness from G and metalness from B: a greyscale image gives both the value, and metalness
            # is multiplied by metallicFactor 0
            material["pbrMetallicRoughness"]["roughnessFactor"] = 1.0
            material["pbrMetallicRoughness"]["metallicRoughnessTexture"] = {"index": self.maps.index("roughness")}
        self._first_image_view = len(views)
        self._json = {
            "asset": {"version": "2.0", "generator": "tissue-lab stream"},
            "extensionsUsed": [QUANTIZATION],
            "extensionsRequired": [QUANTIZATION],
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "translation": [float(v) for v in grid.offset], "scale": [grid.quantum] * 3}],
            "meshes": [mesh],
            "materials": [material],
            "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR, "wrapS": _CLAMP, "wrapT": _CLAMP}],
            "textures": [{"sampler": 0, "source": k} for k in range(len(self.maps))],
            "images": [{"bufferView": self._first_image_view + k, "mimeType": "image/png"} for k in range(len(self.maps))],
            "accessors": accessors,
            "bufferViews": views,
            "buffers": [{"byteLength": 0}],
        }

    def crop(self, image: np.ndarray) -> np.ndarray:
        return image[self.r0:self.r1, self.c0:self.c1]

    def blocks(self, block: int) -> tuple[slice, slice]:
        """(rows, cols) slices of the block x block texel blocks this crop meets."""
        return slice(self.r0 // block, -(-self.r1 // block)), slice(self.c0 // block, -(-self.c1 // block))

    def glb(self, images) -> bytes:
        """The tile's GLB with these encoded maps: [(bytes, mime)], one per map in self.maps order."""
        doc = self._json
        doc["bufferViews"] = doc["bufferViews"][:self._first_image_view]
        offset, chunks = len(self._geometry), [self._geometry]
        for image, (data, mime) in zip(doc["images"], images):
            image["mimeType"] = mime
            doc["bufferViews"].append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
            chunks.append(pad4(data))
            offset += len(chunks[-1])
        binary = b"".join(chunks)
        doc["buffers"][0]["byteLength"] = len(binary)
        text = pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
        total = 12 + 8 + len(text) + 8 + len(binary)
        return b"".join([struct.pack("<4sII", b"glTF", 2, total), struct.pack("<I4s", len(text), b"JSON"), text, struct.pack("<I4s", len(binary), b"BIN\x00"), binary])

