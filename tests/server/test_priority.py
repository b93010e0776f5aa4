"""Ingest first: the mapping stage's threads run nicer than ingest (``shared/priority.py``,
``[mapping] nice``), and the back-end loads its numba kernel before the first keyframe."""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import pytest

from wardmap.server.backend.stage import BackendStage
from wardmap.server.mapping import MapPipeline, PipelineConfig
from wardmap.server.mapping.workers import MappingConfig
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import SqliteMapStore
from wardmap.shared.priority import nice_this_thread

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="per-thread niceness is Linux's")

MODEL = Path(__file__).resolve().parents[2] / "server" / "models" / "hospital_seg.onnx"


def _nice(tid: int = 0) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def test_a_thread_made_nicer_leaves_its_process_alone_and_passes_it_on() -> None:
    """``nice_this_thread(5)`` on a thread: that thread is 5 steps nicer, the calling test thread
    is not, and a thread it starts afterwards inherits it; 0 changes nothing."""
    base = _nice(threading.get_native_id())
    seen: dict[str, int] = {}

    def child() -> None:
        seen["child"] = _nice(threading.get_native_id())

    def worker() -> None:
        nice_this_thread(0)
        seen["after 0"] = _nice(threading.get_native_id())
        nice_this_thread(5)
        seen["worker"] = _nice(threading.get_native_id())
        t = threading.Thread(target=child)
        t.start()
        t.join()

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    want = min(19, base + 5)
    assert seen == {"after 0": base, "worker": want, "child": want}
    assert _nice(threading.get_native_id()) == base


@pytest.mark.skipif(not MODEL.is_file(), reason="the packaged segmentation network is not built")
def test_the_mapping_stage_and_the_back_end_run_nicer_than_their_caller(tmp_path: Path) -> None:
    """A mapping stage with ``[mapping] nice = 6`` and its back-end: both threads 6 steps nicer
    than the thread that started them (ingest's peers), which keeps its own niceness."""
    base = _nice(threading.get_native_id())
    want = min(19, base + 6)
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        backend = BackendStage(store, nice=6)
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(poll_s=0.05), backend=backend,
                           shared=MappingConfig(nice=6))
        pipe.start()
        try:
            threads = [pipe._thread, backend._thread]  # white box: the two stage threads
            assert all(t is not None and t.native_id is not None for t in threads)
            tids = [t.native_id for t in threads if t is not None and t.native_id is not None]
            deadline = time.monotonic() + 10.0
            while [_nice(tid) for tid in tids] != [want, want] and time.monotonic() < deadline:
                time.sleep(0.02)
            assert [_nice(tid) for tid in tids] == [want, want]
            assert _nice(threading.get_native_id()) == base
        finally:
            pipe.stop()


def test_the_back_end_loads_its_kernels_before_the_first_keyframe() -> None:
    """``warm_up_kernels`` (run by ``BackendStage.start``) leaves place recognition's numba
    kernel loaded, so the first keyframe does not hold the interpreter lock for it (a fresh
    interpreter: nothing else loaded it before)."""
    import subprocess

    code = ("from wardmap.shared import hamming\n"
            "from wardmap.server.backend.stage import warm_up_kernels\n"
            "assert not hamming._knn2.signatures\n"
            "warm_up_kernels()\n"
            "assert hamming._knn2.signatures, 'not loaded'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
