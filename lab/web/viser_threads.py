"""Make viser 1.1.1's message sends safe from threads other than its event loop's.

`AsyncMessageBuffer.push` (viser/infra/_async_message_buffer.py) calls `message_event.set()` on an asyncio.Event
directly from whichever thread sends, then again through `call_soon_threadsafe`. asyncio.Event is not thread-safe: the
direct call from the simulation thread races with the loop's waiters and was seen to raise "RuntimeError: deque
mutated during iteration" in the lab (once in a 30 minute soak, once while a page was frozen), out of an add_glb or a
gizmo move. Here every buffer's event becomes one whose set() from another thread is handed to the loop; viser's own
threadsafe call right after it does the same, and nothing reads the event synchronously (viser 1.1.1 only waits and
clears it in the loop), so nothing else changes.
"""
from __future__ import annotations

import asyncio


class LoopSafeEvent(asyncio.Event):
    """An asyncio.Event whose set() may be called from any thread: off its loop it is scheduled on the loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        super().__init__()
        self.home_loop = loop

    def set(self) -> None:
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is self.home_loop:
            super().set()
            return
        try:
            self.home_loop.call_soon_threadsafe(super().set)
        except RuntimeError:  # the loop is closed: nobody waits any more
            pass


def make_sends_thread_safe() -> None:
    """Give every viser message buffer made from now on a LoopSafeEvent (idempotent). Call before creating a
    ViserServer. Raises RuntimeError when this viser has no AsyncMessageBuffer with message_event and event_loop."""
    from viser.infra import _async_message_buffer as module

    cls = getattr(module, "AsyncMessageBuffer", None)
    fields = getattr(cls, "__dataclass_fields__", {})
    if cls is None or "message_event" not in fields or "event_loop" not in fields:
        raise RuntimeError("lab.web.viser_threads: viser has no AsyncMessageBuffer(message_event, event_loop); check the fix still applies")
    if getattr(cls, "_lab_loop_safe", False):
        return
    original = cls.__init__

    def __init__(self, *args, **kwargs):
        original(self, *args, **kwargs)
        self.message_event = LoopSafeEvent(self.event_loop)

    cls.__init__ = __init__
    cls._lab_loop_safe = True
