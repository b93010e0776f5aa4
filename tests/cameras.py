"""What every live camera source must survive (tests/edge/test_realsense.py, test_orbbec.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from wardmap.edge.live import ReconnectingSource, SourceLostError
from wardmap.edge.stream import FrameStream, StreamSource

T0 = 1.7e9
"""Stamps of the first connection start at ``T0 + 10`` s, of the second at ``T0 + 20`` s."""


def check_unplug_and_replug(plug_in: Callable[[threading.Event, float], StreamSource]) -> None:
    """``plug_in(stop, start)`` connects a camera that streams 30 Hz for about a second from
    ``start`` (``T0 + 10`` s, then ``T0 + 20`` s) and is then unplugged; the first try after the
    unplug finds no camera. Read at 20 Hz through a one-frame stream: the source reconnects once,
    frames come from before and after, the slow reader's drops are counted and the stamps only
    grow."""
    tries = [0]

    def connect(stop: threading.Event) -> StreamSource:
        tries[0] += 1
        if tries[0] == 2:
            raise SourceLostError("no camera is connected")
        return plug_in(stop, T0 + 10.0 * (1 if tries[0] == 1 else 2))

    source = ReconnectingSource(connect, backoff_first_s=0.05)
    taken: list[float] = []
    with FrameStream(source, capacity=1) as stream:
        for item in stream:
            taken.append(item.stamp)
            time.sleep(0.05)  # tracking at 20 Hz behind a 30 Hz camera
            if source.reconnects == 1 and item.stamp > T0 + 20.5:
                stream.close()
    assert source.reconnects == 1
    assert any(s < T0 + 11 for s in taken) and any(s > T0 + 20 for s in taken)  # before and after
    assert stream.dropped > 0  # the tracker was behind: the oldest frames were dropped, counted
    assert np.all(np.diff(taken) > 0)
