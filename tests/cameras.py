"""What every live camera source must survive (tests/edge/test_realsense.py, test_orbbec.py)."""

from __future__ import annotations

import time

import numpy as np

from wardmap.edge.live import Connector, ReconnectingSource
from wardmap.edge.stream import FrameStream

T0 = 1.7e9
"""Stamps of the first connection start at ``T0 + 10`` s, of the second at ``T0 + 20`` s."""


def check_unplug_and_replug(connect: Connector) -> None:
    """``connect`` gives a camera streaming 30 Hz for about a second from ``T0 + 10 * n`` s (n: its
    connection), then unplugged; its second try fails (no camera). Read at 20 Hz through a
    one-frame stream: the source reconnects once, frames come from before and after, the slow
    reader's drops are counted and the stamps only grow."""
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
