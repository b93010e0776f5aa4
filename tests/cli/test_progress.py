"""``cli/progress.py``: plain lines with rate and ETA off a terminal, rich bars on one."""

from __future__ import annotations

import io

from wardmap.cli.progress import Progress


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_plain_lines_every_few_seconds_with_rate_and_eta() -> None:
    """Off a terminal: no line at the start, then one per task every 5 s with the count, the
    rate since the task began and the time left, and always the last one with the duration;
    two tasks are timed apart."""
    out, clock = io.StringIO(), Clock()
    with Progress("frames", stream=out, terminal=False, clock=clock) as p:
        p.update("robot_0", 0, 100)
        clock.t += 1.0
        p.update("robot_0", 10, 100)  # 1 s in: quiet
        clock.t += 4.0
        p.update("robot_0", 50, 100)  # 5 s in: 10 frames/s, 5 s to go
        p.update("robot_1", 0, 10)
        clock.t += 1.0
        p.update("robot_0", 55, 100)  # quiet again
        clock.t += 1.0
        p.update("robot_1", 10, 10, "done")
    assert out.getvalue().splitlines() == [
        "robot_0: 50/100 frames (10.0/s, ETA 5 s)",
        "robot_1: 10/10 frames (5.0/s) in 2.0 s done",
    ]


def test_bars_on_a_terminal() -> None:
    """On a terminal each task is a bar with its count and rate."""
    out, clock = io.StringIO(), Clock()
    with Progress("keyframes", stream=out, terminal=True, clock=clock) as p:
        p.update("ward_a", 0, 40)
        clock.t += 2.0
        p.update("ward_a", 40, 40)
    text = out.getvalue()
    assert "ward_a" in text and "40/40" in text and "20.0 keyframes/s" in text
