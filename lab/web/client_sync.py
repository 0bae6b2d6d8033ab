"""How far each browser has got through the messages the server sent to it alone.

The viser client applies scene messages in batches, once per drawn frame. A browser that draws one
frame every few seconds (software WebGL on a loaded machine) and got a tile's new node and the
removal of the old one in one batch would drop the old node at once while the new one still
parses: for a frame the tile is a hole. A fixed delay cannot rule that out; an acknowledgement can.

`ClientSync` keeps one round trip in flight per connected client: a localStorage read (viser's
cheapest request with a reply, applied in the same frame-synchronized batches as scene messages, no
render and nothing visible). It goes through the client's own message queue (viser's per-client
buffer), the queue lab.web.stream sends that client's tile nodes through, so the client handles them in
the order they were queued, the request after every tile queued before it. Positions come from the
caller (`position()`, e.g. lab.web.stream's count of tile messages queued so far): each request notes
the position before it is queued, and its reply proves the client applied everything queued to it
before that position. `confirmed_by(client)` is the position that client has applied with one
reply to spare, so a frame has drawn it too; `positions(client)` gives also the position of its last
reply (applied, maybe not drawn yet).

A client that never answers (frozen, or hostile) holds back only its own position; its one request
stays in flight and is sent again after `timeout_s`.
"""
from __future__ import annotations

import threading
import warnings
from typing import Callable

_KEY = "tissue-lab-sync"
_SPARE_REPLIES = 1
# a request raced with the client leaving: nothing is lost, the ping loop ends on the next check
warnings.filterwarnings("ignore", message="Queued a LocalStorageGetItemRequestMessage on a closed connection")


class ClientSync:
    """Background round trips to every client of a viser server; see the module docstring."""

    def __init__(self, server, position: Callable[[], float], interval_s: float = 0.2, timeout_s: float = 30.0):
        """server: viser.ViserServer. position: the position after everything queued to the clients so far (a
        count that only grows). interval_s: pause between one reply and the next request, s. timeout_s: a request
        unanswered this long is sent again, s."""
        self.server = server
        self.position = position
        self.interval_s = float(interval_s)
        self.timeout_s = float(timeout_s)
        self._lock = threading.Lock()
        self._sent: dict[int, list[float]] = {}  # client id -> positions of its last answered requests
        self._stop = threading.Event()
        self._threads: dict[int, threading.Thread] = {}
        self._watcher = threading.Thread(target=self._watch, name="client-sync", daemon=True)
        self._watcher.start()

    def mark(self) -> float:
        """The position after every message queued so far."""
        return float(self.position())

    def positions(self, client_id: int) -> tuple[float, float]:
        """(applied, confirmed) positions of this client (compare with mark()): it has applied everything queued to it
        before `applied` (its last reply), and applied and had a frame to draw everything before `confirmed`; -inf
        until it has answered one request, or enough for the spare reply."""
        with self._lock:
            sent = self._sent.get(client_id, [])
        applied = sent[-1] if sent else float("-inf")
        return applied, sent[0] if len(sent) > _SPARE_REPLIES else float("-inf")

    def confirmed_by(self, client_id: int) -> float:
        """A position p: this client has applied, and had a frame to draw, everything queued to it before p."""
        return self.positions(client_id)[1]

    def confirmed(self) -> float:
        """The smallest confirmed_by over the connected clients; +inf with no clients."""
        return min((self.confirmed_by(client_id) for client_id in self.server.get_clients()), default=float("inf"))

    def close(self) -> None:
        self._stop.set()

    # --- internals --------------------------------------------------------------------------
    def _watch(self) -> None:
        while not self._stop.wait(0.1):
            clients = self.server.get_clients()
            for client_id in [c for c, thread in self._threads.items() if c not in clients and not thread.is_alive()]:
                del self._threads[client_id]
            for client_id, client in clients.items():
                thread = self._threads.get(client_id)
                if thread is None or not thread.is_alive():
                    thread = threading.Thread(target=self._ping, args=(client_id, client), name=f"client-sync-{client_id}",
                                              daemon=True)
                    self._threads[client_id] = thread
                    thread.start()

    def _ping(self, client_id: int, client) -> None:
        """Round trips to one client until it leaves or the sync closes."""
        while not self._stop.is_set() and client_id in self.server.get_clients():
            sent = self.mark()  # before the request is queued: everything counted in it is queued ahead of it
            try:
                client.local_storage.get_item(_KEY, timeout=self.timeout_s)
            except TimeoutError:
                continue
            except RuntimeError:
                if client_id not in self.server.get_clients():
                    break  # it left
                # the browser refused localStorage: still a reply, after the earlier messages
            with self._lock:
                self._sent[client_id] = (self._sent.get(client_id, []) + [sent])[-(_SPARE_REPLIES + 1):]
            self._stop.wait(self.interval_s)
        with self._lock:
            self._sent.pop(client_id, None)
