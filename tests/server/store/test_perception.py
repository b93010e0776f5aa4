"""Protocol tests of perception shared out between servers (:class:`~wardmap.server.store.PerceptionStore`),
run against every backend (``conftest.BACKENDS``): claims over the keyframes after the mapping
cursor, claim expiry, results stored once, the mapping stage's commit clearing the row."""

from __future__ import annotations

import threading

import numpy as np

from wardmap.server.store import MappedPose, MapStore, Perceived
from wardmap.shared.se3 import yaw_transform

from .conftest import Backend, keyframe
from .test_mapping import CAMERA, _measurement

CURSOR = "mapping"
CLAIM_S = 60.0


def _insert(store: MapStore, n: int) -> None:
    for seq in range(n):
        store.insert(*keyframe("r1", "s1", seq), 1.0)


def _result(seq: int, n_measurements: int = 2, failure: str | None = None) -> Perceived:
    key = f"r1/s1/{seq}"
    if failure is not None:
        return Perceived(MappedPose("r1", "s1", seq, None, None), False, [], failure)
    return Perceived(MappedPose("r1", "s1", seq, yaw_transform(seq, 1.0, 0.2, 0.5), CAMERA), True,
                     [_measurement(key, i) for i in range(n_measurements)])


def test_claims_go_in_insertion_order_and_never_twice(store: MapStore) -> None:
    """Three keyframes, four claims by two workers: each keyframe is claimed once, oldest first,
    with its payload and attempt 1; the fourth claim finds nothing."""
    _insert(store, 3)
    a = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    b = store.claim_keyframe("b", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    c = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert a is not None and b is not None and c is not None
    assert [a.seq, b.seq, c.seq] == [0, 1, 2]
    assert [a.attempts, b.attempts, c.attempts] == [1, 1, 1]
    assert a.payload == store.payload("r1", "s1", 0)
    assert store.claim_keyframe("b", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S) is None
    # A named keyframe that is claimed already is not given to a second claimer either.
    assert store.claim_keyframe("w", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S, rowid=a.rowid) is None


def test_concurrent_claimers_never_share_a_keyframe(backend: Backend) -> None:
    """Four threads, each on its own store handle (its own connections), claim from 40
    keyframes until none is left: every keyframe is claimed exactly once."""
    with backend.open() as store:
        _insert(store, 40)
    got: dict[str, list[int]] = {}
    errors: list[BaseException] = []

    def claim_all(name: str) -> None:
        try:
            with backend.open() as s:
                mine = got.setdefault(name, [])
                while (kf := s.claim_keyframe(name, cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)) is not None:
                    mine.append(kf.rowid)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=claim_all, args=(f"w{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    claimed = sorted(r for rows in got.values() for r in rows)
    assert len(claimed) == 40 and len(set(claimed)) == 40


def test_an_expired_claim_is_claimed_again_and_a_result_is_stored_once(store: MapStore) -> None:
    """Worker a claims a keyframe and goes silent: once its claim expired, worker b claims it
    (attempt 2) and stores its result; a's late result is refused, and b's stays."""
    _insert(store, 1)
    a = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=10.0)
    assert a is not None
    assert store.claim_keyframe("b", cursor=CURSOR, now_s=109.0, claim_s=10.0) is None  # still a's
    b = store.claim_keyframe("b", cursor=CURSOR, now_s=110.5, claim_s=10.0)
    assert b is not None and b.rowid == a.rowid and b.attempts == 2
    assert store.store_perceived("b", _result(0, n_measurements=2))
    assert not store.store_perceived("a", _result(0, n_measurements=5))
    # A stored result is never claimed again, however late.
    assert store.claim_keyframe("c", cursor=CURSOR, now_s=1e9, claim_s=10.0) is None
    [slot] = store.perception_slots(0, a.rowid, 10)
    assert slot.result is not None and len(slot.result.measurements) == 2
    assert slot.claim_expires_s is None


def test_a_released_claim_is_claimed_again_at_once(store: MapStore) -> None:
    """A worker that failed unexpectedly releases its claim; the next claim is attempt 2."""
    _insert(store, 1)
    a = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert a is not None
    store.release_claim("b", a.rowid)  # not b's: nothing happens
    assert store.claim_keyframe("b", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S) is None
    store.release_claim("a", a.rowid)
    again = store.claim_keyframe("b", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert again is not None and again.rowid == a.rowid and again.attempts == 2


def test_slots_show_results_claims_and_gaps_in_order(store: MapStore) -> None:
    """perception_slots: a keyframe with a result (measurements, pose, camera round-trip), one
    claimed (its expiry), one failed (its reason, no pose), one untouched (nothing)."""
    _insert(store, 4)
    for _ in range(3):
        store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert store.store_perceived("a", _result(0, n_measurements=3))
    assert store.store_perceived("a", _result(2, failure="WireError: bad jpeg"))
    assert store.count_unperceived(CURSOR) == 2
    slots = store.perception_slots(0, 10, 10)
    assert [s.seq for s in slots] == [0, 1, 2, 3]
    done, claimed, failed, free = slots
    assert done.result is not None and done.result.anchored and done.result.failure is None
    assert [m.keyframe for m in done.result.measurements] == ["r1/s1/0"] * 3
    expected = _result(0, n_measurements=3)
    assert done.result.pose.T_map_camera is not None and expected.pose.T_map_camera is not None
    np.testing.assert_array_equal(done.result.pose.T_map_camera, expected.pose.T_map_camera)
    assert done.result.pose.camera == CAMERA
    np.testing.assert_array_equal(done.result.measurements[1].T_world_object,
                                  expected.measurements[1].T_world_object)
    assert claimed.result is None and claimed.claim_expires_s == 100.0 + CLAIM_S
    assert failed.result is not None and failed.result.failure == "WireError: bad jpeg"
    assert failed.result.pose.T_map_camera is None and not failed.result.measurements
    assert free.result is None and free.claim_expires_s is None


def test_committed_keyframes_leave_the_claims(store: MapStore) -> None:
    """When the mapping stage commits a keyframe its perception row goes, and keyframes at or
    before the mapping cursor are never claimed (even with no row)."""
    _insert(store, 3)
    first = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert first is not None
    assert store.store_perceived("a", _result(0))
    store.commit_keyframe(CURSOR, first.rowid, _result(0).pose, [], anchored=True)
    store.commit_keyframe(CURSOR, first.rowid + 1, MappedPose("r1", "s1", 1, None, None), [], anchored=False)
    assert store.perception_slots(0, first.rowid, 10)[0].result is None  # the row is gone
    assert not store.store_perceived("a", _result(0))
    nxt = store.claim_keyframe("a", cursor=CURSOR, now_s=100.0, claim_s=CLAIM_S)
    assert nxt is not None and nxt.seq == 2
    assert store.count_unperceived(CURSOR) == 1
