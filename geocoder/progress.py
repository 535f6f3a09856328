"""Progress of long jobs: named phases counted in tiles, shown on a terminal or logged.

The pipeline reports through whatever :class:`Progress` is current (see :func:`reporting`);
the default reports nothing. The CLI installs a :class:`TextProgress` on standard error.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import IO, Iterator


class Progress:
    """Receiver of progress events; this base class ignores them."""

    def phase(self, name: str, total: int, *, skipped: int = 0) -> None:
        """A phase of ``total`` units starts; ``skipped`` of them were finished by an earlier run."""

    def advance(self, n: int = 1) -> None:
        """``n`` more units of the current phase are finished."""

    def message(self, text: str) -> None:
        """A one-line note (for example the dashboard link)."""

    def close(self) -> None:
        """The current phase ends."""


class TextProgress(Progress):
    """A progress bar per phase: redrawn in place on a terminal, one line per phase otherwise."""

    def __init__(self, stream: IO[str] | None = None, width: int = 30) -> None:
        self.stream = stream or sys.stderr
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.name: str | None = None
        self.total = self.done = self.skipped = 0
        self.start = 0.0
        self.last_draw = 0.0

    def phase(self, name: str, total: int, *, skipped: int = 0) -> None:
        self.close()
        self.name, self.total, self.skipped, self.done = name, total, skipped, skipped
        self.start = time.perf_counter()
        self._draw(force=True)

    def advance(self, n: int = 1) -> None:
        self.done += n
        self._draw()

    def message(self, text: str) -> None:
        self.close()
        print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self.name is None:
            return
        self._draw(force=True, final=True)
        self.name = None

    def _line(self) -> str:
        total = max(self.total, 1)
        filled = int(self.width * min(self.done, total) / total)
        bar = "#" * filled + "." * (self.width - filled)
        extra = f", {self.skipped} done earlier" if self.skipped else ""
        return f"{self.name:<28} [{bar}] {self.done}/{self.total} tiles{extra} {time.perf_counter() - self.start:6.1f} s"

    def _draw(self, *, force: bool = False, final: bool = False) -> None:
        now = time.perf_counter()
        if self.tty:
            if force or now - self.last_draw > 0.2:
                end = "\n" if final else ""
                print("\r" + self._line(), end=end, file=self.stream, flush=True)
                self.last_draw = now
        elif final:
            print(self._line(), file=self.stream, flush=True)


_current: ContextVar[Progress] = ContextVar("geocoder_progress", default=Progress())


def current() -> Progress:
    """The progress receiver of the running job."""
    return _current.get()


@contextmanager
def reporting(progress: Progress | bool | None) -> Iterator[Progress]:
    """Make ``progress`` current inside the block (True: a :class:`TextProgress` on stderr)."""
    if progress is None:
        yield current()
        return
    p = TextProgress() if progress is True else (progress or Progress())
    token = _current.set(p)
    try:
        yield p
    finally:
        p.close()
        _current.reset(token)
