"""Keyframe groups (paper 000 Fig. 3): M keyframes per group, j shared by neighbours."""

from __future__ import annotations

import itertools

import pytest

from wardmap.server.association.groups import KeyframeGrouper, group_ranges
from wardmap.shared.errors import ConfigError


def test_groups_of_m_with_j_overlap() -> None:
    """11 keyframes, M = 4, j = 1: groups start every 3 keyframes and share one keyframe."""
    groups = group_ranges(11, 4, 1)
    assert [list(g) for g in groups] == [[0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9], [9, 10]]
    for a, b in itertools.pairwise(groups):
        assert len(set(a) & set(b)) == 1


def test_every_keyframe_is_covered_and_no_group_repeats() -> None:
    """For many (n, M, j): every keyframe lies in a group; full groups have M keyframes."""
    for n in range(1, 25):
        for M in range(1, 7):
            for j in range(M):
                groups = group_ranges(n, M, j)
                covered = set().union(*map(set, groups))
                assert covered == set(range(n))
                assert all(len(g) == M for g in groups[:-1])
                assert all(len(set(a) & set(b)) == j for a, b in itertools.pairwise(groups))


def test_incremental_grouper_emits_each_group_when_complete() -> None:
    """A group is emitted at the push of its last keyframe; flush emits the rest and restarts."""
    g = KeyframeGrouper(3, 1)
    out = [g.push(k) for k in range(6)]
    assert out == [[], [], [range(0, 3)], [], [range(2, 5)], []]
    assert g.flush() == [range(4, 6)]
    assert g.flush() == []
    assert g.push(6) == [] and g.push(7) == [] and g.push(8) == [range(6, 9)]
    assert g.flush() == []


def test_grouper_refuses_skipped_keyframes() -> None:
    g = KeyframeGrouper(3, 1)
    g.push(0)
    with pytest.raises(ValueError, match="expected keyframe 1"):
        g.push(2)


@pytest.mark.parametrize(("M", "j"), [(0, 0), (3, 3), (3, -1)])
def test_bad_group_parameters(M: int, j: int) -> None:
    with pytest.raises(ConfigError):
        KeyframeGrouper(M, j)
