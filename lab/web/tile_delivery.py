"""What one browser is sent of the texture stream (lab.web.stream): its own tile nodes under its own root, drawn from
a capped pool of names, each tile replaced only once the browser applied its current node, and replaced nodes removed
once the browser has drawn their successors (lab.web.client_sync positions)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.web.tile_glb import TileGeometry


@dataclass
class Node:
    name: str
    handle: object = None
    replaced_at: float = 0.0     # when its successor was added, the stream's clock, s
    mark: float = 0.0            # stream position after its own message (ClientSync positions)
    successor_mark: float = 0.0  # stream position after its successor's message


@dataclass
class Tile:
    positions: np.ndarray            # (m, 3) int64 grid integers (Grid): the tile's vertices, then its normal ghosts
    uv: np.ndarray                   # (m, 2) OBJ-convention UVs of those vertices
    faces: np.ndarray                # (n, 3) indices into positions
    morph_ids: np.ndarray            # (k,) ghost corners, moved onto their vertex by a morph target
    morph_delta: np.ndarray          # (k, 3) int64 grid integers
    geometry: TileGeometry | None = None
    sent: dict | None = None         # map name -> the crop last published (full resolution)
    encoded: dict | None = None      # map name -> (bytes, mime) of that crop as sent
    sent_at: float = -1.0
    glb: bytes | None = None         # the GLB of those crops, shared by every browser
    version: int = -1                # which publication it is (stream-wide count; -1: none in this layout)
    index: int = -1                  # its place in the stream's tiles
    seen_change: int | None = None   # its largest texel change (levels) when last examined since it was published
    examined_at: float = -1.0        # when an update last compared its crops (the stream's clock)


class Viewer:
    """One browser's share of the stream: its own tile nodes (viser's per-client scene) under its own root, the
    version of every tile it was sent, the replaced nodes it has not confirmed yet, and its pool of node names."""

    def __init__(self, client, name: str, tile_count: int, max_nodes: int, receive_shadow: bool):
        self.client = client
        self.name = name
        self.receive_shadow = receive_shadow
        self.root = client.scene.add_frame(name, show_axes=False)
        self.nodes: list[Node | None] = [None] * tile_count  # the newest node showing each tile
        self.versions = [-1] * tile_count                      # the version each tile node shows
        self.added_at = [-1.0] * tile_count                    # when each was added, the stream's clock, s
        self.retiring: list[Node] = []                        # replaced nodes, oldest first
        self.max_nodes = max_nodes
        self.names: list[str] = []                             # every node name this browser has been sent
        self.free: list[str] = []                              # names not in its scene now
        self.stats = {"tiles_sent": 0, "tiles_behind": 0, "removed": 0, "removed_unconfirmed": 0}

    def show(self, tiles: list[Tile], now: float, applied: float, next_mark) -> int:
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
            self.nodes[i], self.versions[i], self.added_at[i] = Node(name, handle, mark=mark), tiles[i].version, now
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
