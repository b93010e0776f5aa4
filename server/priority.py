"""CPU priority of the server's background work: mapping yields the cores to ingest.

Robots wait for ingest's acks; the mapping stage (back-end, perception, association) can fall
behind and catch up. On Linux niceness is per thread, so the mapping stage's threads are made
nicer than the ingest thread of the same process (``[mapping] nice``; perception worker
processes get the same value for the whole process). Measured: BENCHMARKS.md, "32 robots with
the mapping stage on".
"""

from __future__ import annotations

import logging
import os
import sys
import threading

__all__ = ["nice_this_thread"]

log = logging.getLogger(__name__)


def nice_this_thread(increment: int) -> None:
    """Add ``increment`` (0-19) to the calling thread's niceness; threads it starts later inherit
    it. Linux only (elsewhere ``setpriority`` applies to the whole process, so nothing is done);
    a refusal is logged, never raised."""
    if increment <= 0 or not hasattr(os, "setpriority") or sys.platform != "linux":
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + increment))
    except OSError as exc:
        log.warning("cannot lower the priority of thread %s: %s", threading.current_thread().name, exc)
