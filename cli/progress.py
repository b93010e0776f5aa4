"""Progress of long commands on stderr: a bar with rate and ETA on a terminal, plain lines
otherwise (a log file, CI, a pipe).

Commands hand :meth:`Progress.update` to their library function as its ``progress``
callback (the library never prints). On a terminal each task (a robot, a data set, a stage)
gets a rich bar with count, rate and time left; elsewhere a line ``task: 120/500 frames
(24.0/s, ETA 16 s)`` at most every :data:`PLAIN_EVERY_S` seconds per task and when it ends.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from types import TracebackType
from typing import IO, Any, Final

__all__ = ["PLAIN_EVERY_S", "Progress"]

PLAIN_EVERY_S: Final = 5.0


class Progress:
    """Report progress of named tasks; use as a ``with`` block (it ends the bars)."""

    def __init__(
        self,
        unit: str,
        *,
        stream: IO[str] | None = None,
        terminal: bool | None = None,
        every_s: float = PLAIN_EVERY_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """
        Args:
            unit: what is counted, plural (``frames``, ``keyframes``, ``steps``).
            stream: where to write; stderr by default.
            terminal: draw bars (True) or print lines (False); None: bars when ``stream`` is
                a terminal.
            every_s: seconds between plain lines of one task.
            clock: seconds, monotonic (tests pass their own).
        """
        self._unit = unit
        self._stream = stream if stream is not None else sys.stderr
        self._terminal = self._stream.isatty() if terminal is None else terminal
        self._every_s = every_s
        self._clock = clock
        self._started: dict[str, float] = {}
        self._last_line: dict[str, float] = {}
        self._bars: Any = None
        self._bar_ids: dict[str, Any] = {}

    def __enter__(self) -> Progress:
        if self._terminal:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            from rich.progress import Progress as Bars

            self._bars = Bars(
                TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                TextColumn(f"{{task.fields[rate]}} {self._unit}/s"), TimeElapsedColumn(), TextColumn("ETA"),
                TimeRemainingColumn(), TextColumn("{task.fields[note]}"),
                console=Console(file=self._stream, force_terminal=True),
            )
            self._bars.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._bars is not None:
            self._bars.stop()
            self._bars = None

    def update(self, task: str, done: int, total: int, note: str = "") -> None:
        """``done`` of ``total`` units of ``task`` are finished (``note``: a short status)."""
        now = self._clock()
        started = self._started.setdefault(task, now)
        rate = done / (now - started) if now > started else 0.0
        if self._bars is not None:
            if task not in self._bar_ids:
                self._bar_ids[task] = self._bars.add_task(task, total=total, rate="-", note="")
            self._bars.update(self._bar_ids[task], completed=done, total=total, rate=f"{rate:.1f}", note=note)
            return
        if done < total and now - self._last_line.get(task, started) < self._every_s:
            return  # a line per task every `every_s` seconds, and the last one
        self._last_line[task] = now
        eta = f", ETA {(total - done) / rate:.0f} s" if 0 < done < total and rate > 0 else ""
        took = f" in {now - started:.1f} s" if done >= total else ""
        tail = f" {note}" if note else ""
        print(f"{task}: {done}/{total} {self._unit} ({rate:.1f}/s{eta}){took}{tail}", file=self._stream,
              flush=True)
