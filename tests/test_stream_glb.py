"""lab.web.stream.TextureStream without a browser: which tiles it publishes and when, and what its tile GLBs hold (the
material maps, the quantized geometry, the normal ghosts). A raw websocket client (testing.raw_client) stands in for a
browser; what the stream sends is read back from the connected client's scene."""
from __future__ import annotations

import io
import json
import struct
import time
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from lab.reference.meshes import plane_mesh
from testing import browser

SHORT, UNSIGNED_SHORT, UNSIGNED_INT, FLOAT = 5122, 5123, 5125, 5126
_DTYPES = {5120: np.int8, 5121: np.uint8, SHORT: np.int16, UNSIGNED_SHORT: np.uint16, UNSIGNED_INT: np.uint32, FLOAT: np.float32}
_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


# --- reading a GLB as a glTF loader does --------------------------------------------------------

def glb_parts(glb: bytes):
    """(the JSON document, the BIN chunk) of a GLB, checking its header and chunk types."""
    magic, version, total = struct.unpack_from("<4sII", glb, 0)
    assert magic == b"glTF" and version == 2 and total == len(glb)
    json_length, kind = struct.unpack_from("<I4s", glb, 12)
    assert kind == b"JSON" and json_length % 4 == 0
    document = json.loads(glb[20:20 + json_length])
    binary_length, kind = struct.unpack_from("<I4s", glb, 20 + json_length)
    assert kind == b"BIN\x00" and 28 + json_length + binary_length == len(glb)
    return document, glb[28 + json_length:28 + json_length + binary_length]


def _view_bytes(document, binary, index) -> bytes:
    view = document["bufferViews"][index]
    return binary[view.get("byteOffset", 0):view.get("byteOffset", 0) + view["byteLength"]]


def accessor(document, binary, index, normalized_to_float: bool = False) -> np.ndarray:
    """An accessor's elements (count, components) in its component type, honouring byteStride and sparse
    substitution; normalized integers as floats (value / max) when normalized_to_float."""
    entry = document["accessors"][index]
    dtype, size, count = np.dtype(_DTYPES[entry["componentType"]]), _SIZES[entry["type"]], entry["count"]
    if "bufferView" in entry:
        view = document["bufferViews"][entry["bufferView"]]
        data = _view_bytes(document, binary, entry["bufferView"])[entry.get("byteOffset", 0):]
        stride = view.get("byteStride", dtype.itemsize * size)
        assert stride % 4 == 0 or view.get("target") != 34962, "vertex attributes align to 4 bytes"
        out = np.stack([np.frombuffer(data, dtype, size, i * stride) for i in range(count)]) if count else np.zeros((0, size), dtype)
    else:
        out = np.zeros((count, size), dtype)
    if "sparse" in entry:
        sparse = entry["sparse"]
        ids = np.frombuffer(_view_bytes(document, binary, sparse["indices"]["bufferView"]), _DTYPES[sparse["indices"]["componentType"]], sparse["count"])
        values = np.frombuffer(_view_bytes(document, binary, sparse["values"]["bufferView"]), dtype, sparse["count"] * size)
        out = out.copy()
        out[ids] = values.reshape(-1, size)
    if normalized_to_float and entry.get("normalized"):
        return out.astype(np.float64) / np.iinfo(dtype).max
    return out


def images(glb: bytes) -> list[np.ndarray]:
    """Every image of the GLB, decoded (greyscale stays 2-D)."""
    document, binary = glb_parts(glb)
    return [np.asarray(Image.open(io.BytesIO(_view_bytes(document, binary, image["bufferView"])))) for image in document["images"]]


def material_images(glb: bytes) -> dict:
    """{"color", "normal", "roughness"}: the decoded image of each texture the material uses."""
    document, _ = glb_parts(glb)
    decoded = images(glb)
    material = document["materials"][0]
    slots = {"color": material["pbrMetallicRoughness"].get("baseColorTexture"), "normal": material.get("normalTexture"),
             "roughness": material["pbrMetallicRoughness"].get("metallicRoughnessTexture")}
    return {kind: decoded[document["textures"][slot["index"]]["source"]] for kind, slot in slots.items() if slot is not None}


class TileMesh:
    """A tile GLB's mesh as the viser client has it: grid integers, the node's dequantization, glTF UVs, faces, the
    morph target's ghost corners and deltas."""

    def __init__(self, glb: bytes):
        document, binary = glb_parts(glb)
        self.document = document
        node = document["nodes"][0]
        self.scale = node["scale"]
        self.translation = np.asarray(node.get("translation", [0.0, 0.0, 0.0]))
        primitive = document["meshes"][0]["primitives"][0]
        self.position_accessor = document["accessors"][primitive["attributes"]["POSITION"]]
        self.uv_accessor = document["accessors"][primitive["attributes"]["TEXCOORD_0"]]
        self.positions = accessor(document, binary, primitive["attributes"]["POSITION"]).astype(np.int64)
        self.st = accessor(document, binary, primitive["attributes"]["TEXCOORD_0"], normalized_to_float=True)
        self.faces = accessor(document, binary, primitive["indices"]).reshape(-1, 3).astype(np.int64)
        self.morph_ids, self.deltas = np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
        self.targets = primitive.get("targets", [])
        if self.targets:
            target = document["accessors"][self.targets[0]["POSITION"]]
            sparse = target["sparse"]
            self.morph_accessor = target
            self.morph_ids = np.frombuffer(_view_bytes(document, binary, sparse["indices"]["bufferView"]),
                                           _DTYPES[sparse["indices"]["componentType"]], sparse["count"]).astype(np.int64)
            self.deltas = accessor(document, binary, self.targets[0]["POSITION"]).astype(np.int64)[self.morph_ids]
        self.ghost_faces = np.isin(self.faces, self.morph_ids).any(axis=1)
        self.real = np.setdiff1d(np.arange(len(self.positions)), self.morph_ids)

    def world(self, positions=None) -> np.ndarray:
        """Positions in mm: the node's translation plus its (uniform) scale times the integers."""
        positions = self.positions if positions is None else positions
        return self.translation + float(self.scale[0]) * np.asarray(positions, np.float64)

    def drawn(self) -> np.ndarray:
        """The integer positions after the morph target (weight 1)."""
        drawn = self.positions.copy()
        drawn[self.morph_ids] += self.deltas
        return drawn

    def normal_sums(self) -> np.ndarray:
        """three.js computeVertexNormals before normalizing, over the un-morphed positions: per vertex the sum of
        (c - b) x (a - b) of its triangles (exact in integers)."""
        tri = self.positions[self.faces]
        cross = np.cross(tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 1])
        sums = np.zeros_like(self.positions)
        for corner in range(3):
            np.add.at(sums, self.faces[:, corner], cross)
        return sums


# --- fixtures -----------------------------------------------------------------------------------

def bumpy_patch(cells: int = 24, seam: bool = False):
    """A 60 x 40 mm patch with bumps (normals vary), UVs over [0, 1]^2, as TextureStream wants it. seam: the vertices
    on x = 0 split into two copies, as at a UV seam (the normals must still be welded there)."""
    mesh = plane_mesh(60.0, 40.0, cells=cells)
    vertices = np.asarray(mesh.vertices, np.float64).copy()
    vertices[:, 2] = 3.0 * np.sin(vertices[:, 0] / 7.0) * np.cos(vertices[:, 1] / 5.0)
    surface = SimpleNamespace(vertices_mm=vertices.astype(np.float32), faces=np.asarray(mesh.faces, np.int32),
                              uv=np.asarray(mesh.visual.uv, np.float32))
    if seam:
        vertices, faces = surface.vertices_mm, surface.faces.copy()
        on_seam = np.flatnonzero(np.abs(vertices[:, 0]) < 1e-4)
        right = vertices[faces].mean(axis=1)[:, 0] > 0
        remap = np.arange(len(vertices) + len(on_seam))
        remap[on_seam] = len(vertices) + np.arange(len(on_seam))
        faces[right] = remap[faces[right]]
        surface.vertices_mm = np.concatenate([vertices, vertices[on_seam]])
        surface.uv = np.concatenate([surface.uv, surface.uv[on_seam]])
        surface.faces = faces
    return surface


class Recorder:
    """Wraps the add_glb of the connected clients' scenes (the stream sends each browser its own tile nodes) to keep
    what the stream sends."""

    def __init__(self, server):
        self.sent = []
        for client in server.get_clients().values():
            original = client.scene.add_glb

            def add_glb(name, glb_data, _original=original, **kwargs):
                self.sent.append((name, glb_data))
                return _original(name, glb_data, **kwargs)

            client.scene.add_glb = add_glb


@pytest.fixture
def server():
    """A viser server with one connected client (a raw websocket client that answers as a browser does)."""
    import viser

    from testing.raw_client import RawClient

    instance = viser.ViserServer(host="127.0.0.1", port=browser.free_port(), verbose=False)
    client = RawClient(instance.get_port())
    deadline = time.monotonic() + 30
    while not instance.get_clients() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert instance.get_clients(), "the raw client did not connect"
    yield instance
    client.close()
    instance.stop()


def applied(server, stream, timeout_s: float = 10.0) -> None:
    """Wait until every client has applied every tile node queued to it so far (a tile is replaced for a client only
    once it has applied the tile's current node)."""
    mark, deadline = stream.sync.mark(), time.monotonic() + timeout_s
    while not all(stream.sync.positions(client_id)[0] >= mark for client_id in server.get_clients()):
        assert time.monotonic() < deadline, "the client did not apply its tiles"
        time.sleep(0.02)


def coordinate_image(height: int, width: int) -> np.ndarray:
    """Every texel tells its own place: R, G = column, row (mod 256), B = 60."""
    rows, cols = np.mgrid[0:height, 0:width]
    return np.stack([cols % 256, rows % 256, np.full_like(rows, 60)], axis=-1).astype(np.uint8)


def crop_box(color: np.ndarray) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1) of a colour crop cut from coordinate_image (rows and columns below 256)."""
    r0, c0 = int(color[0, 0, 1]), int(color[0, 0, 0])
    return r0, r0 + color.shape[0], c0, c0 + color.shape[1]


def half(image: np.ndarray) -> np.ndarray:
    """2 x 2 texel means, rounded half up (even-sized input)."""
    total = image.astype(np.int32)
    total = total[0::2, 0::2] + total[1::2, 0::2] + total[0::2, 1::2] + total[1::2, 1::2]
    return ((total + 2) // 4).astype(np.uint8)


def material_maps(height: int, width: int, seed: int = 0):
    """A smooth normal map with per-texel noise of +-10 levels, and a roughness map between 80 and 200."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width] / max(height, width)
    relief = np.sin(cols * 9.0) * np.cos(rows * 7.0)
    grad_row, grad_col = np.gradient(relief * 20.0)
    normal = np.stack([-grad_col, grad_row, np.ones_like(relief)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.clip(np.rint(normal * 127.5 + 127.5) + rng.integers(-10, 11, normal.shape), 0, 255).astype(np.uint8)
    roughness = np.clip(140 + 60 * np.sin(cols * 5 + 1) * np.cos(rows * 4), 80, 200).astype(np.uint8)
    return normal, roughness


# --- publishing: which tiles, when ----------------------------------------------------------------

def test_stream_sends_only_changed_tiles_and_removes_replaced_nodes_later(server):
    from lab.web.stream import TextureStream

    recorder = Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=4, hide_after_s=0.3)
    image = np.full((64, 64, 3), 120, np.uint8)
    first = stream.update(image)
    assert first["tiles_sent"] == 16 and first["bytes"] == sum(len(glb) for _, glb in recorder.sent)
    assert stream.update(image)["tiles_sent"] == 0
    applied(server, stream)
    image[40:44, 10:14] = 255  # inside one tile, far from its borders
    assert stream.update(image)["tiles_sent"] == 1
    assert stream.node_count == 17  # the replaced node stays under the new one for now
    time.sleep(0.35)
    deadline = time.monotonic() + 10  # and goes once the client confirmed its successor (a few 0.2 s round trips)
    while stream.node_count > 16 and time.monotonic() < deadline:
        time.sleep(0.05)
        stream.update(image)
    assert stream.node_count == 16
    image[40:44, 10:14] = 0
    stream.update(image)
    assert len(recorder.sent) == 18 and len({name for name, _ in recorder.sent}) == 17, "the removed node's name is used again"
    stream.close()
    assert stream.update(image)["tiles_sent"] == 0


def test_stream_rate_limit_defers_changed_tiles_and_sends_their_newest_crop(server):
    from lab.web.stream import TextureStream

    recorder = Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=10.0)
    image = np.zeros((64, 64, 3), np.uint8)
    stream.update(image)  # the first texture goes whole, whatever the limit
    applied(server, stream)
    sent, deferred, started = 0, 0, time.monotonic()
    for value in range(1, 30):
        image[:] = value  # every tile changes on every update
        result = stream.update(image)
        sent += result["tiles_sent"]
        deferred += result["tiles_deferred"]
        time.sleep(0.02)
    assert deferred > 0 and sent <= 10.0 * (time.monotonic() - started) + 6  # the rate, plus half a second's burst
    newest = {}

    def every_tile_newest():
        newest.clear()
        for name, glb in recorder.sent[16:]:
            tile = TileMesh(glb)
            newest[tuple(tile.position_accessor["min"])] = material_images(glb)["color"]
        return len(newest) == 16 and all((crop == 29).all() for crop in newest.values())

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # nothing changes any more: the deferred tiles catch up
        stream.update(image)
        if every_tile_newest():
            break
        time.sleep(0.1)
    assert every_tile_newest(), "every tile ends with the newest texture"
    stream.close()


def test_a_planned_update_reads_only_the_blocks_it_asked_for(server):
    """TextureStream.plan: every tile changes faster than the rate limit lets go; the stream asks the maps' maker for
    the blocks of a few tiles only, the maker brings only those up to date (its maps stay stale elsewhere, as the
    look's are when sims.scene.assembly.Scene.composite gets `wanted`), and every crop published is the newest, never a stale
    one. Once the changes stop, every tile ends up published with the newest texture."""
    from lab.web.stream import TextureStream

    now, block = [0.0], 8
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=8.0, settle_s=0.0, clock=lambda: now[0])
    truth, shown = np.zeros((64, 64, 3), np.uint8), np.zeros((64, 64, 3), np.uint8)

    def pending():  # the blocks the maker's next maps would change
        return block, (shown != truth).any(axis=-1).reshape(8, block, 8, block).any(axis=(1, 3))

    assert stream.plan(pending()) is None  # before the first update: every block
    stream.update(shown)
    asked = []
    for step in range(1, 61):
        now[0] = 0.125 * step
        truth[:] = min(step, 24)  # changes for 3 s of the clock, then none
        wanted = stream.plan(pending())
        asked.append(wanted[1].mean())
        fresh = np.kron(wanted[1], np.ones((block, block), bool))
        shown[fresh] = truth[fresh]
        versions = [tile.version for tile in stream._tiles]
        stream.update(shown)
        for tile, before in zip(stream._tiles, versions):
            if tile.version != before:
                assert (tile.sent["color"] == truth[0, 0]).all(), f"a stale crop was published at step {step}"
    assert min(asked[:24]) <= 0.75  # while everything changes, only some blocks are asked for
    assert all((tile.sent["color"] == 24).all() for tile in stream._tiles), "every tile ends with the newest texture"
    stream.close()


def test_a_planned_update_does_not_pass_over_a_tile_a_change_reaches_again(server):
    """A tile the stream examined and found unchanged (pending work that changed no texel) is examined again when a
    change reaches it, though six other tiles keep changing and the budget is two tiles an update: a burn starting
    there is published within the rate limit's turn (one tile a second here), not passed over for good."""
    from lab.web.stream import TextureStream

    now, block = [0.0], 8
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=1.0, settle_s=0.0, clock=lambda: now[0])
    truth = np.zeros((64, 64, 3), np.uint8)
    stream.update(truth.copy())
    busy = [(0, 0), (0, 2), (1, 1), (2, 0), (2, 2), (3, 1)]  # stream tiles of 16 x 16 texels, by (row, col)
    quiet = (3, 3)
    flags = np.zeros((8, 8), bool)

    def tile_blocks(row, col):
        flags[2 * row:2 * row + 2, 2 * col:2 * col + 2] = True

    for row, col in busy:
        tile_blocks(row, col)
    tile_blocks(*quiet)  # pending work reaches the quiet tile, but its texels stay as published
    quiet_index = next(i for i, t in enumerate(stream._tiles) if t.geometry.r0 >= 46 and t.geometry.c0 >= 46)
    published_at = None
    for step in range(1, 60):
        for row, col in busy:
            truth[16 * row:16 * row + 16, 16 * col:16 * col + 16] = 10 * step % 250 + 5
        if step == 10:
            truth[52:60, 52:60] = 255  # a burn starts in the quiet tile
            tile_blocks(*quiet)
        version = stream._tiles[quiet_index].version
        now[0] = 0.125 * step
        stream.plan((block, flags.copy()))
        stream.update(truth.copy())
        flags[:] = False
        for row, col in busy:
            tile_blocks(row, col)
        if step >= 10 and stream._tiles[quiet_index].version != version:
            published_at = step
            break
    assert published_at is not None, "the burn's tile was never published"
    assert (stream._tiles[quiet_index].sent["color"] == 255).any()
    stream.close()


def test_stream_rate_limit_follows_the_clock_it_is_given(server):
    """A bench passes the simulated time as the clock: the stream then publishes per simulated second what the lab
    publishes per second, however fast or slow the machine runs (lab.bench.common.lab_stream)."""
    from lab.web.stream import TextureStream

    now = [0.0]
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=8.0, settle_s=0.0, clock=lambda: now[0])
    image = np.zeros((64, 64, 3), np.uint8)
    assert stream.update(image)["tiles_sent"] == 16  # the first texture goes whole
    sent = []
    for value in range(1, 17):  # every tile changes at every update, 1/8 s of the clock apart
        now[0] = 0.125 * value
        image[:] = value
        sent.append(stream.update(image)["tiles_sent"])
    assert sent == [4] + [1] * 15  # half a second's burst, then 8 per second of the clock: one per update
    now[0] += 10.0  # a long quiet spell of the clock: only the burst is saved up
    image[:] = 99
    assert stream.update(image)["tiles_sent"] == 4
    stream.close()


def test_stream_compares_only_the_blocks_its_maker_flags_and_keeps_deferred_tiles(server):
    """update(changed=(tile, flags)): texels outside the flagged blocks are taken as unchanged (the scene knows what it
    recomposed), so a change there is not looked at; a flagged tile the rate limit defers is still sent later, when
    nothing is flagged any more."""
    from lab.web.stream import TextureStream

    Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=2.0, settle_s=0.0)
    image = np.full((64, 64, 3), 120, np.uint8)
    stream.update(image)
    applied(server, stream)
    nothing = np.zeros((4, 4), bool)
    image[40:44, 10:14] = 255
    assert stream.update(image, changed=(16, nothing))["tiles_sent"] == 0  # not flagged: not compared
    flags = nothing.copy()
    flags[2, 0] = True  # the 16 x 16 block holding rows 40-43, columns 10-13
    image[2:6, 2:6] = 0   # and a change in another tile, flagged too
    flags[0, 0] = True
    time.sleep(0.6)  # one token
    first = stream.update(image, changed=(16, flags))
    assert first["tiles_sent"] == 1 and first["tiles_deferred"] == 1
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and not stream.update(image, changed=(16, nothing))["tiles_sent"]:
        time.sleep(0.1)  # the deferred tile goes with the next token although nothing is flagged now
    assert stream.update(image)["tiles_sent"] == 0, "every change was sent: a full comparison finds nothing left"
    stream.close()


def test_stream_sends_the_largest_change_first_and_lets_faint_changes_settle(server):
    """With one tile's budget: a fresh burn goes before a tile that changed less; a one-level change (tissue cooling)
    waits settle_s and then goes too."""
    from lab.web.stream import TextureStream

    recorder = Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=4, max_tiles_per_s=2.0, settle_s=1.0)  # one token per 0.5 s
    image = np.full((64, 64, 3), 120, np.uint8)
    stream.update(image)
    applied(server, stream)
    image[3:13, 3:13] = 130     # inside the top-left tile only (crops overlap by 2 texels): a change of 10 levels
    image[40:44, 40:44] = 250   # a fresh burn inside another tile
    first = stream.update(image)
    assert first["tiles_sent"] == 1 and first["tiles_deferred"] == 1
    assert (material_images(recorder.sent[-1][1])["color"] == 250).any(), "the burn should go first"
    time.sleep(0.6)
    assert stream.update(image)["tiles_sent"] == 1 and (material_images(recorder.sent[-1][1])["color"] == 130).any()
    time.sleep(0.6)
    image[20:28, 20:28] = 140   # a third tile changes and goes...
    assert stream.update(image)["tiles_sent"] == 1
    sent_at = time.monotonic()
    image[20:28, 20:28] = 141   # ...and right after, by one level more
    applied(server, stream)
    time.sleep(max(0.0, sent_at + 0.6 - time.monotonic()))  # a token is back, settle_s (since the tile's last send) not over yet
    assert stream.update(image) == {"tiles_sent": 0, "bytes": 0, "tiles_deferred": 1}, "a faint change waits to settle"
    time.sleep(0.5)
    assert stream.update(image)["tiles_sent"] == 1 and (material_images(recorder.sent[-1][1])["color"] == 141).any()
    assert stream.update(image)["tiles_deferred"] == 0
    stream.close()


@pytest.mark.parametrize("kind", ["normal", "roughness"])
def test_a_tile_whose_only_change_is_in_a_material_map_is_published_with_only_that_map_encoded_again(server, kind):
    from lab.web.stream import TextureStream

    recorder = Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=4)
    rgb = np.full((64, 64, 3), 120, np.uint8)
    normal, roughness = material_maps(64, 64)
    stream.update(rgb, normal=normal, roughness=roughness)
    applied(server, stream)
    encoded = []
    original = stream._encode
    stream._encode = lambda which, crop: encoded.append(which) or original(which, crop)
    before = {name: glb for name, glb in recorder.sent}
    maps = {"normal": normal.copy(), "roughness": roughness.copy()}
    maps[kind][40:44, 40:44] = 255 - maps[kind][40:44, 40:44]  # inside one tile, far from its borders
    result = stream.update(rgb, **maps)
    assert result["tiles_sent"] == 1 and encoded == [kind], (result, encoded)
    glb = recorder.sent[-1][1]
    old = material_images([g for name, g in before.items() if TileMesh(g).position_accessor == TileMesh(glb).position_accessor][0])
    new = material_images(glb)
    assert np.array_equal(old["color"], new["color"])
    for which in ("normal", "roughness"):
        assert np.array_equal(old[which], new[which]) == (which != kind), which
    assert stream.update(rgb, **maps)["tiles_sent"] == 0
    stream.close()


def test_update_checks_every_map_and_names_the_one_that_does_not_fit(server):
    from lab.web.stream import TextureStream

    stream = TextureStream(server, bumpy_patch(), tiles=2)
    rgb = np.zeros((32, 32, 3), np.uint8)
    normal, roughness = material_maps(32, 32)
    for arguments, name in [({"normal": normal[:16]}, "normal"), ({"normal": normal.astype(np.uint16)}, "normal"),
                            ({"normal": normal[..., :2]}, "normal"), ({"roughness": roughness[:, :16]}, "roughness"),
                            ({"roughness": roughness.astype(np.float32)}, "roughness"),
                            ({"roughness": normal}, "roughness")]:
        with pytest.raises(ValueError, match=f"^{name}:"):
            stream.update(rgb, **arguments)
    with pytest.raises(ValueError, match="^rgb:"):
        stream.update(rgb[..., 0])
    assert stream.update(rgb, normal=normal, roughness=roughness)["tiles_sent"] == 4
    stream.close()


# --- what a tile GLB holds ------------------------------------------------------------------------

def test_without_maps_a_tile_has_one_texture_and_the_constant_roughness(server):
    from lab.web.stream import TextureStream

    recorder = Recorder(server)
    stream = TextureStream(server, bumpy_patch(), tiles=2, roughness=0.55)
    stream.update(coordinate_image(32, 32))
    for _, glb in recorder.sent:
        document, _ = glb_parts(glb)
        material = document["materials"][0]
        assert set(material) == {"pbrMetallicRoughness"} and len(document["images"]) == 1
        assert material["pbrMetallicRoughness"] == {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 0.55}
    # maps from now on: every tile is published again, with them
    normal, roughness = material_maps(32, 32)
    assert stream.update(coordinate_image(32, 32), normal=normal, roughness=roughness)["tiles_sent"] == 4
    assert all(set(material_images(glb)) == {"color", "normal", "roughness"} for _, glb in recorder.sent[4:])
    stream.close()


@pytest.mark.parametrize("divisors, shape", [((1, 2), (96, 128)), ((1, 1), (96, 128)), ((2, 2), (96, 128)), ((1, 2), (61, 67))])
def test_tile_glb_has_the_maps_crops_quantized_geometry_and_exact_ghosts(server, divisors, shape):
    """Every tile: baseColorTexture, normalTexture and metallicRoughnessTexture decode to the crops of the maps (the
    normal or roughness map at half resolution when its divisor is 2: 2 x 2 texel means); POSITION int16 under a uniform node scale, within
    half a quantum of the mesh; normalized uint16 UVs that put each vertex on its own texel; ghost corners that the
    morph target puts exactly onto their vertex; and normals, as three.js recomputes them per tile, equal to the
    whole mesh's welded at seams."""
    from lab.web.stream import TextureStream
    from sims.surface.texels import welded_normal_sums

    recorder = Recorder(server)
    surface = bumpy_patch(seam=True)
    stream = TextureStream(server, surface, tiles=4, normal_divisor=divisors[0], roughness_divisor=divisors[1])
    height, width = shape
    rgb = coordinate_image(height, width)
    normal, roughness = material_maps(height, width)
    assert stream.update(rgb, normal=normal, roughness=roughness)["tiles_sent"] == 16
    vertices = np.asarray(surface.vertices_mm, np.float64)
    quantum = stream.grid.quantum
    whole = stream.grid.offset + quantum * stream.grid.quantize(vertices)  # the mesh as the tiles carry it
    welded = welded_normal_sums(whole, surface.faces)
    welded_float = welded_normal_sums(vertices, surface.faces)
    lookup = {tuple(np.round(v, 9)): i for i, v in enumerate(whole)}
    visible_faces, worst, worst_float, plain_worst = 0, 0.0, 0.0, 0.0
    for _, glb in recorder.sent:
        document, _ = glb_parts(glb)
        assert document["extensionsUsed"] == ["KHR_mesh_quantization"] == document["extensionsRequired"]
        # the material and its maps
        pbr = document["materials"][0]["pbrMetallicRoughness"]
        assert pbr["metallicFactor"] == 0.0 and pbr["roughnessFactor"] == 1.0
        maps = material_images(glb)
        r0, r1, c0, c1 = crop_box(maps["color"])

        def cut(image):  # the crop; a box may reach a texel past an odd-sized image: its edge texels repeat there
            pad = ((0, max(r1 - height, 0)), (0, max(c1 - width, 0))) + ((0, 0),) * (image.ndim - 2)
            return np.pad(image, pad, mode="edge")[r0:r1, c0:c1]

        assert np.array_equal(maps["color"], cut(rgb))
        if 2 in divisors:
            assert r0 % 2 == 0 == c0 % 2 and (r1 - r0) % 2 == 0 == (c1 - c0) % 2, "the box lines up with the 2 x 2 means"
        for kind, image, divisor in (("normal", normal, divisors[0]), ("roughness", roughness, divisors[1])):
            assert np.array_equal(maps[kind], cut(image) if divisor == 1 else half(cut(image))), kind
        assert maps["normal"].shape[2] == 3 and maps["roughness"].ndim == 2, "RGB normal map, greyscale roughness"
        # quantized geometry: SHORT positions (not normalized, 8-byte stride), one uniform node scale
        tile = TileMesh(glb)
        assert tile.position_accessor["componentType"] == SHORT and not tile.position_accessor.get("normalized", False)
        assert document["bufferViews"][tile.position_accessor["bufferView"]]["byteStride"] == 8
        assert tile.scale == [quantum] * 3
        assert tile.position_accessor["min"] == tile.positions.min(axis=0).tolist()
        assert tile.position_accessor["max"] == tile.positions.max(axis=0).tolist()
        assert np.abs(tile.positions).max() <= 32767
        assert tile.uv_accessor["componentType"] == UNSIGNED_SHORT and tile.uv_accessor["normalized"] is True
        # NORMAL declared as zeros without bytes: three.js shades it smoothly (it flat-shades a primitive without it)
        normals = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]]
        assert normals == {"componentType": 5126, "count": len(tile.positions), "type": "VEC3"}
        real = tile.world()[tile.real]
        nearest = [np.abs(vertices - p).max(axis=1).argmin() for p in real]
        assert np.abs(real - vertices[nearest]).max() <= 0.5 * quantum * (1 + 1e-9)
        # every real vertex: the texel under its glTF UV (origin top left) is the one under its OBJ UV
        crop_h, crop_w = r1 - r0, c1 - c0
        for index, original in zip(tile.real, nearest):
            u, v = surface.uv[original]
            row, col = min(int((1.0 - v) * height), height - 1), min(int(u * width), width - 1)
            s, t = tile.st[index]
            got = maps["color"][min(int(t * crop_h), crop_h - 1), min(int(s * crop_w), crop_w - 1)]
            assert abs(int(got[0]) - col % 256) <= 1 and abs(int(got[1]) - row % 256) <= 1, (u, v, got)
        # the ghosts: int16 sparse morph deltas, each ghost face a real vertex and two corners that morph onto it
        if tile.targets:
            morph = tile.morph_accessor
            assert morph["componentType"] == SHORT and not morph.get("normalized", False)
            assert morph["min"] == np.minimum(tile.deltas.min(axis=0), 0).tolist()
            assert morph["max"] == np.maximum(tile.deltas.max(axis=0), 0).tolist()
            assert document["meshes"][0]["weights"] == [1.0]
        drawn = tile.drawn()
        ghosts = tile.faces[tile.ghost_faces]
        assert np.isin(ghosts[:, 0], tile.real).all() and np.isin(ghosts[:, 1:], tile.morph_ids).all()
        assert np.array_equal(drawn[ghosts[:, 1]], drawn[ghosts[:, 0]]) and np.array_equal(drawn[ghosts[:, 2]], drawn[ghosts[:, 0]])
        assert np.array_equal(drawn[tile.real], tile.positions[tile.real]), "the morph moves ghost corners only"
        visible_faces += int((~tile.ghost_faces).sum())
        # normals as the browser recomputes them (un-morphed positions, ghosts counted)
        sums = tile.normal_sums().astype(np.float64)
        plain = np.zeros_like(sums)
        tri = tile.positions[tile.faces[~tile.ghost_faces]]
        cross = np.cross(tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 1]).astype(np.float64)
        for corner in range(3):
            np.add.at(plain, tile.faces[~tile.ghost_faces][:, corner], cross)
        for index in tile.real:
            target = lookup[tuple(np.round(tile.world()[index], 9))]

            def angle(a, b):
                return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0)))

            worst = max(worst, angle(sums[index], welded[target]))
            worst_float = max(worst_float, angle(sums[index], welded_float[target]))
            plain_worst = max(plain_worst, angle(plain[index], welded[target]))
    assert visible_faces == len(surface.faces)
    assert plain_worst > 2.0, "the test patch should need the ghosts"
    assert worst < 0.01, f"tile normals differ from the whole quantized mesh's by {worst:.4f} degrees"
    assert worst_float < 0.05, f"tile normals differ from the unquantized mesh's by {worst_float:.4f} degrees"
    stream.close()


def test_a_mesh_too_large_for_a_micrometre_grid_gets_a_coarser_one_that_still_fits_int16(server):
    """The grid's quantum comes from the mesh's extent (here 300 mm: about 5 um); positions and ghost corners fit
    int16, and positions stay within half a quantum."""
    from lab.web.stream import TextureStream

    surface = bumpy_patch()
    surface.vertices_mm = surface.vertices_mm * 5.0
    recorder = Recorder(server)
    stream = TextureStream(server, surface, tiles=4)
    stream.update(np.zeros((32, 32, 3), np.uint8))
    assert 300.0 / 65534 < stream.grid.quantum < 2 * 300.0 / 65534
    for _, glb in recorder.sent:
        tile = TileMesh(glb)
        assert np.abs(tile.positions).max() <= 32767 and np.abs(tile.drawn()).max() <= 32767
        real = tile.world()[tile.real]
        assert max(np.abs(surface.vertices_mm - p).max(axis=1).min() for p in real) <= 0.5 * stream.grid.quantum * 1.0001
    stream.close()
