"""Stream a changing texture on a static mesh to every browser (viser) without blanking it.

viser has no message that updates a mesh texture in place, and re-sending a mesh blanks it in the
browser while the new GLB parses (DESIGN section 5). So the mesh is cut into K x K UV tiles (a
triangle goes to the tile of its UV centroid); every tile is its own GLB node textured with the crop
of the texture over its UV box plus a margin. An update re-sends only the tiles whose crop changed,
each as a NEW node added visible over the old one (the newest identical copy draws last and wins);
the old node is removed at least `hide_after_s` later and only once that browser has applied and
drawn the new one (lab.client_sync: a browser that draws a frame every few seconds would otherwise
get the add and the remove in one batch and show a hole while the new node parses).

Publishing is shared, delivery is per browser. An update publishes changed tiles at most
`max_tiles_per_s` (a tile that changes faster is published later with its then newest crop, so
stale textures are dropped instead of queued); when the budget runs short the tiles that changed
most go first (a fresh burn before a fading one, weighed by how long each has waited), and a change
of a level or two (cooling tissue fades by one level per update) waits `settle_s` to add up before
it takes a slot. Each published tile is encoded once into a GLB. Then every browser gets, through
viser's per-client scene (`client.scene`), the newest published version of each tile it lacks, as
a node of its own drawn from its own capped pool of names (which keeps viser's buffers bounded); its
replaced nodes wait for its own confirmations only. A tile is replaced for a browser only once that
browser has applied the tile's current node: one that applies a batch every few seconds gets the
newest version then, instead of every version in between (each of which it would parse, and draw
under its successor until removed). A browser that is slow, frozen or silent (never answers the
sync request) gets replacements only as fast as it applies them, or none, and its names run out
before viser's queue for it grows: it slows only itself. A new browser gets every tile at
once; one that leaves takes its nodes with it.

The trade-off against one shared scene (`server.scene`, as before): a GLB goes through viser's
message path once per browser instead of once; that costs little, since viser serializes and
compresses every message per connection anyway (one producer per client), and the tiles no longer
sit in viser's persistent broadcast buffer that every new browser replays. With a shared scene, a
node can only be removed once every browser has drawn its successor, so one browser that never
answers held every removal for max_hide_s (15 s) and dried up the shared pool: a normal browser's
stream fell from 21 to 4 tiles/s. Per browser, node names and confirmations are private, and the
normal browser keeps its full rate.

Call `update` and `close` from one thread (the simulation thread); a lock makes a `close` from
another thread safe too.
"""
from __future__ import annotations

import concurrent.futures
import io
import json
import os
import struct
import threading
import time
import warnings
from dataclasses import dataclass

import numpy as np
from PIL import Image

from lab.client_sync import ClientSync
from sims.surface import welded_normal_sums

_MARGIN_TEXELS = 2
# a browser left between the stream listing it and sending to it: nothing is lost, it is dropped on the next update
warnings.filterwarnings("ignore", message="Queued a (GlbMessage|FrameMessage) on a closed connection")
_LINEAR, _CLAMP = 9729, 33071  # glTF sampler constants


def _face_cross(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) cross products of the triangles' edges (twice the area times the unit normal), as three.js sums them."""
    tri = np.asarray(positions, np.float64)[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def _normal_ghosts(positions: np.ndarray, faces: np.ndarray, target: np.ndarray):
    """Invisible triangles that make a tile's recomputed normals equal the whole mesh's.

    The viser client recomputes the vertex normals of every GLB mesh from the mesh's own triangles
    (three.js computeVertexNormals: per vertex index, the sum of the adjacent triangles' edge cross
    products) and ignores any normals sent. A vertex on a tile border misses the triangles of the
    neighbouring tile (across a UV seam, those of its other copies too) and would shade differently
    from its neighbour. For each such vertex p we add one ghost triangle (p, p + L t1, p + L t2) with
    t1 x t2 = m / |m| and L^2 = |m|, m the missing sum: its cross product is exactly m. A morph
    target (weight 1) moves the two new corners back onto p, so the ghost is drawn with zero area and
    never shows, while computeVertexNormals (which reads the un-morphed positions) counts it.
    Returns (new corner positions (2k, 3), the vertex each copies its UV from (2k,), ghost faces (k, 3)
    indexed after the existing vertices, morph deltas of the new corners (2k, 3))."""
    own = np.zeros((len(positions), 3))
    cross = _face_cross(positions, faces)
    for corner in range(3):
        np.add.at(own, faces[:, corner], cross)
    missing = target - own
    size = np.linalg.norm(missing, axis=1)
    use = np.flatnonzero(size > 1e-5 * np.maximum(np.linalg.norm(target, axis=1), 1e-30))
    n = missing[use] / np.maximum(size[use, None], 1e-30)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    length = np.sqrt(size[use])[:, None]
    p = np.asarray(positions, np.float64)[use]
    extra = np.stack([p + length * t1, p + length * t2], axis=1).reshape(-1, 3).astype(np.float32)
    base = len(positions) + 2 * np.arange(len(use))
    ghost_faces = np.stack([use, base, base + 1], axis=1)
    source = np.repeat(use, 2)
    delta = np.asarray(positions, np.float32)[source] - extra
    return extra, source, ghost_faces, delta


def _pad4(data: bytes, fill: bytes = b"\x00") -> bytes:
    return data + fill * (-len(data) % 4)


class _TileGeometry:
    """One tile's triangles, its crop box in a (H, W) texture, and the GLB bytes except the image."""

    def __init__(self, positions, uv, faces, morph_ids, morph_delta, shape, margin: int, roughness: float):
        height, width = shape
        x = uv[:, 0].astype(np.float64) * width
        y = (1.0 - uv[:, 1].astype(np.float64)) * height  # image rows: row 0 is v = 1
        self.c0 = max(int(np.floor(x.min())) - margin, 0)
        self.c1 = min(int(np.ceil(x.max())) + margin, width)
        self.r0 = max(int(np.floor(y.min())) - margin, 0)
        self.r1 = min(int(np.ceil(y.max())) + margin, height)
        # glTF texture coordinates: (0, 0) is the top-left texel corner of the image
        st = np.stack([(x - self.c0) / (self.c1 - self.c0), (y - self.r0) / (self.r1 - self.r0)], axis=1).astype(np.float32)
        index_type, index_dtype = (5123, np.uint16) if len(positions) < 65536 else (5125, np.uint32)
        chunks, views, accessors = [], [], []
        offset = 0

        def view(data: bytes, target=None):
            nonlocal offset
            entry = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
            if target is not None:
                entry["target"] = target
            views.append(entry)
            chunks.append(_pad4(data))
            offset += len(chunks[-1])
            return len(views) - 1

        positions = np.ascontiguousarray(positions, np.float32)
        attributes = {}
        accessors.append({"bufferView": view(positions.tobytes(), 34962), "componentType": 5126, "count": len(positions), "type": "VEC3",
                          "min": positions.min(axis=0).tolist(), "max": positions.max(axis=0).tolist()})
        attributes["POSITION"] = len(accessors) - 1
        accessors.append({"bufferView": view(st.tobytes(), 34962), "componentType": 5126, "count": len(st), "type": "VEC2"})
        attributes["TEXCOORD_0"] = len(accessors) - 1
        accessors.append({"bufferView": view(np.ascontiguousarray(faces, index_dtype).tobytes(), 34963), "componentType": index_type, "count": int(faces.size), "type": "SCALAR"})
        indices = len(accessors) - 1
        primitive = {"attributes": attributes, "indices": indices, "material": 0}
        mesh = {"primitives": [primitive]}
        if len(morph_ids):
            # a sparse morph target: zero everywhere except the ghost corners (see _normal_ghosts)
            delta = np.ascontiguousarray(morph_delta, np.float32)
            accessors.append({"componentType": 5126, "count": len(positions), "type": "VEC3",
                              "min": np.minimum(delta.min(axis=0), 0).tolist(), "max": np.maximum(delta.max(axis=0), 0).tolist(),
                              "sparse": {"count": len(morph_ids),
                                         "indices": {"bufferView": view(np.ascontiguousarray(morph_ids, index_dtype).tobytes()), "componentType": index_type},
                                         "values": {"bufferView": view(delta.tobytes())}}})
            primitive["targets"] = [{"POSITION": len(accessors) - 1}]
            mesh["weights"] = [1.0]
        self._geometry = b"".join(chunks)
        self._json = {
            "asset": {"version": "2.0", "generator": "tissue-lab stream"},
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [mesh],
            "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": roughness}}],
            "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR, "wrapS": _CLAMP, "wrapT": _CLAMP}],
            "textures": [{"sampler": 0, "source": 0}],
            "images": [{"bufferView": len(views), "mimeType": "image/png"}],
            "accessors": accessors,
            "bufferViews": views + [{"buffer": 0, "byteOffset": len(self._geometry), "byteLength": 0}],
            "buffers": [{"byteLength": 0}],
        }

    def crop(self, rgb: np.ndarray) -> np.ndarray:
        return rgb[self.r0:self.r1, self.c0:self.c1]

    def glb(self, image: bytes, mime: str) -> bytes:
        doc = self._json
        doc["images"][0]["mimeType"] = mime
        doc["bufferViews"][-1]["byteLength"] = len(image)
        binary = self._geometry + _pad4(image)
        doc["buffers"][0]["byteLength"] = len(binary)
        text = _pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
        total = 12 + 8 + len(text) + 8 + len(binary)
        return b"".join([struct.pack("<4sII", b"glTF", 2, total), struct.pack("<I4s", len(text), b"JSON"), text, struct.pack("<I4s", len(binary), b"BIN\x00"), binary])


@dataclass
class _Node:
    name: str
    handle: object = None
    replaced_at: float = 0.0     # when its successor was added, time.monotonic() s
    mark: float = 0.0            # stream position after its own message (ClientSync positions)
    successor_mark: float = 0.0  # stream position after its successor's message


@dataclass
class _Tile:
    positions: np.ndarray            # (m, 3) float32, mm: the tile's vertices, then its normal ghosts
    uv: np.ndarray                   # (m, 2) OBJ-convention UVs of those vertices
    faces: np.ndarray                # (n, 3) indices into positions
    morph_ids: np.ndarray            # (k,) ghost corners, moved onto their vertex by a morph target
    morph_delta: np.ndarray          # (k, 3)
    geometry: _TileGeometry | None = None
    sent: np.ndarray | None = None   # the crop last published
    sent_at: float = -1.0
    glb: bytes | None = None         # the GLB of that crop, shared by every browser
    version: int = -1                # which publication it is (stream-wide count; -1: none in this layout)


class _Viewer:
    """One browser's share of the stream: its own tile nodes (viser's per-client scene) under its own root, the
    version of every tile it was sent, the replaced nodes it has not confirmed yet, and its pool of node names."""

    def __init__(self, client, name: str, tile_count: int, max_nodes: int, receive_shadow: bool):
        self.client = client
        self.name = name
        self.receive_shadow = receive_shadow
        self.root = client.scene.add_frame(name, show_axes=False)
        self.nodes: list[_Node | None] = [None] * tile_count  # the newest node showing each tile
        self.versions = [-1] * tile_count                      # the version each tile node shows
        self.added_at = [-1.0] * tile_count                    # when each was added, time.monotonic() s
        self.retiring: list[_Node] = []                        # replaced nodes, oldest first
        self.max_nodes = max_nodes
        self.names: list[str] = []                             # every node name this browser has been sent
        self.free: list[str] = []                              # names not in its scene now
        self.stats = {"tiles_sent": 0, "tiles_behind": 0, "removed": 0, "removed_unconfirmed": 0}

    def show(self, tiles: list[_Tile], now: float, applied: float, next_mark) -> int:
        """Send this browser the newest published version of every tile it lacks, those it has waited for longest
        first, while node names last; a tile is replaced only once the browser has applied its current node
        (applied: its ClientSync position), so a browser that applies slowly gets the newest version then instead of
        every version in between. next_mark(): the stream position after one more message. Returns the number of
        tiles sent."""
        lacking = [i for i, tile in enumerate(tiles) if tile.glb is not None and self.versions[i] != tile.version]
        stale = [i for i in lacking if self.nodes[i] is None or self.nodes[i].mark <= applied]
        stale.sort(key=lambda i: self.added_at[i])
        sent = 0
        for i in stale:
            name = self._take_name()
            if name is None:
                break
            handle = self.client.scene.add_glb(name, tiles[i].glb, visible=True, cast_shadow=False,
                                               receive_shadow=self.receive_shadow)
            mark = next_mark()
            old = self.nodes[i]
            if old is not None:
                old.replaced_at, old.successor_mark = now, mark
                self.retiring.append(old)
            self.nodes[i], self.versions[i], self.added_at[i] = _Node(name, handle, mark=mark), tiles[i].version, now
            sent += 1
        self.stats["tiles_sent"] += sent
        self.stats["tiles_behind"] += len(lacking) - sent
        return sent

    def remove_retired(self, now: float, confirmed: float, hide_after_s: float,
                       max_hide_s: float | None) -> tuple[int, int]:
        """Remove replaced nodes whose delay has passed and whose successor this browser has drawn (confirmed: its
        ClientSync position), or that waited max_hide_s; their names go back to the pool. Oldest first: both
        conditions hold for a prefix of the list. Returns (nodes removed, of those without confirmation)."""
        removed = unconfirmed = 0
        while self.retiring and self.retiring[0].replaced_at + hide_after_s <= now:
            node = self.retiring[0]
            if confirmed < node.successor_mark:
                if max_hide_s is None or now < node.replaced_at + max_hide_s:
                    break
                unconfirmed += 1
            self.retiring.pop(0)
            node.handle.remove()
            self.free.append(node.name)
            removed += 1
        self.stats["removed"] += removed
        self.stats["removed_unconfirmed"] += unconfirmed
        return removed, unconfirmed

    def node_count(self) -> int:
        return sum(node is not None for node in self.nodes) + len(self.retiring)

    def close(self) -> None:
        """Remove this browser's tile nodes (its root and everything below it)."""
        try:
            self.root.remove()
        except Exception:  # the client or the server may be gone already
            pass

    def _take_name(self) -> str | None:
        if self.free:
            return self.free.pop()
        if len(self.names) >= self.max_nodes:
            return None
        self.names.append(f"{self.name}/n{len(self.names):04d}")
        return self.names[-1]


class TextureStream:
    """Streams a changing texture on a static mesh to every browser without blanking."""

    def __init__(self, server, surface, name: str = "/tissue", tiles: int = 8, hide_after_s: float = 3.0,
                 max_pool: int | None = None, max_tiles_per_s: float | None = None, image_format: str = "png",
                 seamless_normals: bool = True, roughness: float = 0.7, receive_shadow: bool = True,
                 wait_for_clients: bool = True, max_hide_s: float | None = None, min_change: int = 3,
                 settle_s: float = 1.0):
        """server: viser.ViserServer. surface: anything with vertices_mm (V, 3), faces (F, 3) and uv (V, 2) in [0, 1]
        (OBJ convention, v up), e.g. sims.surface.TissueSurface. name: the scene node holding each browser's tiles.
        tiles: K, for K x K UV tiles. hide_after_s: how long a replaced tile node stays under its successor at least
        before it is removed, s. wait_for_clients: also wait until the browser has applied and drawn the successor
        (lab.client_sync). max_hide_s: remove a replaced node after this long even if its browser has not confirmed
        its successor, s (None: never; a browser that does not answer only stops getting replacements once its
        max_pool nodes are used up). min_change, settle_s: a tile whose largest texel change is below min_change
        colour levels is re-published only settle_s after its last publication.
        max_pool: node names per browser beyond one per tile, i.e. replaced tiles not yet removed (default K^2).
        max_tiles_per_s: tile versions published per second at most, spread evenly (default max_pool / hide_after_s,
        which keeps the pool of a browser that keeps up from running dry). image_format: "png" (exact) or "jpeg"
        (quality 90, no chroma subsampling: about a third of the bytes at 512^2, not bit-exact). seamless_normals:
        add invisible triangles so the normals the browser recomputes per tile equal those of the whole mesh welded
        at UV seams. roughness: the material's PBR roughness (metalness 0). receive_shadow: shadows of other objects
        fall on it."""
        if tiles < 1:
            raise ValueError("tiles must be >= 1")
        if image_format not in ("png", "jpeg"):
            raise ValueError("image_format must be 'png' or 'jpeg'")
        self.server = server
        self.name = "/" + name.strip("/")
        self.tiles = int(tiles)
        self.hide_after_s = float(hide_after_s)
        self.image_format = image_format
        self.roughness = float(roughness)
        self.receive_shadow = bool(receive_shadow)
        self.max_hide_s = None if max_hide_s is None else float(max_hide_s)
        self.min_change, self.settle_s = int(min_change), float(settle_s)
        self._lock = threading.Lock()
        self._closed = False
        self._queued = 0        # tile messages queued to any browser so far: the ClientSync positions
        self._publications = 0  # tile versions published so far
        self._encoders = concurrent.futures.ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1)), thread_name_prefix="tile-encode")
        self.sync = ClientSync(server, position=lambda: self._queued) if wait_for_clients else None
        self._tiles = self._cut(surface, seamless_normals)
        self.max_pool = tiles * tiles if max_pool is None else max(int(max_pool), 0)
        if max_tiles_per_s is None:
            max_tiles_per_s = self.max_pool / self.hide_after_s if self.hide_after_s > 0 else float("inf")
        self.max_tiles_per_s = float(max_tiles_per_s)
        self._burst = max(1.0, 0.5 * self.max_tiles_per_s)  # tiles that may go at once after a quiet spell
        self._tokens, self._tokens_at = self._burst, None
        self._viewers: dict[int, _Viewer] = {}  # client id -> its share of the stream
        self._shape = None
        self.stats = {"updates": 0, "tiles_sent": 0, "bytes": 0, "tiles_deferred": 0, "python_s": 0.0,
                      "tiles_delivered": 0, "removed": 0, "removed_unconfirmed": 0}
        # tiles_sent, bytes, tiles_deferred: versions published; tiles_delivered: tile nodes sent, all browsers;
        # removed: replaced nodes removed, all browsers; of those, removed_unconfirmed: after max_hide_s without
        # their browser's confirmation

    def _cut(self, surface, seamless_normals: bool) -> list[_Tile]:
        """The K x K UV tiles of the surface (a triangle goes to the tile of its UV centroid), with normal ghosts."""
        tiles = self.tiles
        positions = np.asarray(surface.vertices_mm, np.float32)
        all_faces = np.asarray(surface.faces, np.int64)
        uv = np.asarray(surface.uv, np.float32)
        target = welded_normal_sums(positions, all_faces) if seamless_normals else None
        centroid = uv[all_faces].mean(axis=1)
        col = np.clip((centroid[:, 0] * tiles).astype(np.int64), 0, tiles - 1)
        row = np.clip(((1.0 - centroid[:, 1]) * tiles).astype(np.int64), 0, tiles - 1)
        key = row * tiles + col
        out = []
        for tile_key in np.unique(key):
            vertex_ids, local = np.unique(all_faces[key == tile_key], return_inverse=True)
            tile_positions, tile_uv, faces = positions[vertex_ids], uv[vertex_ids], local.reshape(-1, 3)
            morph_ids, morph_delta = np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
            if target is not None:
                extra, source, ghost_faces, morph_delta = _normal_ghosts(tile_positions, faces, target[vertex_ids])
                morph_ids = len(tile_positions) + np.arange(len(extra))
                tile_positions = np.concatenate([tile_positions, extra])
                tile_uv = np.concatenate([tile_uv, tile_uv[source]])
                faces = np.concatenate([faces, ghost_faces])
            out.append(_Tile(tile_positions, tile_uv, faces, morph_ids, morph_delta))
        return out

    # --- public -----------------------------------------------------------------------------
    @property
    def node_count(self) -> int:
        """Tile nodes in the browsers' scenes now, all browsers (each: one per tile plus its replaced ones not yet
        removed)."""
        return sum(viewer.node_count() for viewer in list(self._viewers.values()))

    @property
    def pending_removals(self) -> int:
        """Replaced tile nodes still in the browsers' scenes, all browsers, waiting for their delay and their
        browser's confirmation."""
        return sum(len(viewer.retiring) for viewer in list(self._viewers.values()))

    def client_stats(self, client_id: int) -> dict:
        """One browser's share: {"nodes", "pending_removals", "tiles_sent" (tile nodes sent to it), "tiles_behind"
        (summed over updates: tiles it lacked the newest version of after the update), "removed",
        "removed_unconfirmed"}; all zero for a client the stream has not seen."""
        viewer = self._viewers.get(client_id)
        if viewer is None:
            return {"nodes": 0, "pending_removals": 0, "tiles_sent": 0, "tiles_behind": 0, "removed": 0,
                    "removed_unconfirmed": 0}
        return {"nodes": viewer.node_count(), "pending_removals": len(viewer.retiring), **viewer.stats}

    def update(self, rgb: np.ndarray) -> dict:
        """Publish the tiles whose texture crop changed since their last publication, and send every browser the
        tiles it lacks. rgb: (H, W, 3) uint8, image orientation. Returns {"tiles_sent": int, "bytes": int}: tile
        versions published (each encoded once, then sent to every browser that keeps up) and their GLB bytes (what
        viser gets per browser), and "tiles_deferred": changed tiles left for a later update by the rate limit or
        settling."""
        start = time.perf_counter()
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb.dtype} {rgb.shape}")
        rgb = rgb[:, :, :3]
        with self._lock:
            if self._closed:
                return {"tiles_sent": 0, "bytes": 0, "tiles_deferred": 0}
            now = time.monotonic()
            if rgb.shape[:2] != self._shape:
                self._layout(rgb.shape[:2])
            result = self._publish(rgb, now)
            self._deliver(now)
            self.stats["updates"] += 1
            for key, value in result.items():
                self.stats[key] += value
            self.stats["python_s"] += time.perf_counter() - start
        return result

    def close(self) -> None:
        """Remove every node of this stream from every browser's scene. Later updates do nothing."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._encoders.shutdown(wait=True)
            if self.sync is not None:
                self.sync.close()
            for viewer in self._viewers.values():
                viewer.close()
            self._viewers.clear()

    # --- internals --------------------------------------------------------------------------
    def _layout(self, shape) -> None:
        """Crop boxes and GLB geometry for a texture of this (H, W); every tile is published and sent again."""
        self._shape = tuple(shape)
        for tile in self._tiles:
            tile.geometry = _TileGeometry(tile.positions, tile.uv, tile.faces, tile.morph_ids, tile.morph_delta,
                                          self._shape, _MARGIN_TEXELS, self.roughness)
            tile.sent, tile.glb, tile.version = None, None, -1

    def _publish(self, rgb: np.ndarray, now: float) -> dict:
        """Encode the changed tiles, most urgent first, within the token bucket (a tile's first version is free)."""
        self._refill(now)
        changed, deferred = self._changed_by_priority(rgb, now)
        chosen = []
        for tile in changed:
            first = tile.sent is None
            if not first and self._tokens < 1.0:
                deferred += 1
                continue
            if not first:
                self._tokens -= 1.0
            chosen.append((tile, np.array(tile.geometry.crop(rgb))))  # a copy: the caller may reuse its buffer
        # Pillow's encoder releases the GIL: the crops are encoded on every core at once, published in order
        for (tile, crop), encoded in zip(chosen, self._encoders.map(self._encode, [crop for _, crop in chosen])):
            tile.glb = tile.geometry.glb(*encoded)
            tile.sent, tile.sent_at, tile.version = crop, now, self._publications
            self._publications += 1
        return {"tiles_sent": len(chosen), "bytes": sum(len(tile.glb) for tile, _ in chosen), "tiles_deferred": deferred}

    def _deliver(self, now: float) -> None:
        """Follow the browsers that came and left, then per browser: remove its confirmed replaced nodes and send it
        the tiles it lacks."""
        clients = self.server.get_clients()
        for client_id in [c for c in self._viewers if c not in clients]:
            del self._viewers[client_id]  # its nodes went with its connection
        for client_id, client in clients.items():
            viewer = self._viewers.get(client_id)
            if viewer is None:
                viewer = self._viewers[client_id] = _Viewer(client, self.name, len(self._tiles),
                                                            len(self._tiles) + self.max_pool, self.receive_shadow)
            applied, confirmed = self.sync.positions(client_id) if self.sync is not None else (float("inf"),) * 2
            removed, unconfirmed = viewer.remove_retired(now, confirmed, self.hide_after_s, self.max_hide_s)
            self.stats["removed"] += removed
            self.stats["removed_unconfirmed"] += unconfirmed
            self.stats["tiles_delivered"] += viewer.show(self._tiles, now, applied, self._next_mark)

    def _next_mark(self) -> float:
        """Count one more tile message queued (after it is queued: a ClientSync request that reads the count later
        is queued after it)."""
        self._queued += 1
        return float(self._queued)

    def _changed_by_priority(self, rgb: np.ndarray, now: float) -> tuple[list[_Tile], int]:
        """Tiles to publish, most urgent first: never-published tiles, then by largest texel change (colour levels)
        times (1 + seconds waited); and the number of tiles whose change (below min_change levels) waits for settle_s
        since the tile's last publication."""
        scored, settling = [], 0
        for tile in self._tiles:
            if tile.sent is None:
                scored.append((float("inf"), tile))
                continue
            crop = tile.geometry.crop(rgb)
            if np.array_equal(tile.sent, crop):
                continue
            change = int(np.abs(tile.sent.astype(np.int16) - crop).max())
            waited = now - tile.sent_at
            if change < self.min_change and waited < self.settle_s:
                settling += 1
                continue
            scored.append((change * (1.0 + waited), tile))
        scored.sort(key=lambda item: -item[0])
        return [tile for _, tile in scored], settling

    def _encode(self, crop: np.ndarray) -> tuple[bytes, str]:
        buffer = io.BytesIO()
        image = Image.fromarray(np.ascontiguousarray(crop), "RGB")
        if self.image_format == "png":
            image.save(buffer, format="PNG", compress_level=1)
            return buffer.getvalue(), "image/png"
        image.save(buffer, format="JPEG", quality=90, subsampling=0)
        return buffer.getvalue(), "image/jpeg"

    def _refill(self, now: float) -> None:
        """Token bucket: max_tiles_per_s tokens a second; at most half a second's worth (and one tile) saved up."""
        if self.max_tiles_per_s == float("inf"):
            self._tokens = float("inf")
        elif self._tokens_at is not None:
            self._tokens = min(self._burst, self._tokens + (now - self._tokens_at) * self.max_tiles_per_s)
        self._tokens_at = now


def camera_for(surface, fov_deg: float = 50.0, aspect: float = 16 / 9, fill: float = 0.9, up=(0.0, 0.0, 1.0)):
    """(position, look_at) of a camera above the mesh (along `up`, units of the mesh: mm) so that its bounding box fills
    about `fill` of a view with vertical field of view fov_deg and this width/height aspect. For z up the view shows
    +x to the right and +y up (the camera sits a hair toward -y, off the orbit controls' singular pole)."""
    vertices = np.asarray(surface.vertices_mm, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre = 0.5 * (low + high)
    extent = high - low
    screen_right = np.cross([0.0, 1.0, 0.0], up) if abs(up[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    screen_right /= np.linalg.norm(screen_right)
    screen_up = np.cross(up, screen_right)
    width, height = abs(extent @ screen_right), abs(extent @ screen_up)
    half = np.tan(np.radians(fov_deg) / 2)
    distance = max(height / (2 * half * fill), width / (2 * half * aspect * fill))
    top = centre + up * (0.5 * abs(extent @ up))
    return top + up * distance - screen_up * (0.01 * distance), centre


def set_initial_camera(server, surface, fov_deg: float = 50.0, **kwargs) -> None:
    """Point every new browser's camera at the mesh from above (viser's initial camera; see camera_for). Also sets the
    near and far planes for a scene in millimetres."""
    position, look_at = camera_for(surface, fov_deg=fov_deg, **kwargs)
    camera = server.initial_camera
    camera.fov = np.radians(fov_deg)
    camera.near = 1.0
    camera.far = 10000.0
    camera.position = tuple(float(v) for v in position)
    camera.look_at = tuple(float(v) for v in look_at)
