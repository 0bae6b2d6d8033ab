"""Stream a changing texture on a static mesh to every browser (viser) without blanking it.

viser has no message that updates a mesh texture in place, and re-sending a mesh blanks it in the
browser while the new GLB parses (docs/model/streaming.md, "Why tiles: viser cannot update a texture"). So the mesh is cut into K x K UV tiles (a
triangle goes to the tile of its UV centroid); every tile is its own GLB node textured with the crop
of the texture over its UV box plus a margin. An update re-sends only the tiles whose crop changed,
each as a NEW node added visible over the old one (the newest identical copy draws last and wins);
the old node is removed at least `hide_after_s` later and only once that browser has applied and
drawn the new one (lab.web.client_sync: a browser that draws a frame every few seconds would otherwise
get the add and the remove in one batch and show a hole while the new node parses).

Publishing is shared, delivery is per browser. An update publishes changed tiles at most
`max_tiles_per_s` (a tile that changes faster is published later with its then newest crop, so
stale textures are dropped instead of queued); when the budget runs short the tiles that changed
most go first (a fresh burn before a fading one, weighed by how long each has waited), and a change
of a level or two (cooling tissue fades by one level per update) waits `settle_s` to add up before
it takes a slot. A front end whose maps are costly to make asks plan() first which texel blocks the next update will
read, and makes only those (the lab composes the look there only: sims.scene.assembly.Scene.composite's `wanted`); the update
then examines only the tiles plan chose (those never published and, by the time since each was last published or
examined and by the change it had then unless its maps changed again since, as many as the rate limit lets go plus
two), and the other candidates wait their turn, their maps not yet made. Each published tile is encoded once into a GLB. Then every browser gets, through
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

The GLB of a tile (materials, quantized geometry) is made in lab.web.tile_glb; what one browser is sent and
when its replaced nodes go, in lab.web.tile_delivery.

Call `update` and `close` from one thread (the simulation thread); a lock makes a `close` from
another thread safe too.
"""
from __future__ import annotations

import concurrent.futures
import io
import os
import threading
import time
import warnings

import numpy as np
from PIL import Image

from lab.views import View
from lab.web.client_sync import ClientSync
from lab.web.tile_delivery import Tile, Viewer
from lab.web.tile_glb import INT16_LIMIT, Grid, TileGeometry, normal_ghosts, vertex_sums
from sims.look.tile_mask import TileMask

_MARGIN_TEXELS = 2
EXTRA_EXAMINED = 2     # tiles a planned update examines beyond those the rate limit lets go at once (plan)
_MAX_LEVELS = 255      # the change a tile is taken to have until the stream has examined it
# a browser left between the stream listing it and sending to it: nothing is lost, it is dropped on the next update
warnings.filterwarnings("ignore", message="Queued a (GlbMessage|FrameMessage) on a closed connection")



class TextureStream(View):
    """Streams a changing texture on a static mesh to every browser without blanking."""

    def __init__(self, server, surface, name: str = "/tissue", tiles: int = 8, hide_after_s: float = 3.0,
                 max_pool: int | None = None, max_tiles_per_s: float | None = None, image_format: str = "png",
                 seamless_normals: bool = True, roughness: float = 0.7, receive_shadow: bool = True,
                 wait_for_clients: bool = True, max_hide_s: float | None = None, min_change: int = 3,
                 settle_s: float = 1.0, normal_divisor: int = 1, roughness_divisor: int = 2, clock=time.monotonic):
        """server: viser.ViserServer. surface: anything with vertices_mm (V, 3), faces (F, 3) and uv (V, 2) in [0, 1]
        (OBJ convention, v up), e.g. sims.surface.texels.TissueSurface. name: the scene node holding each browser's tiles.
        tiles: K, for K x K UV tiles. hide_after_s: how long a replaced tile node stays under its successor at least
        before it is removed, s. wait_for_clients: also wait until the browser has applied and drawn the successor
        (lab.web.client_sync). max_hide_s: remove a replaced node after this long even if its browser has not confirmed
        its successor, s (None: never; a browser that does not answer only stops getting replacements once its
        max_pool nodes are used up). min_change, settle_s: a tile whose largest texel change is below min_change
        colour levels is re-published only settle_s after its last publication.
        max_pool: node names per browser beyond one per tile, i.e. replaced tiles not yet removed (default K^2).
        max_tiles_per_s: tile versions published per second at most, spread evenly (default max_pool / hide_after_s,
        which keeps the pool of a browser that keeps up from running dry). image_format: "png" (exact) or "jpeg"
        (quality 90, no chroma subsampling: about a third of the bytes at 512^2, not bit-exact). seamless_normals:
        add invisible triangles so the normals the browser recomputes per tile equal those of the whole mesh welded
        at UV seams. roughness: the material's PBR roughness (metalness 0) when update gets no roughness map.
        receive_shadow: shadows of other objects fall on it. normal_divisor, roughness_divisor: 1 or 2, that map goes at
        the colour's resolution or at half of it (2 x 2 texel means). clock: () -> seconds, the time the rate limit, settling
        and hiding go by (a bench passes the simulated time, so the stream publishes per simulated second what the lab
        publishes per second)."""
        if tiles < 1:
            raise ValueError("tiles must be >= 1")
        if image_format not in ("png", "jpeg"):
            raise ValueError("image_format must be 'png' or 'jpeg'")
        if normal_divisor not in (1, 2) or roughness_divisor not in (1, 2):
            raise ValueError("normal_divisor and roughness_divisor must be 1 or 2")
        self.server = server
        self.divisors = {"color": 1, "normal": int(normal_divisor), "roughness": int(roughness_divisor)}
        self.name = "/" + name.strip("/")
        self.tiles = int(tiles)
        self.hide_after_s = float(hide_after_s)
        self.image_format = image_format
        self.roughness = float(roughness)
        self.receive_shadow = bool(receive_shadow)
        self.max_hide_s = None if max_hide_s is None else float(max_hide_s)
        self.min_change, self.settle_s = int(min_change), float(settle_s)
        self.clock = clock
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
        self._viewers: dict[int, Viewer] = {}  # client id -> its share of the stream
        self._shape = None  # ((H, W), the maps' kinds) of the layout
        self._candidates: set[int] = set()  # tiles that may differ from what they last published (update's changed)
        self._examined: set[int] | None = None  # the tiles plan() chose for the next update (None: every candidate)
        self._pad = None    # np.pad widths that make odd-sized maps even, for half-resolution maps
        self.stats = {"updates": 0, "tiles_sent": 0, "bytes": 0, "tiles_deferred": 0, "python_s": 0.0,
                      "tiles_delivered": 0, "removed": 0, "removed_unconfirmed": 0}
        # tiles_sent, bytes, tiles_deferred: versions published; tiles_delivered: tile nodes sent, all browsers;
        # removed: replaced nodes removed, all browsers; of those, removed_unconfirmed: after max_hide_s without
        # their browser's confirmation

    def _cut(self, surface, seamless_normals: bool) -> list[Tile]:
        """The K x K UV tiles of the surface (a triangle goes to the tile of its UV centroid), with normal ghosts, in
        the integers of one mesh-wide grid (Grid), made coarser until every ghost corner fits int16 too."""
        tiles = self.tiles
        vertices = np.asarray(surface.vertices_mm, np.float64)
        all_faces = np.asarray(surface.faces, np.int64)
        uv = np.asarray(surface.uv, np.float32)
        centroid = uv[all_faces].mean(axis=1)
        col = np.clip((centroid[:, 0] * tiles).astype(np.int64), 0, tiles - 1)
        row = np.clip(((1.0 - centroid[:, 1]) * tiles).astype(np.int64), 0, tiles - 1)
        key = row * tiles + col
        parts = []
        for tile_key in np.unique(key):
            vertex_ids, local = np.unique(all_faces[key == tile_key], return_inverse=True)
            parts.append((vertex_ids, local.reshape(-1, 3)))
        grid = Grid(vertices)
        while True:
            positions = grid.quantize(vertices)
            target = None
            if seamless_normals:  # welded at UV seams: copies of a vertex have the same grid integers
                _, weld = np.unique(positions, axis=0, return_inverse=True)
                weld = weld.reshape(-1)
                target = vertex_sums(positions, all_faces, weld)
            out = []
            for vertex_ids, faces in parts:
                tile_positions, tile_uv = positions[vertex_ids], uv[vertex_ids]
                morph_ids, morph_delta = np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
                if target is not None:
                    extra, source, ghost_faces, morph_delta = normal_ghosts(tile_positions, faces, target[vertex_ids])
                    morph_ids = len(tile_positions) + np.arange(len(extra))
                    tile_positions = np.concatenate([tile_positions, extra])
                    tile_uv = np.concatenate([tile_uv, tile_uv[source]])
                    faces = np.concatenate([faces, ghost_faces])
                out.append(Tile(tile_positions, tile_uv, faces, morph_ids, morph_delta, index=len(out)))
            if all(np.abs(tile.positions).max() <= INT16_LIMIT and np.abs(tile.morph_delta).max(initial=0) <= INT16_LIMIT
                   for tile in out):
                self.grid = grid
                return out
            grid = grid.coarser()

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

    def drawn_whole(self) -> bool:
        """Whether some browser has drawn the whole texture: a node of every tile, each confirmed drawn (its ClientSync
        confirmation; sent is enough without wait_for_clients)."""
        with self._lock:
            for client_id, viewer in self._viewers.items():
                drawn = self.sync.confirmed_by(client_id) if self.sync is not None else float("inf")
                if all(node is not None and node.mark <= drawn for node in viewer.nodes):
                    return True
        return False

    def client_stats(self, client_id: int) -> dict:
        """One browser's share: {"nodes", "pending_removals", "tiles_sent" (tile nodes sent to it), "tiles_behind"
        (summed over updates: tiles it lacked the newest version of after the update), "removed",
        "removed_unconfirmed"}; all zero for a client the stream has not seen."""
        viewer = self._viewers.get(client_id)
        if viewer is None:
            return {"nodes": 0, "pending_removals": 0, "tiles_sent": 0, "tiles_behind": 0, "removed": 0,
                    "removed_unconfirmed": 0}
        return {"nodes": viewer.node_count(), "pending_removals": len(viewer.retiring), **viewer.stats}

    def show(self, scene, seconds: dict | None = None) -> dict:
        """One frame of `scene` (a sims.scene.assembly.Scene) in every browser: the display tiles the scene would change
        are planned against what this stream will read (plan), only those composed (Scene.composite), and the tiles that
        changed compared, encoded and sent with the normal and roughness maps (update). The lab's loop and the bench
        both call this. Returns update's stats; seconds, when given, gets the wall seconds spent "copying maps" (off the
        device) and "in the stream" (planning and updating); composing is timed by the scene's own profile."""
        start = time.perf_counter()
        wanted = self.plan(scene.pending_display_changes())
        planning_s = time.perf_counter() - start
        rgb = scene.composite(wanted)
        start = time.perf_counter()
        maps = scene.material_maps()
        maps_s = time.perf_counter() - start
        start = time.perf_counter()
        stats = self.update(rgb, *maps, changed=scene.take_display_changes())
        if seconds is not None:
            seconds["copying maps"] = maps_s
            seconds["in the stream"] = planning_s + time.perf_counter() - start
        return stats

    def update(self, rgb: np.ndarray, normal: np.ndarray | None = None, roughness: np.ndarray | None = None,
               changed: TileMask | None = None) -> dict:
        """Publish the tiles whose maps changed since their last publication, and send every browser the tiles it
        lacks. All maps in image orientation (row 0 is v = 1), the same (H, W):
        rgb: (H, W, 3) uint8 base colour, sRGB.
        normal: (H, W, 3) uint8 glTF tangent-space normal map, or None: R = x to the right (+u), G = y up in the image
        (toward row 0, i.e. +v), B = z out of the surface; 128 is 0 (n = value / 127.5 - 1).
        roughness: (H, W) uint8 PBR roughness * 255, or None (then the constant roughness given to the constructor).
        A tile is published when any of its crops changed; its change is the largest over the maps (levels).
        changed: the blocks (sims.look.tile_mask.TileMask, or a (tile, flags) pair) from the maps' maker: only texels
        in the blocks it flags may differ from the maps of the last update (sims.scene.assembly.Scene.
        take_display_changes); the stream then compares only the tiles whose crops meet a flagged block, and those it
        has left waiting. None: any texel may have changed (every tile is compared).
        Returns {"tiles_sent": int, "bytes": int}: tile versions published (each map encoded once, then the GLB sent
        to every browser that keeps up) and their GLB bytes (what viser gets per browser), and "tiles_deferred":
        changed tiles left for a later update by the rate limit or settling. After plan(), only the tiles it chose
        are compared (the maps may be stale elsewhere); the others stay candidates for a later update."""
        start = time.perf_counter()
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb: expected an (H, W, 3) uint8 image, got {rgb.dtype} {rgb.shape}")
        maps = {"color": rgb[:, :, :3]}
        if normal is not None:
            normal = np.asarray(normal)
            if normal.ndim != 3 or normal.shape[2] != 3 or normal.shape[:2] != rgb.shape[:2] or normal.dtype != np.uint8:
                raise ValueError(f"normal: expected an {rgb.shape[:2] + (3,)} uint8 normal map (the shape of rgb), "
                                 f"got {normal.dtype} {normal.shape}")
            maps["normal"] = normal
        if roughness is not None:
            roughness = np.asarray(roughness)
            if roughness.shape != rgb.shape[:2] or roughness.dtype != np.uint8:
                raise ValueError(f"roughness: expected an {rgb.shape[:2]} uint8 roughness map (the shape of rgb), "
                                 f"got {roughness.dtype} {roughness.shape}")
            maps["roughness"] = roughness
        with self._lock:
            if self._closed:
                return {"tiles_sent": 0, "bytes": 0, "tiles_deferred": 0}
            now = self.clock()
            layout = (rgb.shape[:2], tuple(maps))
            if layout != self._shape:
                self._layout(*layout)
                self._examined = None  # a new layout publishes every tile: the maps must be whole
            if self._pad is not None:  # half-resolution maps of an odd-sized image: crops may reach one texel past it
                maps = {kind: np.pad(image, self._pad[:image.ndim], mode="edge") for kind, image in maps.items()}
            self._mark_candidates(changed)
            result = self._publish(maps, now)
            self._deliver(now)
            self.stats["updates"] += 1
            for key, value in result.items():
                self.stats[key] += value
            self.stats["python_s"] += time.perf_counter() - start
        return result

    def plan(self, pending: TileMask) -> TileMask | None:
        """Before an update whose maps are made on demand: which texel blocks it will read. pending: the blocks
        (sims.look.tile_mask.TileMask, or a (tile, flags) pair) that the maker's next maps would change
        (sims.scene.assembly.Scene.pending_display_changes). The tiles meeting a flagged block become
        candidates; of those the update examines the never-published ones and, most urgent first, as many as the
        rate limit lets go now plus EXTRA_EXAMINED, urgency being the change a tile had when last examined if nothing
        reached it since (the most, _MAX_LEVELS, if it was not examined since its last publication or a change
        reached it again: a tile found unchanged or settling is not passed over when a burn starts in it) times
        (1 + seconds since it was last published or examined: tiles whose changes show no texel, as heat below a
        colour level, take their turn and do not hold the budget). Returns the
        TileMask of the blocks those tiles' crops meet, for the maker to bring up to date (the other blocks may be
        stale: the update does not look at them), or None before the first update (every block is wanted)."""
        with self._lock:
            block, flags = TileMask.of(pending)
            if self._closed or self._shape is None or flags.shape != tuple(-(-size // block) for size in self._shape[0]):
                self._examined = None
                return None
            self._mark_candidates(TileMask(block, flags))
            now = self.clock()
            self._refill(now)
            fresh = [index for index in self._candidates if self._tiles[index].sent is None]
            urgency = sorted(((_MAX_LEVELS if tile.seen_change is None else tile.seen_change)
                              * (1.0 + now - max(tile.sent_at, tile.examined_at)), index)
                             for index in self._candidates if (tile := self._tiles[index]).sent is not None)
            budget = (int(self._tokens) if self.max_tiles_per_s != float("inf") else len(urgency)) + EXTRA_EXAMINED
            self._examined = set(fresh) | {index for _, index in urgency[::-1][:budget]}
            wanted = np.zeros_like(flags)
            for index in self._examined:
                box = self._tiles[index].geometry
                wanted[box.blocks(block)] = True
            return TileMask(block, wanted)

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
    def _layout(self, shape, maps) -> None:
        """Crop boxes and GLB geometry for maps of this (H, W) and these kinds; every tile is published and sent
        again."""
        self._shape = (tuple(shape), tuple(maps))
        self._candidates = set(range(len(self._tiles)))
        even = any(self.divisors[kind] == 2 for kind in maps)
        odd = [(0, int(even and size % 2)) for size in shape]
        self._pad = odd + [(0, 0)] if any(pad for _, pad in odd) else None
        for tile in self._tiles:
            tile.geometry = TileGeometry(tile.positions, tile.uv, tile.faces, tile.morph_ids, tile.morph_delta, self.grid,
                                          shape, _MARGIN_TEXELS, self.roughness, maps, even)
            tile.sent, tile.encoded, tile.glb, tile.version, tile.seen_change, tile.examined_at = None, None, None, -1, None, -1.0

    def _mark_candidates(self, changed: TileMask | None) -> None:
        """Add the tiles whose crops meet a block flagged in changed (all tiles for None) to the candidates; their
        maps change again since they were examined, so how much they changed is no longer known (seen_change)."""
        if changed is None:
            self._candidates.update(range(len(self._tiles)))
            for tile in self._tiles:
                tile.seen_change = None
            return
        block, flags = TileMask.of(changed)
        if not flags.any():
            return
        for index, tile in enumerate(self._tiles):
            if flags[tile.geometry.blocks(block)].any():
                self._candidates.add(index)
                tile.seen_change = None

    def _publish(self, maps: dict, now: float) -> dict:
        """Encode the changed tiles, most urgent first, within the token bucket (a tile's first version is free); of a
        tile, only the maps whose crop changed are encoded again."""
        self._refill(now)
        changed, deferred = self._changed_by_priority(maps, now)
        chosen = []
        for tile in changed:
            first = tile.sent is None
            if not first and self._tokens < 1.0:
                deferred += 1
                continue
            if not first:
                self._tokens -= 1.0
            crops = {kind: np.array(tile.geometry.crop(image)) for kind, image in maps.items()}  # copies: the caller may reuse its buffers
            fresh = [kind for kind, crop in crops.items() if first or not np.array_equal(tile.sent[kind], crop)]
            chosen.append((tile, crops, fresh))
        # Pillow's encoder releases the GIL: the crops are encoded on every core at once, published in order
        jobs = [(kind, crops[kind]) for _, crops, fresh in chosen for kind in fresh]
        encoded = iter(self._encoders.map(self._encode, *zip(*jobs)) if jobs else ())
        for tile, crops, fresh in chosen:
            tile.encoded = {**(tile.encoded or {}), **{kind: next(encoded) for kind in fresh}}
            tile.glb = tile.geometry.glb([tile.encoded[kind] for kind in tile.geometry.maps])
            tile.sent, tile.sent_at, tile.version, tile.seen_change = crops, now, self._publications, None
            self._publications += 1
            self._candidates.discard(tile.index)
        return {"tiles_sent": len(chosen), "bytes": sum(len(tile.glb) for tile, _, _ in chosen), "tiles_deferred": deferred}

    def _deliver(self, now: float) -> None:
        """Follow the browsers that came and left, then per browser: remove its confirmed replaced nodes and send it
        the tiles it lacks."""
        clients = self.server.get_clients()
        for client_id in [c for c in self._viewers if c not in clients]:
            del self._viewers[client_id]  # its nodes went with its connection
        for client_id, client in clients.items():
            viewer = self._viewers.get(client_id)
            if viewer is None:
                viewer = self._viewers[client_id] = Viewer(client, self.name, len(self._tiles),
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

    def _changed_by_priority(self, maps: dict, now: float) -> tuple[list[Tile], int]:
        """Tiles to publish, most urgent first: never-published tiles, then by largest texel change over the maps
        (levels) times (1 + seconds waited); and the number of tiles whose change (below min_change levels) waits for
        settle_s since the tile's last publication."""
        scored, settling = [], 0
        examined, self._examined = self._examined, None
        for index in sorted(self._candidates if examined is None else self._candidates & examined):
            tile = self._tiles[index]
            if tile.sent is None:
                scored.append((float("inf"), tile))
                continue
            change = 0
            for kind, image in maps.items():
                crop = tile.geometry.crop(image)
                if not np.array_equal(tile.sent[kind], crop):
                    change = max(change, int(np.abs(tile.sent[kind].astype(np.int16) - crop).max()))
            tile.seen_change, tile.examined_at = change, now
            if change == 0:
                self._candidates.discard(index)  # as published: nothing to do until a change reaches it
                continue
            waited = now - tile.sent_at
            if change < self.min_change and waited < self.settle_s:
                settling += 1
                continue
            scored.append((change * (1.0 + waited), tile))
        scored.sort(key=lambda item: -item[0])
        return [tile for _, tile in scored], settling

    def _encode(self, kind: str, crop: np.ndarray) -> tuple[bytes, str]:
        """One map's crop as an image: the colour as image_format; the normal map (RGB) and the roughness (greyscale:
        R = G = B, so glTF's G is the roughness and B, the metalness, is cancelled by metallicFactor 0) as PNG at zlib
        level 3 (the colour PNG at level 1, as before), at 1 / its divisor of the colour's resolution (2 x 2 texel
        means: the crop box is aligned to even texels)."""
        buffer = io.BytesIO()
        if self.divisors[kind] == 2:
            total = crop.astype(np.uint16)
            total = total[0::2, 0::2] + total[1::2, 0::2] + total[0::2, 1::2] + total[1::2, 1::2]
            crop = ((total + 2) // 4).astype(np.uint8)
        image = Image.fromarray(np.ascontiguousarray(crop), "L" if kind == "roughness" else "RGB")
        if kind == "color" and self.image_format == "jpeg":
            image.save(buffer, format="JPEG", quality=90, subsampling=0)
            return buffer.getvalue(), "image/jpeg"
        image.save(buffer, format="PNG", compress_level=1 if kind == "color" else 3)
        return buffer.getvalue(), "image/png"

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
