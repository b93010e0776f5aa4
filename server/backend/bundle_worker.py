"""The back-end's bundle adjustment in a child process, so the back-end thread goes on meanwhile.

One adjustment over a long loop takes one to three minutes on one core (decision 0036), and
gtsam holds the interpreter lock while it optimises: in the back-end's own thread no keyframe
would enter the graph meanwhile. :class:`BundleWorker` runs
:func:`~wardmap.server.backend.bundle.bundle_adjust` in a child process started with ``spawn``
(forking a process with running threads and a Zenoh session is unsafe), one adjustment at a
time; the back-end polls it between keyframes and adds the result as ``bundle`` edges when it
is there (ORB-SLAM2 runs its global bundle adjustment on a thread of its own after a loop,
likewise, and merges the result later).

The frames go to the child pickled (numpy arrays and dataclasses; about 60 KB per keyframe),
the result comes back through a pipe. :meth:`BundleWorker.close` terminates a running child.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

from wardmap.server.backend.bundle import BundleConfig, BundleFrame, BundleResult, bundle_adjust
from wardmap.shared.errors import GeometryError

log = logging.getLogger(__name__)


def _child(conn: Connection, frames: Sequence[BundleFrame], config: BundleConfig) -> None:
    """The child's work: one adjustment, its result (or its error, as text) sent back."""
    try:
        conn.send(("ok", bundle_adjust(frames, config)))
    except (GeometryError, RuntimeError) as exc:  # different cameras; gtsam's own failures
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


class BundleWorker:
    """At most one bundle adjustment at a time, in a child process (see the module docstring).

    Owned by the back-end thread: :meth:`submit`, :meth:`collect` and :meth:`close` are called
    from it only.
    """

    def __init__(self) -> None:
        self._ctx = multiprocessing.get_context("spawn")
        self._proc: BaseProcess | None = None
        self._conn: Connection | None = None
        self._frames = 0
        self._started = 0.0

    def busy(self) -> bool:
        """Whether an adjustment is running (its result not collected yet)."""
        return self._proc is not None

    def submit(self, frames: Sequence[BundleFrame], config: BundleConfig) -> None:
        """Start adjusting ``frames`` in a child process.

        Raises:
            RuntimeError: one is running already (check :meth:`busy`).
        """
        if self._proc is not None:
            raise RuntimeError("a bundle adjustment is running already")
        parent, child = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_child, args=(child, list(frames), config), name="wardmap-bundle",
                                 daemon=True)
        proc.start()
        child.close()  # the child holds its end; EOF here once it exits
        self._proc, self._conn = proc, parent
        self._frames, self._started = len(frames), time.monotonic()

    def collect(self, timeout_s: float = 0.0) -> BundleResult | None:
        """The finished adjustment's result, once (None: none running, not finished within
        ``timeout_s``, or it failed: logged). The child is reaped either way when done."""
        if self._proc is None or self._conn is None:
            return None
        if not self._conn.poll(timeout_s) and self._proc.is_alive():
            return None
        try:
            status, value = self._conn.recv()
        except (EOFError, OSError):
            status, value = "error", f"the child exited with code {self._proc.exitcode} and no result"
        self._reap()
        if status != "ok":
            log.warning("bundle adjustment over %d keyframes failed: %s", self._frames, value)
            return None
        assert isinstance(value, BundleResult)
        return value

    def close(self) -> None:
        """Terminate a running adjustment (its result is lost; the pairs stay unbundled and a
        later loop adjusts them)."""
        if self._proc is not None and self._proc.is_alive():
            log.info("bundle adjustment over %d keyframes stopped after %.0f s", self._frames,
                     time.monotonic() - self._started)
            self._proc.terminate()
        self._reap()

    def _reap(self) -> None:
        if self._proc is not None:
            self._proc.join(timeout=10.0)
        if self._conn is not None:
            self._conn.close()
        self._proc, self._conn = None, None


__all__ = ["BundleWorker"]
