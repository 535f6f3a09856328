"""Ctrl-C that Python dropped, delivered again where the job can stop.

Python raises a Ctrl-C as ``KeyboardInterrupt`` in whatever the main thread runs at that
moment. Inside a garbage collector callback or a finalizer (``__del__``, a weakref callback)
the exception cannot propagate: Python prints "Exception ignored in ..." and carries on, and a
command whose user pressed Ctrl-C ran to its end (seen with distributed's GC diagnostics
callback). While :func:`keep_dropped_interrupts` is active such a dropped interrupt is
remembered instead of printed, and :func:`raise_dropped_interrupt` raises it again at the
job's next checkpoint (every finished task of :func:`geocoder.runtime.compute_as_completed`).
"""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager
from typing import Iterator

_dropped = threading.Event()


@contextmanager
def keep_dropped_interrupts() -> Iterator[None]:
    """Inside the block, a ``KeyboardInterrupt`` that Python could not raise is kept for
    :func:`raise_dropped_interrupt` (and not printed); other unraisable errors are reported as
    before."""
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _dropped.set()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous
        _dropped.clear()


def raise_dropped_interrupt() -> None:
    """Raise ``KeyboardInterrupt`` if one was dropped since the last call (see the module)."""
    if _dropped.is_set():
        _dropped.clear()
        raise KeyboardInterrupt
