"""Keyframes decoded once per server process: ingest -> back-end -> mapping stage.

Ingest decodes each keyframe to validate it (``shared.wire.decode_keyframe``); the back-end
(fern codes) and the mapping stage (perception) need the same message and the same colour and
depth rasters. :class:`DecodedCache` hands them on: ingest :meth:`~DecodedCache.put`\\ s each
keyframe it newly stored, the back-end and the mapping stage take it with
:meth:`~DecodedCache.decoded` (the rasters with :meth:`~DecodedCache.images`, decoded by the
first stage that asks), and the mapping stage, the last reader, :meth:`~DecodedCache.discard`\\ s
it. Keys are ``"<robot_id>/<session_id>/<seq>"`` (the store's ``StoredKeyframe.key``).

Policy: **bounded in bytes, least recently used out first**. Entries count their payload's
size plus their decoded rasters; past ``max_bytes`` the oldest go (counted as ``evicted``).
A stage that finds no entry (after a restart, an eviction, a keyframe another server stored)
decodes the stored payload itself, and that is counted (``from_store``), so the figure says
how often a keyframe was decoded twice. ``max_bytes = 0`` keeps nothing: every stage decodes
from the store (the behaviour before this cache; ``bench/decode_once.py`` compares the two).

Not through this cache: the back-end's loop checks read the keypoints of *older* keyframes
(fern candidates and their neighbours) from the store, with a small cache of their features
of its own (``backend/stage.py``, ``FEATURE_CACHE``).

Thread safety: every method may be called from any thread; one lock guards the entries and
counters, and no decoding happens under it.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import ConfigError, WireError
from wardmap.shared.wire import KeyframeMsg, decode_depth, decode_keyframe

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_MAX_BYTES", "DecodedCache", "DecodedCounters", "DecodedKeyframe", "KeyframeImages",
           "decode_images", "keyframe_key"]

DEFAULT_MAX_BYTES: Final = 128 * 2**20
"""Bytes the cache holds (128 MiB: about 100 keyframes of 640x480 with their colour and depth
decoded, many times the mapping stage's usual lag behind ingest; kept well inside the server's
600 MiB bound under hostile input, docs/deploy.md)."""


def keyframe_key(msg: KeyframeMsg) -> str:
    """``"<robot_id>/<session_id>/<seq>"``: the key the store names ``msg`` by (``StoredKeyframe.key``)."""
    return f"{msg.robot_id}/{msg.session_id}/{msg.seq}"


@dataclass(frozen=True, slots=True)
class KeyframeImages:
    """A keyframe's decoded rasters.

    Attributes:
        bgr: (H, W, 3) uint8, the colour image (``rgb_jpeg`` decoded; OpenCV's channel order).
        depth_m: (h, w) float32 metres at the depth raster's own size (``depth.meta``; the colour
            size divided by the depth stride), 0 where unknown.

    Both arrays are read-only: the back-end and the mapping stage share them.
    """

    bgr: NDArray[np.uint8]
    depth_m: NDArray[np.float32]

    @property
    def nbytes(self) -> int:
        return int(self.bgr.nbytes + self.depth_m.nbytes)


def decode_images(msg: KeyframeMsg) -> KeyframeImages:
    """Decode ``msg``'s colour JPEG and depth raster (sizes are capped by the wire's checks).

    Raises:
        WireError: the colour image does not decode (``rgb_jpeg``) or the depth does not.
    """
    decoded = cv2.imdecode(np.frombuffer(msg.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    if decoded is None:
        raise WireError("rgb_jpeg", "the colour image does not decode")
    bgr: NDArray[np.uint8] = np.ascontiguousarray(decoded, np.uint8)
    depth = decode_depth(msg.depth.data, msg.depth.meta)
    depth_m: NDArray[np.float32] = np.ascontiguousarray(depth, np.float32)
    bgr.flags.writeable = depth_m.flags.writeable = False  # shared by the stages: nobody may change them
    return KeyframeImages(bgr, depth_m)


class DecodedKeyframe:
    """One keyframe's decoded message (``msg``) and, once a stage asked for them, its rasters.
    Read-only for its users; the cache sets the rasters once."""

    __slots__ = ("_images", "key", "msg", "payload_bytes")

    def __init__(self, key: str, msg: KeyframeMsg, payload_bytes: int) -> None:
        self.key = key
        self.msg = msg
        self.payload_bytes = payload_bytes
        self._images: KeyframeImages | WireError | None = None

    @property
    def nbytes(self) -> int:
        """Bytes this entry holds: its payload's size (the message's arrays and JPEG are about
        that) plus its rasters once decoded."""
        return self.payload_bytes + (self._images.nbytes if isinstance(self._images, KeyframeImages) else 0)


@dataclass(frozen=True, slots=True)
class DecodedCounters:
    """A snapshot of the cache (for ``/metrics`` and benchmarks).

    Attributes:
        put: keyframes ingest handed on.
        hits: messages a stage took from the cache.
        from_store: messages a stage had to decode from the stored payload (no entry).
        image_hits: rasters a stage took already decoded.
        images_decoded: rasters decoded (once per keyframe when the cache holds it).
        evicted: entries dropped for the byte bound before the mapping stage was done.
        entries: entries now; nbytes: their bytes now.
    """

    put: int
    hits: int
    from_store: int
    image_hits: int
    images_decoded: int
    evicted: int
    entries: int
    nbytes: int


class DecodedCache:
    """Decoded keyframes by key, bounded in bytes (see the module docstring).

    Args:
        max_bytes: most bytes held (>= 0; 0: nothing is kept, every stage decodes itself).
        active: whether :meth:`put` keeps anything (see :meth:`set_active`).
    """

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES, *, active: bool = True) -> None:
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 0:
            raise ConfigError(f"decoded cache max_bytes must be an int >= 0, got {max_bytes!r}")
        self._max_bytes = max_bytes
        self._active = active  # under _lock
        self._lock = threading.Lock()
        self._entries: OrderedDict[str, DecodedKeyframe] = OrderedDict()  # under _lock
        self._bytes = 0  # under _lock
        names = ("put", "hits", "from_store", "image_hits", "images_decoded", "evicted")
        self._counts = dict.fromkeys(names, 0)  # under _lock

    def set_active(self, active: bool) -> None:
        """Keep what :meth:`put` hands on only while a stage runs here to take it (a server
        that is a standby for the writer lease runs none); inactive, the entries go."""
        with self._lock:
            self._active = active
            if not active:
                self._entries.clear()
                self._bytes = 0

    def put(self, key: str, msg: KeyframeMsg, payload_bytes: int) -> None:
        """Keep ``msg``, decoded from a ``payload_bytes`` payload stored under ``key`` (ingest,
        after the commit); nothing while inactive."""
        entry = DecodedKeyframe(key, msg, payload_bytes)
        with self._lock:
            if not self._active:
                return
            self._counts["put"] += 1
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._entries[key] = entry
            self._bytes += entry.nbytes
            self._trim()

    def decoded(self, key: str, payload: bytes) -> DecodedKeyframe:
        """The entry of ``key``, or, when there is none, ``payload`` (that key's stored payload)
        decoded now and counted as ``from_store`` (not kept: the caller holds it as long as it
        needs it).

        Raises:
            WireError: the payload does not decode.
        """
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
                self._counts["hits"] += 1
                return entry
            self._counts["from_store"] += 1
        return DecodedKeyframe(key, decode_keyframe(payload), len(payload))

    def images(self, entry: DecodedKeyframe) -> KeyframeImages:
        """``entry``'s rasters, decoded on the first call for it (:func:`decode_images`).

        Raises:
            WireError: they do not decode (and will not on a later call either).
        """
        with self._lock:
            done = entry._images
            if done is not None:
                self._counts["image_hits"] += 1
        if done is None:
            try:
                done = decode_images(entry.msg)
            except WireError as exc:
                done = exc
            with self._lock:
                self._counts["images_decoded"] += 1
                if entry._images is None:
                    held = self._entries.get(entry.key) is entry
                    entry._images = done
                    if held and isinstance(done, KeyframeImages):
                        self._bytes += done.nbytes
                        self._trim()
                else:  # another thread decoded them meanwhile; keep the first
                    done = entry._images
        if isinstance(done, WireError):
            raise done
        return done

    def discard(self, key: str) -> None:
        """Drop ``key``'s entry (its last reader is done); nothing when there is none."""
        with self._lock:
            entry = self._entries.pop(key, None)
            if entry is not None:
                self._bytes -= entry.nbytes

    def counters(self) -> DecodedCounters:
        with self._lock:
            c = self._counts
            return DecodedCounters(c["put"], c["hits"], c["from_store"], c["image_hits"], c["images_decoded"],
                                   c["evicted"], len(self._entries), self._bytes)

    # ------------------------------------------------------------------ under _lock

    def _trim(self) -> None:
        while self._entries and self._bytes > self._max_bytes:
            _, old = self._entries.popitem(last=False)
            self._bytes -= old.nbytes
            self._counts["evicted"] += 1
