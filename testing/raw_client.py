"""A raw websocket client for viser 1.1.1 that does what any web page can do, and no more.

It speaks the viser client's protocol (viser/client/src/WebsocketClientWorker.ts, MessageHandler.tsx):
the `viser-v<version>` subprotocol; from the server, binary frames of
`[8 bytes inner size][8 bytes compressed size][zstd(msgpack {"messages", "timestampSec",
"binaryBufferLengths"})][binary buffers, each 8-byte aligned]` where numpy arrays appear in the
messages as `{"__binary_index", "dtype"}` placeholders; to the server, one msgpack dict per message
with its class name under "type". Values are sent as given (NaN, inf, a string not among a
dropdown's options, numbers out of range): the server has to cope with whatever a page sends.

Modes: a normal client answers localStorage reads as a browser does (lab.web.client_sync relies on
them); `answer_requests=False` gives a "silent" client that reads everything and never answers;
`stall()` stops reading the socket (websockets then stops reading from TCP once `max_queue` frames
are waiting, so the server's sends back up), `resume()` reads again.
"""
from __future__ import annotations

import collections
import socket
import threading
import time

import msgspec.msgpack
import numpy as np
import viser
import websockets.exceptions
import websockets.sync.client
import zstandard
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.typing import Origin, Subprotocol
from websockets.uri import parse_uri


def decode_frame(frame: bytes) -> list[dict]:
    """The messages of one server frame, numpy arrays in place of their binary placeholders."""
    inner_size = int.from_bytes(frame[0:8], "little")
    compressed_size = int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16:16 + compressed_size], max_output_size=inner_size)
    payload = msgspec.msgpack.decode(inner)
    arrays, offset = [], 16 + compressed_size
    for length in payload.get("binaryBufferLengths") or ():
        offset += -offset % 8
        arrays.append(memoryview(frame)[offset:offset + length])
        offset += length
    return [_fill(message, arrays) for message in payload["messages"]]


def _fill(value, arrays):
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return np.frombuffer(arrays[value["__binary_index"]], np.dtype(value["dtype"]))
        return {key: _fill(item, arrays) for key, item in value.items()}
    if isinstance(value, list):
        return [_fill(item, arrays) for item in value]
    return value


class RawClient:
    """One websocket connection to a viser server, read on a background thread.

    Keeps what it learned: `gui` (label -> the element's add message: uuid, type, value, props with
    min/max/options...), `nodes` (scene node name -> its add message), `counts` (messages received
    per type), `glbs` ((monotonic s, node name, GLB bytes) of every GLB node added), and
    `requests_seen` / `requests_answered` (localStorage reads), `positions` (node name -> every position the server
    set, SetPositionMessage, in order)."""

    def __init__(self, port: int, origin: str | None = None, answer_requests: bool = True, timeout_s: float = 30.0,
                 host: str = "127.0.0.1", send_camera: bool = True, max_queue: int | None = None, strict: bool = False):
        """port: the viser server's port. origin: the Origin header to send (None: none, as non-browser tools do).
        answer_requests: answer localStorage reads. timeout_s: for opening the connection, s.
        send_camera: send a camera pose at once, as the viser client does; viser counts a client as connected
        (get_clients, on_client_connect, GUI callbacks) only after its first camera message.
        max_queue: frames websockets keeps unread before it stops reading the socket (None: no limit). A limit lets
        stall() back up the server, but a reader that falls behind under load then stops answering the server's pings
        too, and the server closes the connection after 20 s (a test's clicks were lost that way in CI).
        strict: a send on a closed connection raises instead of returning False."""
        self.strict = strict
        self.answer_requests = answer_requests
        self.gui: dict[str, dict] = {}
        self.nodes: dict[str, dict] = {}
        self.counts: collections.Counter = collections.Counter()
        self.glbs: list[tuple[float, str, bytes]] = []
        self.positions: collections.defaultdict = collections.defaultdict(list)
        self.requests_seen = self.requests_answered = 0
        self.close_code: int | None = None
        self._changed = threading.Condition()
        self._send_lock = threading.Lock()
        self._reading = threading.Event()
        self._reading.set()
        self._closing = False
        self._ws = websockets.sync.client.connect(
            f"ws://{host}:{port}", subprotocols=[f"viser-v{viser.__version__}"], origin=origin, compression=None,
            max_size=None, max_queue=max_queue, open_timeout=timeout_s)
        self._open = True
        self._reader = threading.Thread(target=self._read, name=f"raw-client-{port}", daemon=True)
        self._reader.start()
        if send_camera:
            self.send_camera()

    # --- what a page sends ------------------------------------------------------------------
    def send(self, message: dict) -> bool:
        """Send one message (a dict with "type"). False if the connection is closed."""
        try:
            with self._send_lock:
                self._ws.send(msgspec.msgpack.encode(message))
            return True
        except websockets.exceptions.ConnectionClosed as exc:
            if self.strict:
                raise ConnectionError(f"the server closed this client's connection: {exc}") from None
            return False

    def send_frame(self, data: bytes | str) -> bool:
        """Send one websocket frame as it is (str: a text frame), however malformed. False if the connection is closed."""
        try:
            with self._send_lock:
                self._ws.send(data)
            return True
        except websockets.exceptions.ConnectionClosed:
            return False

    def send_camera(self, position=(0.0, -100.0, 100.0), look_at=(0.0, 0.0, 0.0)) -> bool:
        """A viewer camera pose (mm), as the viser client sends on connecting and whenever the view moves."""
        return self.send({"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": list(position),
                          "fov": 0.87, "near": 0.01, "far": 1000.0, "image_height": 600, "image_width": 960,
                          "look_at": list(look_at), "up_direction": [0.0, 0.0, 1.0]})

    def set_gui_value(self, label: str, value) -> bool:
        """Send a new value for the GUI element with this label, whatever the value is."""
        return self.send_gui_update(self.wait_for_gui(label)["uuid"], value)

    def send_gui_update(self, uuid: str, value) -> bool:
        return self.send({"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}})

    def click_button(self, label: str) -> bool:
        """Click the button with this label (the viser client sends value true)."""
        return self.set_gui_value(label, True)

    def move_transform(self, node_name: str, wxyz, position) -> bool:
        """Drag the transform controls named node_name to this pose (any numbers, NaN included), as the gizmo does:
        drag start, update, drag end."""
        owner = self.wait_for_node(node_name).get("owner", "")
        update = {"type": "TransformControlsUpdateMessage", "name": node_name, "wxyz": [float(v) for v in wxyz],
                  "position": [float(v) for v in position], "owner": owner}
        return all(self.send(message) for message in (
            {"type": "TransformControlsDragStartMessage", "name": node_name, "owner": owner}, update,
            {"type": "TransformControlsDragEndMessage", "name": node_name, "owner": owner}))

    def click_scene(self, ray_origin, ray_direction, screen_pos=(0.5, 0.5)) -> bool:
        """A click in the 3D view: viser's ScenePointerMessage carries the camera ray (world units) and the click's
        position on the screen (OpenCV convention, 0..1)."""
        return self.send({"type": "ScenePointerMessage", "event_type": "click",
                          "ray_origin": [float(v) for v in ray_origin], "ray_direction": [float(v) for v in ray_direction],
                          "screen_pos": [[float(v) for v in screen_pos]], "modifier": None})

    # --- what it learned --------------------------------------------------------------------
    def wait_for(self, predicate, timeout_s: float = 30.0):
        """Wait until predicate() is truthy (checked whenever a message arrives) and return its value."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not (result := predicate()):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._open:
                    raise TimeoutError(f"{getattr(predicate, '__name__', 'condition')} not met in {timeout_s} s"
                                       f"{'' if self._open else ' (connection closed)'}")
                self._changed.wait(min(remaining, 0.5))
            return result

    def wait_for_gui(self, label: str, timeout_s: float = 30.0) -> dict:
        """The add message of the GUI element with this label (uuid, type, value, props)."""
        return self.wait_for(lambda: self.gui.get(label), timeout_s)

    def wait_for_node(self, name: str, timeout_s: float = 30.0) -> dict:
        """The add message of the scene node with this name (type, props, owner)."""
        return self.wait_for(lambda: self.nodes.get(name), timeout_s)

    @property
    def connected(self) -> bool:
        """False once the connection is closed (by the server or by close())."""
        return self._open

    def stall(self) -> None:
        """Stop reading (a page that hangs): with max_queue set, websockets then stops reading the socket and the
        server's sends to it back up."""
        self._reading.clear()

    def resume(self) -> None:
        self._reading.set()

    def close(self) -> None:
        self._closing = True
        self._reading.set()
        self._ws.close()
        self._reader.join(timeout=10)

    # --- internals --------------------------------------------------------------------------
    def _read(self) -> None:
        try:
            while not self._closing:
                if not self._reading.wait(0.1):
                    continue
                try:
                    frame = self._ws.recv(timeout=0.1)
                except TimeoutError:
                    continue
                for message in decode_frame(frame):
                    self._handle(message)
        except websockets.exceptions.ConnectionClosed:
            pass
        finally:
            self.close_code = self._ws.close_code
            with self._changed:
                self._open = False
                self._changed.notify_all()

    def _handle(self, message: dict) -> None:
        kind = message.get("type", "")
        with self._changed:
            self.counts[kind] += 1
            props = message.get("props")
            if "uuid" in message and isinstance(props, dict) and "label" in props:
                self.gui[props["label"]] = message
            elif kind == "GuiUpdateMessage":  # the server changed a value or a prop: keep the latest
                for known in self.gui.values():
                    if known["uuid"] == message["uuid"]:
                        known["props"] = {**known["props"], **message.get("updates", {})}
            elif kind == "GuiRemoveMessage":
                self.gui = {label: m for label, m in self.gui.items() if m["uuid"] != message["uuid"]}
            elif kind == "SetPositionMessage":
                self.positions[message["name"]].append(tuple(message["position"]))
            elif kind == "RemoveSceneNodeMessage":
                self.nodes.pop(message["name"], None)
            elif "name" in message and isinstance(props, dict):
                self.nodes[message["name"]] = message
                if kind == "GlbMessage":
                    self.glbs.append((time.monotonic(), message["name"], bytes(props["glb_data"])))
            self._changed.notify_all()
        if kind == "LocalStorageGetItemRequestMessage":
            self.requests_seen += 1
            if self.answer_requests:
                self.send({"type": "LocalStorageGetItemResponseMessage", "value": None, "error": None,
                           "request_uuid": message["request_uuid"]})
                self.requests_answered += 1


def pipelined_connection(port: int, origin: str | None, messages: list[dict], host: str = "127.0.0.1",
                         timeout_s: float = 10.0) -> dict:
    """Open a websocket and send `messages` in the same TCP write as the upgrade request, before any answer (what
    a page's fastest possible sends look like to the server), then read until the server closes or timeout_s.
    Returns {"status": HTTP status of the handshake, "close_code": int or None, "frames": data frames received}."""
    protocol = ClientProtocol(parse_uri(f"ws://{host}:{port}"), origin=Origin(origin) if origin else None,
                              subprotocols=[Subprotocol(f"viser-v{viser.__version__}")])
    protocol.send_request(protocol.connect())
    frames = b"".join(Frame(Opcode.BINARY, msgspec.msgpack.encode(m)).serialize(mask=True, extensions=[])
                      for m in messages)
    result = {"status": None, "close_code": None, "frames": 0}
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        sock.sendall(protocol.data_to_send()[0] + frames)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and result["close_code"] is None:
            try:
                data = sock.recv(1 << 16)
            except socket.timeout:
                break
            if not data:
                break
            protocol.receive_data(data)
            for event in protocol.events_received():
                if hasattr(event, "status_code"):
                    result["status"] = event.status_code
                elif event.opcode is Opcode.CLOSE:
                    result["close_code"] = protocol.close_rcvd.code if protocol.close_rcvd else None
                elif event.opcode in (Opcode.BINARY, Opcode.TEXT):
                    result["frames"] += 1
            for chunk in protocol.data_to_send():
                if chunk:
                    sock.sendall(chunk)
    return result
