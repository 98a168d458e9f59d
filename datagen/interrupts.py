"""A stop request that a swallowed KeyboardInterrupt cannot lose.

A signal handler that raises KeyboardInterrupt can fire inside a ``__del__`` or a weakref
callback, where Python prints "Exception ignored" and carries on: the interrupt is gone and
a long start-up (dataset generation) runs to its end. :func:`request` is such a handler that
also records the request; long loops call :func:`check` between units of work (frames,
trajectories), which raises again while a request is pending.
"""

from __future__ import annotations

import signal
import sys

__all__ = ["request", "check", "clear", "pending", "install"]

_pending = False


def request(signum=None, frame=None) -> None:
    """Signal handler: record the stop request and raise KeyboardInterrupt."""
    global _pending
    _pending = True
    raise KeyboardInterrupt


def install(signals) -> None:
    """:func:`request` as the handler of ``signals``; a KeyboardInterrupt it raises inside a
    finalizer is then not printed as "Exception ignored" (the request is recorded and acted on
    at the next :func:`check`); other unraisable exceptions reach the previous hook."""
    for sig in signals:
        signal.signal(sig, request)
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if not (_pending and isinstance(unraisable.exc_value, KeyboardInterrupt)):
            previous(unraisable)

    sys.unraisablehook = hook


def check() -> None:
    """Raise KeyboardInterrupt if a stop was requested (and not cleared) since the start."""
    if _pending:
        raise KeyboardInterrupt


def pending() -> bool:
    return _pending


def clear() -> None:
    """Forget a request (a caller that has handled it and goes on)."""
    global _pending
    _pending = False
