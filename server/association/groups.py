"""Keyframe groups, paper 000 Sec. III-A and Fig. 3.

Keyframes ``F_1..F_D`` are cut into groups of ``M`` adjacent keyframes; two neighbouring
groups share ``j`` keyframes, so group ``n`` (0-based) holds keyframes
``n * (M - j) .. n * (M - j) + M - 1`` (0-based keyframe indices).
"""

from __future__ import annotations

from wardmap.shared.errors import ConfigError

__all__ = ["KeyframeGrouper", "group_ranges"]


def _check(size: int, overlap: int) -> None:
    if size < 1:
        raise ConfigError(f"group size M must be >= 1, got {size}")
    if not 0 <= overlap < size:
        raise ConfigError(f"group overlap j must satisfy 0 <= j < M = {size}, got {overlap}")


def group_ranges(n_keyframes: int, size: int, overlap: int) -> list[range]:
    """All groups of ``n_keyframes`` keyframes, the last one possibly shorter.

    Every keyframe lies in at least one group; the last group starts on the regular
    stride and holds the remaining keyframes (it exists only if it adds a keyframe not
    in the previous group).

    Raises:
        ConfigError: ``size < 1`` or not ``0 <= overlap < size``.
    """
    grouper = KeyframeGrouper(size, overlap)
    out: list[range] = []
    for k in range(n_keyframes):
        out.extend(grouper.push(k))
    out.extend(grouper.flush())
    return out


class KeyframeGrouper:
    """Incremental grouping: feed keyframe indices 0, 1, 2, ... and get each group once.

    A group is emitted as soon as its last keyframe arrives; :meth:`flush` emits the
    incomplete group at the end of a run (or of a robot session) and restarts numbering
    at the next pushed index.
    """

    def __init__(self, size: int, overlap: int) -> None:
        _check(size, overlap)
        self.size = size
        self.overlap = overlap
        self._first = 0  # index of the first keyframe of the current run
        self._next_group = 0  # group number (within the run) that completes next
        self._last: int | None = None  # last pushed keyframe index
        self._covered = -1  # last keyframe index inside an emitted group

    @property
    def stride(self) -> int:
        """Keyframes between the starts of two neighbouring groups (M - j)."""
        return self.size - self.overlap

    def push(self, index: int) -> list[range]:
        """Add keyframe ``index`` (must be the previous index + 1); returns completed groups."""
        expected = self._first if self._last is None else self._last + 1
        if index != expected:
            raise ValueError(f"KeyframeGrouper.push: expected keyframe {expected}, got {index}")
        self._last = index
        start = self._first + self._next_group * self.stride
        if index == start + self.size - 1:
            self._next_group += 1
            self._covered = index
            return [range(start, index + 1)]
        return []

    def flush(self) -> list[range]:
        """The incomplete last group (if it holds an uncovered keyframe); the next run starts fresh."""
        out: list[range] = []
        if self._last is not None and self._last > self._covered:
            start = self._first + self._next_group * self.stride
            out.append(range(start, self._last + 1))
        if self._last is not None:
            self._first = self._last + 1
        self._next_group = 0
        self._covered = self._first - 1
        self._last = None
        return out
