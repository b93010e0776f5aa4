"""Image retention and erasure: stored keyframe images do not outlive their purpose.

``[store] image_retention`` (e.g. ``"30d"``; ``"none"`` or ``"0"`` keeps them) bounds how long
the server keeps the colour JPEG and thermal raster of a keyframe after it received it. The
:class:`ImageRetention` job (one thread, owned by the composition root) erases the images of
older keyframes every ``image_retention_check_s``; poses, features, the pose graph,
measurements and objects stay, so the back-end and mapping still work on such keyframes
(:func:`~wardmap.server.store.codec.without_images`). Each run is logged when it erased
something and counted on ``/metrics`` (``wardmap_images_erased_total``; a failed run in
``wardmap_image_retention_failures_total``, tried again next period). An erase order for a time
range of capture stamps (``wardmap images erase``) uses the same store method
(:func:`erase_range`).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass
from typing import Final

from wardmap.server.store import MapStore, StoreError
from wardmap.server.telemetry import ServerTelemetry
from wardmap.shared.errors import ConfigError

log = logging.getLogger(__name__)

_UNITS_S: Final = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
_DURATION_RE: Final = re.compile(r"(\d+(?:\.\d+)?)([smhd])")


def parse_retention(text: str) -> float | None:
    """``"30d"``, ``"12h"``, ``"90m"``, ``"3600s"`` as seconds; ``"none"`` or ``"0"``: None (keep).

    Raises:
        ConfigError: anything else (the message names ``store.image_retention``).
    """
    value = text.strip().lower()
    if value in ("none", "0", ""):
        return None
    match = _DURATION_RE.fullmatch(value)
    if match is None or float(match.group(1)) <= 0:
        raise ConfigError(f"store.image_retention must be a duration like 30d, 12h, 90m or 3600s, "
                          f"or none/0 to keep images; got {text!r}")
    return float(match.group(1)) * _UNITS_S[match.group(2)]


@dataclass(frozen=True)
class RetentionConfig:
    """Image retention (``[store]`` table of the server's TOML config).

    Attributes:
        image_retention: how long keyframe images are kept after the server received them
            (``"30d"``, ``"12h"``; ``"none"``/``"0"``: forever).
        image_retention_check_s: how often the retention job runs (seconds).
    """

    image_retention: str = "none"
    image_retention_check_s: float = 3600.0

    def __post_init__(self) -> None:
        parse_retention(self.image_retention)
        if not 1.0 <= self.image_retention_check_s <= 86400.0:
            raise ConfigError(f"store.image_retention_check_s must be in [1, 86400] s, "
                              f"got {self.image_retention_check_s}")

    @property
    def retention_s(self) -> float | None:
        """The retention in seconds, None to keep images."""
        return parse_retention(self.image_retention)


def erase_range(store: MapStore, start_s: float, end_s: float, *, robot_id: str | None = None) -> int:
    """Erase the images of keyframes captured in ``[start_s, end_s)`` (POSIX seconds), of
    ``robot_id`` only when given; how many were erased (logged)."""
    n = store.erase_images(now_s=time.time(), stamp_from=start_s, stamp_to=end_s, robot_id=robot_id)
    log.info("erase order: images of %d keyframes in [%.3f, %.3f)%s erased", n, start_s, end_s,
             f" of {robot_id}" if robot_id else "")
    return n


class ImageRetention:
    """The retention job: a thread that erases images older than the retention every period.

    It owns nothing but its thread and stop event; the store serialises its writes.
    """

    def __init__(self, store: MapStore, retention_s: float, check_s: float,
                 telemetry: ServerTelemetry | None = None) -> None:
        if not retention_s > 0 or not check_s > 0:
            raise ConfigError(f"image retention {retention_s} s and check period {check_s} s must be > 0")
        self.store, self.retention_s, self.check_s = store, retention_s, check_s
        self._telemetry = telemetry
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="wardmap-image-retention", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """End the job (waits for a run in progress; idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def run_once(self, now_s: float | None = None) -> int:
        """Erase the images of keyframes received before ``now_s - retention``; how many.

        Raises:
            StoreError: the store failed (earlier batches stay erased).
        """
        now = time.time() if now_s is None else now_s
        n = self.store.erase_images(now_s=now, received_before_s=now - self.retention_s)
        if n:
            log.info("image retention: erased the images of %d keyframes received before %.0f s ago",
                     n, self.retention_s)
        if self._telemetry is not None:
            self._telemetry.images_erased.inc(n)
        return n

    def _main(self) -> None:
        while True:
            try:
                self.run_once()
            except StoreError as exc:
                log.warning("image retention: store failed, trying again in %.0f s: %s", self.check_s, exc)
                if self._telemetry is not None:
                    self._telemetry.image_retention_failures.inc()
            if self._stop.wait(self.check_s):
                return
