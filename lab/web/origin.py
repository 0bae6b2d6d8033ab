"""Refuse websocket connections that a foreign web page opens to the lab's viser server.

A browser lets any page open a websocket to ws://127.0.0.1:PORT (no same-origin rule for
websockets), and viser 1.1.1 checks no Origin: any site the user visits could drive the lab's
sliders, tools and scene. A page cannot leave out or forge the Origin header, so a connection whose
Origin is present and not the server's own is refused; connections without one (scripts, the tests'
raw client) are let in: they could as well set any header they like.

Where it hooks into viser (private parts, checked by `refuse_foreign_origins`; it raises if an
upgrade removed them). viser's per-connection handler (viser/infra/_infra.py, `ws_handler`) runs
the infra-level `WebsockServer.on_client_connect` callbacks after the websocket handshake and BEFORE
it starts the tasks that send to the client and read from it. `ViserServer.on_client_connect` is
too late: it fires on the client's first camera message, and GUI updates sent before that camera
message would already have been applied. So an async infra-level callback looks up the
connection's handshake request (`WebsockServer._live_connections[client_id].request.headers`) and,
for a foreign Origin, closes the websocket (code 1008) before anything is sent to it: the scene and
GUI never leave the server. Messages the page pipelined behind the handshake can still be read from
the socket after the close, so the server's message dispatch (`WebsockServer._handle_incoming_message`)
passes on only messages of connections that passed the check, and a refused connection's own
dispatch (its camera handler: the client would count as connected) drops everything.

A foreign page could also show the lab inside a frame of its own and trick the user into clicking it: every HTTP
response says that only the lab's own pages may frame it (FRAME_HEADERS). viser keeps its websockets Server only in
a local (`serve_future`) of its `start_server` coroutine, found among the event loop's tasks; it gets a
`process_response` hook. The guard installs lab.web.client_guard too (`OriginGuard.messages`): what a connection that
passed may send.
"""
from __future__ import annotations

import asyncio
import socket
from typing import Iterable

_POLICY_VIOLATION = 1008  # websocket close code
_WILDCARD_HOSTS = {"", "0.0.0.0", "::", "[::]"}
_LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")
FRAME_HEADERS = {"X-Frame-Options": "SAMEORIGIN", "Content-Security-Policy": "frame-ancestors 'self'"}


def own_origins(host: str, port: int, allowed: Iterable[str] = ()) -> set[str]:
    """Origins of pages served by this server (lower case, no trailing slash): http and https on 127.0.0.1,
    localhost, [::1], this machine's host name and the bound host (unless a wildcard), at port; plus `allowed`
    (e.g. "https://lab.example.org" for a reverse proxy)."""
    hosts = set(_LOOPBACK_HOSTS) | {socket.gethostname().lower()}
    if host not in _WILDCARD_HOSTS:
        hosts.add(_bracketed(host.lower()))
    origins = {f"{scheme}://{name}:{port}" for scheme in ("http", "https") for name in hosts}
    return origins | {origin.strip().rstrip("/").lower() for origin in allowed}


def _bracketed(host: str) -> str:
    """An IPv6 literal as it appears in a URL."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


class OriginGuard:
    """The check installed on one ViserServer; see the module docstring and `refuse_foreign_origins`."""

    def __init__(self, server, allowed: Iterable[str] = ()):
        """server: a started viser.ViserServer (1.1.1). allowed: more origins to let in, e.g. a reverse proxy's."""
        from lab.web.client_guard import guard_client_messages

        websock = getattr(server, "_websock_server", None)
        live = getattr(websock, "_live_connections", None)
        if not isinstance(live, dict) or not callable(getattr(websock, "_handle_incoming_message", None)) \
                or not callable(getattr(websock, "on_client_connect", None)):
            raise RuntimeError("lab.web.origin: this viser version has no WebsockServer._live_connections / "
                               "_handle_incoming_message / on_client_connect; the Origin check cannot be installed")
        self.origins = own_origins(server.get_host(), server.get_port(), allowed)
        self.refused = 0                  # connections refused so far
        self.last_refused: str | None = None  # the Origin of the last one
        self._port = server.get_port()
        self._live = live
        self._accepted: set[int] = set()  # ids of the open connections that passed the check
        dispatch = websock._handle_incoming_message

        async def dispatch_if_accepted(client_id, message):
            if client_id in self._accepted:
                await dispatch(client_id, message)

        websock.on_client_connect(self._check)
        websock.on_client_disconnect(self._forget)
        for client_id, raw in list(live.items()):  # connections opened before the guard: check them now
            if self._admit(raw):
                self._accepted.add(client_id)
            else:
                asyncio.run_coroutine_threadsafe(raw.close(_POLICY_VIOLATION, "origin not allowed"),
                                                 websock._background_event_loop)
        websock._handle_incoming_message = dispatch_if_accepted
        _forbid_framing(websock)
        self.messages = guard_client_messages(server)  # what an accepted connection may send

    def allows(self, origin: str | None, local_ip: str | None = None) -> bool:
        """True for no Origin, one of `origins`, or the address the connection came in on (a page loaded from
        http://<this machine's IP>:PORT when the server listens on every interface)."""
        if origin is None:
            return True
        origin = origin.strip().rstrip("/").lower()
        if origin in self.origins:
            return True
        return local_ip is not None and origin in {f"{scheme}://{_bracketed(local_ip.lower())}:{self._port}"
                                                   for scheme in ("http", "https")}

    def _admit(self, raw) -> bool:
        """Check one connection's handshake request (raw: its websockets ServerConnection, or None)."""
        request = getattr(raw, "request", None)
        origin = request.headers.get("Origin") if request is not None else "<no request>"
        local = raw.local_address[0] if request is not None and raw.local_address else None
        if request is not None and self.allows(origin, local):
            return True
        self.refused += 1
        self.last_refused = origin
        return False

    async def _check(self, conn) -> None:
        """Infra-level connect callback: runs before viser sends to or reads from the connection."""
        raw = self._live.get(conn.client_id)
        if self._admit(raw):
            self._accepted.add(conn.client_id)
            return
        conn._handle_incoming_message = _drop  # the handlers registered on this connection (camera etc.)
        if raw is not None:
            await raw.close(_POLICY_VIOLATION, "origin not allowed")

    def _forget(self, conn) -> None:
        self._accepted.discard(conn.client_id)


def _forbid_framing(websock) -> None:
    """Every HTTP response of this viser WebsockServer carries FRAME_HEADERS (see the module docstring)."""

    async def find_server():
        for task in asyncio.all_tasks():
            coro = task.get_coro()
            if getattr(coro, "__name__", "") == "start_server" and getattr(coro, "cr_frame", None) is not None:
                return coro.cr_frame.f_locals.get("serve_future")
        return None

    http = asyncio.run_coroutine_threadsafe(find_server(), websock._background_event_loop).result(timeout=30)
    if http is None or getattr(http, "process_response", False) is not None:
        raise RuntimeError("lab.web.origin: viser's start_server task holds no websockets Server without process_response; "
                           "the framing headers cannot be added")
    http.process_response = _add_frame_headers


def _add_frame_headers(connection, request, response) -> None:
    """websockets process_response hook: the response as it is, plus FRAME_HEADERS."""
    for name, value in FRAME_HEADERS.items():
        response.headers[name] = value


async def _drop(client_id, message) -> None:
    """A refused client's messages go nowhere."""


def refuse_foreign_origins(server, allowed: Iterable[str] = ()) -> OriginGuard:
    """Make a viser 1.1.1 ViserServer refuse websocket connections whose Origin header is present and not the
    server's own (see own_origins and OriginGuard.allows); `allowed` adds origins, e.g. a reverse proxy's
    "https://lab.example.org". Call it right after creating the server, before a browser can connect.
    Raises RuntimeError if viser lacks the private parts it hooks into."""
    return OriginGuard(server, allowed)
