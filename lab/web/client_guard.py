"""Decide which client messages reach viser (1.1.1): only what the viser client's widgets send.

viser applies a client's message as it comes. Every key of a GuiUpdateMessage is assigned to the server's handle
(`gui_api`, `update_cb`, `sync_cb`: one page could break a widget, or the lab, for every browser); a gizmo pose is
relayed to every other browser before the app has looked at it; a frame it cannot decode ends in a traceback. Here,
between the socket and viser's dispatch, each frame is one of:
- malformed (a text frame, bad msgpack, nesting too deep, an unknown type or one only the server sends): counted under
  "malformed", and that connection is closed (code 1003) without a traceback;
- a message the lab does not take: a GUI update other than {"value": v} for an input that is shown and enabled, v of the
  input's kind (a button: true); a camera with numbers that are not finite; a click, drag or storage answer whose fields
  have the wrong shape; a type the lab does not use (uploads, forms, commands, share URLs, renders, node clicks and
  drags): dropped, counted under its type;
- passed on. A gizmo pose of 3 + 4 numbers is passed on whatever the numbers (the app refuses it and puts the gizmo back),
  but viser relays it to the other browsers only when it is sound (`sound_pose`), its quaternion normalised; one that
  is not is counted under "pose not relayed".

Where it hooks into viser (private parts, checked by `ClientGuard`; it raises RuntimeError if an upgrade removed them):
`viser.infra._infra._message_consumer`, looked up by viser's per-connection handler each time a connection opens,
becomes `_guarded_consumer`; a `_TransformControlsState` keeps its `sync_cb` (the relay) as `lab_relay`, which
`SceneApi._fire_transform_controls_callbacks` calls before the callbacks (`_relay_then_fire`). All process-wide, idempotent; a connection of a server without a
ClientGuard has its malformed frames refused the same way and everything else passed on, as viser would.
"""
from __future__ import annotations

import collections
import logging
import math
import numbers
import weakref

import numpy as np

POSE_LIMIT = 1e6           # |coordinate| beyond which a gizmo position is not relayed (scene units: mm in the lab)
UNSUPPORTED_DATA = 1003    # websocket close code for a malformed frame
MAX_INT = 2**63            # whole numbers an integer input takes (msgpack encodes at most 64 bits)
# what the viser 1.1.1 client sends (viser/client/src: its sendMessage calls); any other type is the server's own
BROWSER_SENDS = frozenset({
    "ViewerCameraMessage", "GuiUpdateMessage", "TransformControlsUpdateMessage", "TransformControlsDragStartMessage",
    "TransformControlsDragEndMessage", "ScenePointerMessage", "LocalStorageGetItemResponseMessage", "GuiButtonHoldMessage",
    "GuiFormSubmitMessage", "GuiFormDirtyMessage", "FileTransferStartUpload", "FileTransferPart", "FileTransferPartAck",
    "CommandTriggerMessage", "SceneNodeClickMessage", "SceneNodeDragMessage", "GetRenderResponseMessage",
    "ShareUrlRequest", "ShareUrlDisconnect",
})
_ROUTES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # websockets connection -> (ClientGuard, client id)
_GUARDS: weakref.WeakSet = weakref.WeakSet()


def sound_pose(wxyz, position) -> bool:
    """A pose other browsers may be sent: 4 + 3 finite numbers, the position within POSE_LIMIT, the quaternion not
    (near) zero."""
    wxyz, position = np.asarray(wxyz, np.float64), np.asarray(position, np.float64)
    if not (np.isfinite(wxyz).all() and np.isfinite(position).all()):
        return False
    with np.errstate(over="ignore"):
        return bool(np.abs(position).max() <= POSE_LIMIT and 1e-6 < np.linalg.norm(wxyz) < math.inf)


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers(value, length: int, finite: bool = False) -> bool:
    """value is `length` numbers (all finite if asked)."""
    return isinstance(value, (list, tuple)) and len(value) == length and all(
        _number(v) and (not finite or math.isfinite(v)) for v in value)


def _like(value, current) -> bool:
    """value is what the widget holding `current` sends: a bool, a number (a whole one for an integer input), a text,
    or a tuple of those; viser casts it to current's type, which then cannot fail or turn a text into a number."""
    if isinstance(current, (bool, np.bool_)):
        return isinstance(value, bool)
    if isinstance(current, numbers.Integral):  # viser casts it to an int and sends that to every browser: one past
        return _number(value) and -MAX_INT < value < MAX_INT  # msgpack's 64 bits broke their connections (1e308)
    if isinstance(current, numbers.Real):
        return _number(value)
    if isinstance(current, str):
        return isinstance(value, str)
    if isinstance(current, tuple):
        return isinstance(value, (list, tuple)) and len(value) == len(current) and all(map(_like, value, current))
    return False


class ClientGuard:
    """The checks installed on one ViserServer; see the module docstring. `dropped` counts what was refused, by
    message type, "malformed", "pose not relayed" and "failed handshake" (a connection that closed or sent nonsense
    before its websocket opened)."""

    def __init__(self, server):
        """server: a started viser.ViserServer (1.1.1)."""
        websock = getattr(server, "_websock_server", None)
        inputs = getattr(getattr(server, "gui", None), "_gui_input_handle_from_uuid", None)
        if not isinstance(getattr(websock, "_live_connections", None), dict) or not isinstance(inputs, dict) \
                or not callable(getattr(websock, "on_client_connect", None)):
            raise RuntimeError("lab.web.client_guard: this viser version has no WebsockServer._live_connections / "
                               "GuiApi._gui_input_handle_from_uuid; client messages cannot be checked")
        _install()
        self.dropped: collections.Counter = collections.Counter()
        self.port = server.get_port()
        self._server = server
        self._live = websock._live_connections
        self._checks = {"TransformControlsUpdateMessage": self._pose,
                        "TransformControlsDragStartMessage": _named, "TransformControlsDragEndMessage": _named,
                        "ViewerCameraMessage": _camera, "ScenePointerMessage": _pointer,
                        "LocalStorageGetItemResponseMessage": _storage_answer}
        for client_id, raw in list(self._live.items()):  # connections opened before the guard
            _ROUTES[raw] = (self, client_id)
        websock.on_client_connect(self._route)
        _GUARDS.add(self)

    def admit(self, client_id: int, message) -> bool:
        """Whether viser may have this decoded message of this client; counts it when not."""
        kind = type(message).__name__
        if kind == "GuiUpdateMessage":
            admitted = self._gui_update(client_id, message)
        else:
            check = self._checks.get(kind)
            admitted = check is not None and check(message)
        if admitted:
            return True
        self.dropped[kind] += 1
        return False

    def _route(self, conn) -> None:
        """Infra-level connect callback: runs before viser reads from the connection."""
        raw = self._live.get(conn.client_id)
        if raw is not None:
            _ROUTES[raw] = (self, conn.client_id)

    def _gui_update(self, client_id: int, message) -> bool:
        updates = message.updates
        if not isinstance(message.uuid, str) or not isinstance(updates, dict) or list(updates) != ["value"]:
            return False
        handle = self._server.gui._gui_input_handle_from_uuid.get(message.uuid)
        if handle is None:  # an input of this client's own GUI, if any
            client = self._server.get_clients().get(client_id)
            handle = None if client is None else client.gui._gui_input_handle_from_uuid.get(message.uuid)
        if handle is None:
            return False
        state = handle._impl
        if state.removed or not getattr(state.props, "visible", True) or getattr(state.props, "disabled", False):
            return False
        return updates["value"] is True if state.is_button else _like(updates["value"], state.value)

    def _pose(self, message) -> bool:
        if not (isinstance(message.name, str) and isinstance(message.owner, str) and _numbers(message.wxyz, 4)
                and _numbers(message.position, 3)):
            return False
        if sound_pose(message.wxyz, message.position):
            wxyz = np.asarray(message.wxyz, np.float64)
            message.wxyz = tuple(float(v) for v in wxyz / np.linalg.norm(wxyz))
        else:
            self.dropped["pose not relayed"] += 1
        return True


def _named(message) -> bool:
    return isinstance(message.name, str) and isinstance(message.owner, str)


def _camera(message) -> bool:
    return (_numbers(message.wxyz, 4, True) and _numbers(message.position, 3, True) and _numbers(message.look_at, 3, True)
            and _numbers(message.up_direction, 3, True) and _numbers((message.fov, message.near, message.far), 3, True)
            and all(isinstance(v, int) and 0 <= v <= 1 << 16 for v in (message.image_height, message.image_width)))


def _pointer(message) -> bool:
    """A click or a box selection; the rays' numbers are the app's to check (it says why it refuses them)."""
    screen = message.screen_pos
    return (message.event_type in ("click", "rect-select")
            and all(ray is None or _numbers(ray, 3) for ray in (message.ray_origin, message.ray_direction))
            and isinstance(screen, (list, tuple)) and 1 <= len(screen) <= 2 and all(_numbers(p, 2) for p in screen)
            and (message.modifier is None or isinstance(message.modifier, str) and len(message.modifier) <= 32))


def _storage_answer(message) -> bool:
    return isinstance(message.request_uuid, str) and all(v is None or isinstance(v, str) for v in (message.value, message.error))


def _decode(raw, message_class):
    """The message in one frame, or None for a text frame, bad msgpack, too deep a nesting or a type the client never
    sends."""
    if not isinstance(raw, bytes):
        return None
    try:
        message = message_class.deserialize(raw)
    except Exception:  # msgpack errors, RecursionError, a missing or unknown type, fields that do not fit
        return None
    return message if type(message).__name__ in BROWSER_SENDS else None


async def _guarded_consumer(websocket, handle_message, message_class) -> None:
    """viser's `_message_consumer` with every frame checked first (module docstring)."""
    while True:
        raw = await websocket.recv()
        guard, client_id = _ROUTES.get(websocket, (None, None))
        message = _decode(raw, message_class)
        if message is None:
            if guard is not None:
                guard.dropped["malformed"] += 1
            await websocket.close(UNSUPPORTED_DATA, "malformed message")
            continue  # the next recv raises ConnectionClosed, which viser's handler takes as a disconnect
        if guard is None or guard.admit(client_id, message):
            handle_message(message)


def _relay_then_fire(fire):
    """viser's SceneApi._fire_transform_controls_callbacks, relaying a client's sound gizmo pose to the other browsers
    first. viser relays after handing the pose to the app's callbacks on its thread pool: a put-back made there before
    the relay was replaced by the relay (same node, the sender excluded), and the sender's gizmo stayed where it was."""
    async def relay_then_fire(self, client_id, handle, phase, *args, **kwargs):
        relay = getattr(handle._impl_aux, "lab_relay", None)
        if phase == "update" and relay is not None and not handle._impl.removed \
                and sound_pose(handle._impl.wxyz, handle._impl.position):
            relay(client_id, handle)
        await fire(self, client_id, handle, phase, *args, **kwargs)
    return relay_then_fire


class _QuietHandshakes(logging.Filter):
    """A connection that closes or sends nonsense before its websocket opens is counted, not logged with a traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.getMessage() != "opening handshake failed":
            return True
        local = getattr(getattr(record, "websocket", None), "local_address", None)
        for guard in list(_GUARDS):
            if local and local[1] == guard.port:
                guard.dropped["failed handshake"] += 1
        return False


def _install() -> None:
    """The process-wide hooks (idempotent); RuntimeError when this viser lacks what they replace."""
    from viser import _scene_api, _scene_handles
    from viser.infra import _infra

    state = getattr(_scene_handles, "_TransformControlsState", None)
    fire = getattr(_scene_api.SceneApi, "_fire_transform_controls_callbacks", None)
    if not callable(getattr(_infra, "_message_consumer", None)) or "sync_cb" not in getattr(state, "__dataclass_fields__", {}) \
            or not callable(fire):
        raise RuntimeError("lab.web.client_guard: viser has no infra._message_consumer, _TransformControlsState.sync_cb or "
                           "SceneApi._fire_transform_controls_callbacks; check the client checks still apply")
    if getattr(_infra, "_lab_guarded", False):
        return
    _infra._message_consumer = _guarded_consumer
    _scene_api.SceneApi._fire_transform_controls_callbacks = _relay_then_fire(fire)
    original = state.__init__

    def __init__(self, *args, **kwargs):  # viser's own relay, after the callbacks, is off: _relay_then_fire relays
        original(self, *args, **kwargs)
        self.lab_relay, self.sync_cb = self.sync_cb, None

    state.__init__ = __init__
    # first: viser's own filter for these (added on a server's first HTTP request) would hide them from the count
    logging.getLogger("websockets.server").filters.insert(0, _QuietHandshakes())
    _infra._lab_guarded = True


def guard_client_messages(server) -> ClientGuard:
    """Check every message a client of this viser 1.1.1 ViserServer sends before viser applies it (module docstring).
    Call it right after creating the server. Raises RuntimeError if viser lacks the private parts it hooks into."""
    return ClientGuard(server)
