"""Ctrl-C in the CLI that is never lost and never a traceback.

Python turns SIGINT into a KeyboardInterrupt wherever the main thread happens to be, and libraries swallow it:
trimesh's optional imports catch BaseException, Taichi has bare `except:` clauses at import time (before this
module: 5 of 13 Ctrl-C sent 0.1-2.4 s into a run were lost, the run finishing as if none came). So the handler
also remembers the interrupt, and check() raises it again at the CLI's checkpoints. Until arm() (while the CLI's
own module is imported) it only remembers, so an early Ctrl-C surfaces at arm() instead of as an import traceback.
"""
import signal

_pending = False  # a SIGINT arrived and has not been reported
_armed = False    # the handler raises KeyboardInterrupt (else it only remembers)


def _on_sigint(signum, frame) -> None:
    global _pending
    _pending = True
    if _armed:
        raise KeyboardInterrupt


def install() -> None:
    """Take over SIGINT for this process (the CLI only: a test process keeps its own handler)."""
    signal.signal(signal.SIGINT, _on_sigint)


def arm(armed: bool = True) -> None:
    """From now on a SIGINT raises KeyboardInterrupt (armed) or is only remembered (not); raise one remembered."""
    global _armed
    _armed = armed
    if armed:
        check()


def check() -> None:
    """Raise KeyboardInterrupt if a SIGINT arrived, even one that some library caught and dropped."""
    if _pending:
        raise KeyboardInterrupt
