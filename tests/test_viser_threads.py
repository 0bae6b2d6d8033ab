"""lab.web.viser_threads: a message buffer's event set from another thread wakes the loop's waiter through the loop."""
import asyncio
import threading

from lab.web.viser_threads import LoopSafeEvent, make_sends_thread_safe


def test_an_event_set_from_another_thread_is_set_on_its_loop_and_wakes_the_waiter():
    loop = asyncio.new_event_loop()
    runner = threading.Thread(target=loop.run_forever, daemon=True)
    runner.start()
    try:
        event = asyncio.run_coroutine_threadsafe(_make(loop), loop).result(timeout=10)
        woke = asyncio.run_coroutine_threadsafe(event.wait(), loop)
        seen_on = []
        original = asyncio.Event.set

        def record(self):
            seen_on.append(threading.get_ident())
            original(self)

        asyncio.Event.set = record
        try:
            event.set()  # from this (non-loop) thread
            assert woke.result(timeout=10) is True
        finally:
            asyncio.Event.set = original
        assert seen_on and set(seen_on) == {runner.ident}, "the event was set off its loop's thread"
    finally:
        loop.call_soon_threadsafe(loop.stop)
        runner.join(timeout=10)
        loop.close()


async def _make(loop):
    return LoopSafeEvent(loop)


def test_viser_buffers_made_after_the_fix_carry_a_loop_safe_event():
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    make_sends_thread_safe()
    make_sends_thread_safe()  # idempotent
    loop = asyncio.new_event_loop()
    try:
        assert isinstance(AsyncMessageBuffer(loop, persistent_messages=False).message_event, LoopSafeEvent)
    finally:
        loop.close()
