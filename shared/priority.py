"""CPU priority of background work: it yields the cores to what someone waits for.

On Linux niceness is per thread, and threads and processes a thread starts inherit its value.
The server's mapping stage (back-end, perception, association) runs nicer than ingest, whose
acks robots wait for (``[mapping] nice``; measured: BENCHMARKS.md, "32 robots with the mapping
stage on"); the edge's online readout estimate runs its child nicer than the tracker.
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
