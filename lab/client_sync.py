"""How far each browser has got through the messages the server sent it.

The viser client applies scene messages in batches, once per drawn frame. A browser that draws one
frame every few seconds (software WebGL on a loaded machine), or reads its websocket slowly so that
viser's broadcast queue backs up, gets a tile's new node and the removal of the old one in one batch:
the old node goes at once, the new one is still parsing, and for a frame the tile is a hole. A fixed
delay cannot rule that out; an acknowledgement can.

`ClientSync` keeps one round trip in flight per connected client: a localStorage read (viser's
cheapest request with a reply, applied in the same frame-synchronized batches as scene messages, no
render and nothing visible). Positions in the broadcast queue order what was sent: `mark()` is the
position after everything queued so far; each request notes how far that client's share of the
broadcast queue had been handed to its socket, and a reply proves the client applied all of it.
`confirmed()` is the position every connected client has applied with one reply to spare, so a frame
has drawn it too. Positions are viser's broadcast message ids (private attributes, checked at start);
where a viser version lacks them they fall back to send times, which are exact only while the queue
keeps up, so that case keeps two replies to spare.
"""
from __future__ import annotations

import threading
import time
import warnings

_KEY = "tissue-lab-sync"
# a request raced with the client leaving: nothing is lost, the ping loop ends on the next check
warnings.filterwarnings("ignore", message="Queued a LocalStorageGetItemRequestMessage on a closed connection")


class ClientSync:
    """Background round trips to every client of a viser server; see the module docstring."""

    def __init__(self, server, interval_s: float = 0.2, timeout_s: float = 30.0):
        """server: viser.ViserServer. interval_s: pause between one reply and the next request, s.
        timeout_s: a request unanswered this long is sent again, s."""
        self.server = server
        self.interval_s = float(interval_s)
        self.timeout_s = float(timeout_s)
        self._lock = threading.Lock()
        buffer = getattr(getattr(server, "_websock_server", None), "_broadcast_buffer", None)
        exact = hasattr(buffer, "generator_cursors") and hasattr(buffer, "message_counter")
        self._buffer = buffer if exact else None
        self._spare = 1 if exact else 2  # replies to spare, see the module docstring
        self._sent: dict[int, list[float]] = {}  # client id -> positions of its last answered requests
        self._stop = threading.Event()
        self._threads: dict[int, threading.Thread] = {}
        self._watcher = threading.Thread(target=self._watch, name="client-sync", daemon=True)
        self._watcher.start()

    def mark(self) -> float:
        """The position after every message queued so far."""
        return float(self._buffer.message_counter) if self._buffer is not None else time.monotonic()

    def confirmed(self) -> float:
        """A position p: every connected client has applied, and had a frame to draw, all that was queued before p
        (compare with mark()). +inf with no clients; -inf while a client has not answered enough requests yet."""
        clients = set(self.server.get_clients())
        with self._lock:
            known = [self._sent.get(client_id, []) for client_id in clients]
        return min((sent[0] if len(sent) > self._spare else float("-inf") for sent in known), default=float("inf"))

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

    def _position(self, client_id: int) -> float:
        """How far this client's share of the broadcast queue has been handed to its socket: a request queued now
        goes out after all of it."""
        if self._buffer is None:
            return time.monotonic()
        return float(self._buffer.generator_cursors.get(client_id, -1) + 1)

    def _ping(self, client_id: int, client) -> None:
        """Round trips to one client until it leaves or the sync closes."""
        while not self._stop.is_set() and client_id in self.server.get_clients():
            sent = self._position(client_id)
            try:
                client.local_storage.get_item(_KEY, timeout=self.timeout_s)
            except TimeoutError:
                continue
            except RuntimeError:
                if client_id not in self.server.get_clients():
                    break  # it left
                # the browser refused localStorage: still a reply, after the earlier messages
            with self._lock:
                self._sent[client_id] = (self._sent.get(client_id, []) + [sent])[-(self._spare + 1):]
            self._stop.wait(self.interval_s)
        with self._lock:
            self._sent.pop(client_id, None)
