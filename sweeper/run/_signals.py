"""Ctrl-C and SIGTERM during a launch: both raise ``Interrupted`` (a KeyboardInterrupt) and
are remembered, because Python drops an exception raised while it runs a finalizer or a
weakref callback (it prints "Exception ignored in ..." and goes on): the driver loop asks
``raise_if_stopped`` once a poll, so a signal that landed there still stops the launch.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any

_asked: list[int] = []  # the signals received inside the outermost ``stop_on_signals``
_depth = 0


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM."""


def _interrupt(signum: int, frame: Any) -> None:
    _asked.append(signum)
    raise Interrupted()


def raise_if_stopped() -> None:
    """Raise ``Interrupted`` if a signal arrived whose exception was dropped."""
    if _asked:
        raise Interrupted()


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Inside the block SIGINT (unless ignored) and SIGTERM raise ``Interrupted`` and are
    remembered; the handlers before it come back after, and the outermost block forgets
    the signals. Outside the main thread, which alone receives signals, it changes nothing."""
    global _depth
    # a process started with SIGINT ignored (``nohup cmd &`` from a script) keeps ignoring it
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    caught = [signal.SIGTERM] if ignored else [signal.SIGINT, signal.SIGTERM]
    try:
        previous = {sig: signal.signal(sig, _interrupt) for sig in caught}
    except ValueError:  # not the main thread
        yield
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if not _depth:
            _asked.clear()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
