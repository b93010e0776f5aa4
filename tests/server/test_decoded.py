"""The decoded-keyframe cache between ingest and the stages (``server/decoded.py``): a keyframe
ingest handed on is not decoded again, its rasters are decoded once, the byte bound holds, and a
stage without an entry decodes the stored payload and is counted."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from factories import keyframe, walk

from wardmap.server.decoded import DecodedCache, decode_images, keyframe_key
from wardmap.shared import wire
from wardmap.shared.errors import ConfigError, WireError
from wardmap.shared.wire import KeyframeMsg


def _keyframes(n: int) -> list[KeyframeMsg]:
    return walk(keyframe(np.random.default_rng(0)), n)


def test_an_entry_is_handed_on_and_its_images_decoded_once() -> None:
    """A put keyframe comes back as the same object (no decode); its rasters are decoded by the
    first reader and the second gets the same arrays; after discard a reader decodes from the
    payload and that is counted."""
    msg = _keyframes(1)[0]
    payload = wire.encode(msg)
    key = keyframe_key(msg)
    cache = DecodedCache()
    cache.put(key, msg, len(payload))
    first = cache.decoded(key, b"not used: the entry is there")
    assert first.msg is msg
    images = cache.images(first)
    again = cache.images(cache.decoded(key, payload))
    assert again is images
    expected = decode_images(msg)
    np.testing.assert_array_equal(images.bgr, expected.bgr)
    np.testing.assert_array_equal(images.depth_m, expected.depth_m)
    assert images.depth_m.shape == (msg.depth.meta.height, msg.depth.meta.width)
    c = cache.counters()
    assert (c.put, c.hits, c.from_store, c.images_decoded, c.image_hits) == (1, 2, 0, 1, 1)
    assert c.entries == 1 and c.nbytes == len(payload) + images.nbytes
    cache.discard(key)
    assert cache.counters().nbytes == 0
    fallback = cache.decoded(key, payload)
    assert wire.encode(fallback.msg) == payload and cache.counters().from_store == 1


def test_the_byte_bound_evicts_the_oldest_first() -> None:
    """With room for about two payloads, putting five keeps the newest two; a read of an evicted
    key decodes its payload (counted); decoding an entry's rasters past the bound evicts others,
    never the bytes count's consistency."""
    msgs = _keyframes(5)
    payloads = [wire.encode(m) for m in msgs]
    size = max(len(p) for p in payloads)
    cache = DecodedCache(max_bytes=2 * size + 10)
    for m, p in zip(msgs, payloads, strict=True):
        cache.put(keyframe_key(m), m, len(p))
    c = cache.counters()
    assert (c.entries, c.evicted) == (2, 3) and c.nbytes <= 2 * size + 10
    assert wire.encode(cache.decoded(keyframe_key(msgs[0]), payloads[0]).msg) == payloads[0]
    assert cache.decoded(keyframe_key(msgs[4]), payloads[4]).msg is msgs[4]
    c = cache.counters()
    assert (c.hits, c.from_store) == (1, 1)
    cache.images(cache.decoded(keyframe_key(msgs[4]), payloads[4]))  # its rasters count too
    c = cache.counters()
    assert c.nbytes <= 2 * size + 10 and c.evicted >= 3
    for m in msgs:
        cache.discard(keyframe_key(m))
    assert (cache.counters().entries, cache.counters().nbytes) == (0, 0)  # the count stayed exact


def test_zero_bytes_keeps_nothing() -> None:
    """``max_bytes = 0`` (the behaviour before the cache): every read decodes the payload."""
    msg = _keyframes(1)[0]
    payload = wire.encode(msg)
    cache = DecodedCache(max_bytes=0)
    cache.put(keyframe_key(msg), msg, len(payload))
    entry = cache.decoded(keyframe_key(msg), payload)
    assert wire.encode(entry.msg) == payload and entry.msg is not msg
    c = cache.counters()
    assert (c.entries, c.nbytes, c.evicted, c.from_store, c.hits) == (0, 0, 1, 1, 0)


def test_an_inactive_cache_keeps_nothing_and_going_inactive_empties_it() -> None:
    """A standby server runs no stage: while inactive ``put`` keeps nothing (nor counts it), and
    switching off drops what was kept; switched on, it keeps again."""
    msgs = _keyframes(2)
    payloads = [wire.encode(m) for m in msgs]
    cache = DecodedCache(active=False)
    cache.put(keyframe_key(msgs[0]), msgs[0], len(payloads[0]))
    assert (cache.counters().put, cache.counters().entries) == (0, 0)
    assert cache.decoded(keyframe_key(msgs[0]), payloads[0]).msg is not msgs[0]  # from the store
    cache.set_active(True)
    cache.put(keyframe_key(msgs[1]), msgs[1], len(payloads[1]))
    assert cache.decoded(keyframe_key(msgs[1]), payloads[1]).msg is msgs[1]
    cache.set_active(False)
    c = cache.counters()
    assert (c.put, c.entries, c.nbytes) == (1, 0, 0)


def test_bad_rasters_raise_every_time_and_a_bad_payload_raises() -> None:
    """A JPEG that passes the wire's header check but does not decode: WireError on rgb_jpeg
    for every reader (decoded once); a payload that does not decode: WireError."""
    msg = _keyframes(1)[0]
    bad = replace(msg, rgb_jpeg=msg.rgb_jpeg[:400])  # as tests/server/backend/test_core.py
    cache = DecodedCache()
    cache.put(keyframe_key(bad), bad, 100)
    entry = cache.decoded(keyframe_key(bad), b"")
    for _ in range(2):
        with pytest.raises(WireError) as err:
            cache.images(entry)
        assert err.value.field == "rgb_jpeg"
    assert cache.counters().images_decoded == 1
    with pytest.raises(WireError):
        cache.decoded("r1/s1/99", b"\x00garbage")


@pytest.mark.parametrize("bad", [-1, 1.5, True, "1"])
def test_a_bad_bound_is_refused(bad: object) -> None:
    with pytest.raises(ConfigError, match="max_bytes"):
        DecodedCache(max_bytes=bad)  # type: ignore[arg-type]
