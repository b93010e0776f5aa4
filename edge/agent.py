"""The edge daemon (``wardmap edge``): data set -> tracker -> durable outbox -> Zenoh.

One :class:`EdgeAgent` runs one robot. Threads and the state each one owns:

- the *tracking* thread (the caller of :meth:`EdgeAgent.run`, normally the main thread)
  owns the :class:`~wardmap.edge.tracker.Tracker`, takes frames from the stream, builds and encodes a
  :class:`~wardmap.shared.wire.KeyframeMsg` for every keyframe and puts it into the
  :class:`~wardmap.edge.outbox.Outbox` *before* anything is published. When the outbox is
  full (:class:`~wardmap.edge.outbox.OutboxFull`) it waits for acks and retries:
  backpressure slows the tracker, nothing is dropped.
- the *sender* thread owns the Zenoh publishers and every network counter. It applies
  acks, publishes due outbox items (never sent, or not acked within ``resend_after_s``)
  reliable with congestion control ``BLOCK``, marks them sent, and publishes a
  :class:`~wardmap.shared.wire.HeartbeatMsg` every ``heartbeat_period_s``.
- the Zenoh ack-subscriber callback only enqueues the raw payload into the sender's
  bounded inbox (policy :data:`INBOX_POLICY`); so do the correction subscriber's and the
  correction query's callbacks.

Corrections (docs/wire.md, ``wardmap.correction``): the sender subscribes to the robot's
correction key, queries it at start and every :attr:`AgentConfig.correction_query_s` (a robot
that reconnected, or missed a put, learns its correction) and hands each payload to its
:class:`~wardmap.edge.corrections.Corrections`, which applies the running session's newest and
counts what it refuses by reason. The heartbeat reports ``anchored``, ``corrections``,
``bad_corrections`` and the map pose ``map_x map_y map_z map_yaw_deg`` of the latest keyframe's
base (its camera without odometry); the summary the same, with the refusals by reason.
Keyframes keep carrying only the ``--map-pose`` prior as their ``T_map_odom``.

Acks: ``stored`` and ``duplicate`` remove the item from the outbox. ``rejected`` also
removes it (the server validated it and will never accept that payload, so resending it
is pointless) and counts the reason in ``rejected`` of the summary; it is logged as a
warning. ``retry`` (the server's storage failed: disk full, locked, damaged) keeps the item:
it is resent ``resend_after_s`` after its last send, like an unacked one, and counted in
``retry_later`` (summary and heartbeat); a warning is logged when such a spell begins.

Sources (:mod:`wardmap.edge.stream`, docs/sources.md): any
:class:`~wardmap.edge.stream.StreamSource` (a ROS recording, :class:`~wardmap.edge.bag.BagSource`),
or a data-set folder or :class:`~wardmap.shared.dataset.FrameSource` object (e.g. the
simulator's live run that ``wardmap edge --source sim:SCENARIO`` builds), streamed through
:class:`~wardmap.edge.stream.FrameSourceStream`. A :class:`~wardmap.edge.stream.FrameStream`
runs the source on its own *frame-stream* thread and hands the tracking thread each frame
with its odometry pose; when tracking falls behind a live source (or a replay with
:attr:`AgentConfig.drop_when_behind`), frames are dropped and counted (``frames_dropped`` in the
summary, ``dropped`` in the heartbeat), never queued without bound; any other replay waits for
the tracker. A live source (a camera, ROS 2 topics: :class:`~wardmap.edge.live.ReconnectingSource`)
reconnects by itself; the heartbeat reports its ``reconnects`` and ``source_up``, frames
``received``/``tracked``/``dropped`` and the latest frame's odometry-frame pose ``odom_*``.
:meth:`EdgeAgent.stop` closes the stream. Label source: ``none``, ``oracle`` or
``onnx:PATH`` (:mod:`wardmap.edge.labels`), exactly as ``wardmap track`` runs it.

Privacy (:mod:`wardmap.edge.privacy`, docs/security.md): the label source's person mask of
each keyframe, dilated by :attr:`AgentConfig.privacy_dilate_px`, is blanked or blurred in the
colour image and blanked in the thermal raster (:attr:`AgentConfig.privacy`) before the message
is encoded, so the outbox and the network only see redacted images; a redacting mode with labels
``none`` is refused at construction (nobody could find the people), and ``off`` is logged as a
warning at every start. The summary counts
``keyframes_with_people`` and ``keyframes_unlabelled`` (redacted whole).

Keypoints: the tracker's own features of the keyframe, after dynamic-point removal (what
its map was built from), the strongest :attr:`AgentConfig.max_keypoints` of them. A
keyframe the tracker made without RGB features (rare) gets ORB extracted. The message is
built by :func:`wardmap.edge.keyframes.build_keyframe_msg`, which the offline tools share.

Size budget (docs/wire.md, "Budget"; goal: mean <= 100 KB): JPEG quality
:attr:`AgentConfig.jpeg_quality`, depth at 1/:attr:`AgentConfig.depth_stride`
resolution (falls back to 1 when the image size is not divisible by it), thermal at
1/:attr:`AgentConfig.thermal_stride` resolution, quantised to
:attr:`AgentConfig.thermal_unit_k`, on every :attr:`AgentConfig.thermal_every`-th keyframe
and on every keyframe whose pose came from thermal tracking.

Latency: the sender notes when it first published each item; when its ack arrives the
difference (publish -> server commit -> ack back, an upper bound of publish -> commit)
goes into the summary's ``latency_ms`` percentiles.

Stopping: :meth:`EdgeAgent.stop` (SIGTERM/SIGINT while :func:`run_agent` runs) ends
tracking, then the agent waits up to ``flush_timeout_s`` for the outbox to empty and
closes the session. Anything still unacked stays in the outbox and is re-sent with its
original ``(robot, session, seq)`` by the next start.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from wardmap.edge.corrections import Corrections
from wardmap.edge.keyframes import build_keyframe_msg, thermal_due
from wardmap.edge.labels import LabelSource, make_label_source
from wardmap.edge.metrics import EdgeMetrics
from wardmap.edge.outbox import Outbox, OutboxFull, OutboxItem, SessionIds
from wardmap.edge.privacy import PRIVACY_MODES, person_mask
from wardmap.edge.readout import OnlineReadout
from wardmap.edge.stream import FrameSourceStream, FrameStream, StreamSource
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput, warm_up
from wardmap.shared.dataset import DatasetReader, Frame, FrameSource
from wardmap.shared.errors import ConfigError, DatasetError, WardmapError, WireError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.signals import on_stop_signals
from wardmap.shared.wire import (
    HeartbeatMsg,
    Intrinsics,
    KeyframeMsg,
    decode_ack,
    encode,
)
from wardmap.shared.zenoh_config import (
    ZenohOptions,
    ack_key,
    client_config,
    correction_key,
    heartbeat_key,
    keyframe_key,
    liveliness_key,
    validate_endpoint,
    validate_robot_id,
)
from wardmap.shared.zenoh_load import connect_hint, load_zenoh_config, zenoh_error_line

log = logging.getLogger(__name__)

INBOX_POLICY: Final = "drop-newest"
"""Policy of the sender's bounded inbox (acks and wake-ups). When full, a new entry is
dropped and counted (``inbox_dropped``). Safe: a dropped ack leaves its item in the
outbox, it is re-sent after ``resend_after_s`` and the server answers ``duplicate``; a
dropped wake-up only delays the next send by at most ``poll_s``; a dropped correction makes
the sender query the server for the latest one at once."""

_KICK: Final = b""  # inbox entry that only wakes the sender
MAX_LATENCY_SAMPLES: Final = 1_000_000


@dataclass(frozen=True)
class _Correction:
    """Inbox entry: a correction payload as received (the subscription or a query reply)."""

    payload: bytes


@dataclass(frozen=True)
class AgentConfig:
    """Settings of one edge agent (``[agent]`` table of a TOML config; CLI flags override).

    Attributes:
        rate_hz: frames per second a recorded source is replayed at, at most; 0 = as fast as
            the tracker goes.
        drop_when_behind: replay like a camera: frames the tracker cannot keep up with are
            dropped and counted instead of slowing the replay (:mod:`wardmap.edge.stream`; a
            live source always does this).
        max_frames: stop after this many frames (None: the whole source).
        stream_capacity: frames waiting for the tracker at most (the stream's slot).
        resend_after_s: re-send an item not acked this long after its last send.
        flush_timeout_s: on stop, wait at most this long for the outbox to empty.
        heartbeat_period_s: period of the heartbeat message.
        depth_stride: depth sent at 1/stride resolution (1, 2 or 4).
        jpeg_quality: JPEG quality of the colour image (1-100).
        max_keypoints: keypoints sent per keyframe at most (strongest first).
        thermal_every: send thermal on every n-th keyframe (0: only on thermal-tracked ones).
        thermal_stride: thermal sent at 1/stride resolution (1, 2 or 4).
        thermal_unit_k: thermal quantum in kelvin (the sensor's NETD is ~0.05 K).
        labels: label source spec for dynamic-point removal (``none``, ``oracle``, ``onnx:PATH``).
        label_threads: CPU threads of the label network.
        privacy: what is done to people in the keyframe images before they leave the robot
            (:mod:`wardmap.edge.privacy`): ``blur``, ``blank`` or ``off``. A redacting mode needs
            a label source that finds people: with ``labels = "none"`` the agent refuses to start.
        privacy_dilate_px: margin in colour-image pixels the person mask is grown by.
        send_batch: outbox items read per send round.
        inbox_size: capacity of the sender's inbox (policy :data:`INBOX_POLICY`).
        poll_s: longest the sender sleeps without a wake-up (resend and heartbeat checks).
        correction_query_s: query the server for this session's correction this often (it is
            also subscribed to and queried at start); 0 = only at start.
        outbox_max_items, outbox_max_bytes: outbox capacity (OutboxFull beyond: backpressure).
    """

    rate_hz: float = 0.0
    max_frames: int | None = None
    drop_when_behind: bool = False
    stream_capacity: int = 2
    resend_after_s: float = 2.0
    flush_timeout_s: float = 10.0
    heartbeat_period_s: float = 1.0
    depth_stride: int = 4
    jpeg_quality: int = 80
    max_keypoints: int = 700
    thermal_every: int = 4
    thermal_stride: int = 2
    thermal_unit_k: float = 0.05
    labels: str = "none"
    label_threads: int = 1
    privacy: str = "blank"
    privacy_dilate_px: int = 12
    send_batch: int = 16
    inbox_size: int = 1024
    poll_s: float = 0.1
    correction_query_s: float = 10.0
    outbox_max_items: int = 10_000
    outbox_max_bytes: int = 2 << 30

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate_hz) and self.rate_hz >= 0):
            raise ConfigError(f"agent.rate_hz must be >= 0 (0 = as fast as possible), got {self.rate_hz}")
        if self.max_frames is not None and self.max_frames <= 0:
            raise ConfigError(f"agent.max_frames must be positive, got {self.max_frames}")
        for name in ("resend_after_s", "heartbeat_period_s", "poll_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"agent.{name} must be > 0, got {getattr(self, name)}")
        if not (np.isfinite(self.correction_query_s) and self.correction_query_s >= 0):
            raise ConfigError(f"agent.correction_query_s must be >= 0 (0 = only at start), "
                              f"got {self.correction_query_s}")
        if not self.flush_timeout_s >= 0:
            raise ConfigError(f"agent.flush_timeout_s must be >= 0, got {self.flush_timeout_s}")
        if self.depth_stride not in (1, 2, 4):
            raise ConfigError(f"agent.depth_stride must be 1, 2 or 4, got {self.depth_stride}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"agent.jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if self.thermal_stride not in (1, 2, 4):
            raise ConfigError(f"agent.thermal_stride must be 1, 2 or 4, got {self.thermal_stride}")
        if self.thermal_every < 0 or self.max_keypoints < 0:
            raise ConfigError("agent.thermal_every and agent.max_keypoints must be >= 0")
        if not (np.isfinite(self.thermal_unit_k) and 0 < self.thermal_unit_k <= 1):
            raise ConfigError(f"agent.thermal_unit_k must be in (0, 1] K, got {self.thermal_unit_k}")
        if self.privacy not in PRIVACY_MODES:
            raise ConfigError(f"agent.privacy must be one of {', '.join(PRIVACY_MODES)}, "
                              f"got {self.privacy!r}")
        if not 0 <= self.privacy_dilate_px <= 200:
            raise ConfigError(f"agent.privacy_dilate_px must be in 0..200, got {self.privacy_dilate_px}")
        if self.label_threads < 1:
            raise ConfigError(f"agent.label_threads must be >= 1, got {self.label_threads}")
        for name in ("stream_capacity", "send_batch", "inbox_size", "outbox_max_items", "outbox_max_bytes"):
            if getattr(self, name) < 1:
                raise ConfigError(f"agent.{name} must be >= 1, got {getattr(self, name)}")


@dataclass
class _SenderStats:
    """Counters owned by the sender thread (read by others only after it has stopped)."""

    sent: int = 0
    resent: int = 0
    acked: int = 0
    duplicates: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    retry_later: int = 0
    retrying: bool = False  # the last ack was ``retry`` (logs the start of a spell once)
    bad_acks: int = 0
    heartbeats: int = 0
    first_sent: dict[tuple[str, str, int], float] = field(default_factory=dict)
    latencies_ms: list[float] = field(default_factory=list)


@dataclass
class _TrackStats:
    """Counters owned by the tracking thread."""

    frames: int = 0
    keyframes: int = 0
    lost: int = 0
    outbox_full_waits: int = 0
    payload_bytes: int = 0
    thermal_sent: int = 0
    with_people: int = 0  # keyframes whose images had person pixels redacted
    unlabelled: int = 0  # keyframes redacted whole: the label source gave no labels for them


class EdgeAgent:
    """One robot: tracker over a frame source, outbox, Zenoh sender.

    Construct, then call :meth:`run` (blocks; returns a summary); :meth:`stop` may be
    called from any thread or a signal handler.
    """

    def __init__(
        self,
        robot_id: str,
        source: str | Path | FrameSource | StreamSource,
        connect: Sequence[str],
        outbox_path: str | Path,
        *,
        config: AgentConfig | None = None,
        tracker_config: TrackerConfig | None = None,
        T_map_odom: NDArray[np.float64] | None = None,
        metrics: EdgeMetrics | None = None,
        zenoh_options: ZenohOptions | None = None,
    ) -> None:
        """Args:
            T_map_odom: (4, 4) this session's odom frame (the base at start) in the shared map,
                when the robot starts at a known map pose; sent with every keyframe.
            metrics: where frames, outbox depth and ack latency are recorded
                (``edge/metrics.py``), or None.
            zenoh_options: TLS files (site CA, this robot's certificate and key) and a zenoh
                config file for the session (docs/security.md); checked when :meth:`run` starts.
        """
        self.robot_id = validate_robot_id(robot_id)
        self.T_map_odom = None if T_map_odom is None else np.array(T_map_odom, np.float64)
        self.connect = [validate_endpoint(e) for e in connect]
        self.zenoh_options = zenoh_options
        if not self.connect:
            raise ConfigError("the edge agent needs at least one --connect endpoint")
        if isinstance(source, (str, Path)):
            if not Path(source).is_dir():
                raise DatasetError(f"data set {str(source)!r} is not a folder")
            source = DatasetReader(source)
        # a random-access data set (a folder, the simulator's live run) streams like any source
        self.source: StreamSource = FrameSourceStream(source) if hasattr(source, "frame") else source  # type: ignore[arg-type]
        self.outbox_path = Path(outbox_path)
        self.cfg = config or AgentConfig()
        if self.cfg.privacy != "off" and self.cfg.labels == "none":
            raise ConfigError(
                f"agent.privacy = {self.cfg.privacy!r} needs a label source that finds people, but "
                "agent.labels is 'none': set labels (oracle for simulated data, onnx:PATH) or, only "
                "where the site's privacy officer allows unredacted images, privacy = 'off' (--privacy off)"
            )
        self.tracker_cfg = tracker_config or TrackerConfig()
        self._metrics = metrics
        self._stop = threading.Event()  # set once: end tracking
        self._sender_stop = threading.Event()  # set once: end the sender thread
        self._drained = threading.Event()  # set by the sender when the outbox is empty
        self._space = threading.Event()  # set by the sender after it removed items
        self._inbox: queue.Queue[bytes | _Correction] = queue.Queue(maxsize=self.cfg.inbox_size)
        self._inbox_dropped = 0  # guarded by _dropped_lock (enqueuers run on several threads)
        self._dropped_lock = threading.Lock()
        self._progress: tuple[int, int, int] = (0, 0, 0)  # (frames, keyframes, lost): atomic swap
        self._frame_pose: NDArray[np.float64] | None = None  # T_odom_camera of the latest frame: swapped
        self._sender_stats = _SenderStats()
        self._corrections = Corrections(self.robot_id, T_map_odom_prior=self.T_map_odom)  # sender's
        self._query_correction = threading.Event()  # set when a correction was dropped: ask again
        # (T_odom_base, T_odom_camera) of the latest keyframe put: swapped whole by the tracker
        self._latest_pose: tuple[NDArray[np.float64] | None, NDArray[np.float64]] | None = None
        self._sender_error: BaseException | None = None
        self._stream: FrameStream | None = None  # set by run(); close() ends its iteration
        self._online: OnlineReadout | None = None  # the tracking thread's online readout estimate, if any

    # ------------------------------------------------------------------ control

    def stop(self) -> None:
        """Ask the agent to stop tracking, flush and exit (thread and signal safe)."""
        self._stop.set()
        stream = self._stream
        if stream is not None:
            stream.close()

    def _enqueue(self, entry: bytes | _Correction) -> None:
        """Put into the sender's inbox without blocking (policy :data:`INBOX_POLICY`)."""
        try:
            self._inbox.put_nowait(entry)
        except queue.Full:
            with self._dropped_lock:
                self._inbox_dropped += 1
            if isinstance(entry, _Correction):
                self._query_correction.set()

    # ------------------------------------------------------------------ run

    def run(self, on_ready: Callable[[str, int], None] | None = None) -> dict[str, Any]:
        """Track the data set, send keyframes, flush on stop; return a JSON-able summary.

        ``on_ready(session_id, pending_items)`` is called once the session, the
        publishers, the ack and correction subscribers and the liveliness token are declared.
        """
        import zenoh  # the only zenoh user on the edge; imported here, not at module import

        source = self.source
        kg = KnowledgeGraph.load()
        labels = make_label_source(self.cfg.labels, dataset=source.dataset, kg=kg,
                                   threads=self.cfg.label_threads)
        mobility_lut = kg.mobility_lut()
        if source.live or self.cfg.drop_when_behind:  # a frame missed while compiling is lost
            spent = warm_up(source.calibration, self.tracker_cfg, mobility_lut)
            log.info("tracker kernels ready in %.1f s", spent)
        tracker = Tracker(source.calibration, self.tracker_cfg, mobility_lut)
        stream = FrameStream(source, capacity=self.cfg.stream_capacity, rate_hz=self.cfg.rate_hz,
                             drop_when_behind=self.cfg.drop_when_behind, max_frames=self.cfg.max_frames)
        zcfg = load_zenoh_config(client_config(self.connect, options=self.zenoh_options), self.zenoh_options)
        t_start = time.monotonic()
        track = _TrackStats()
        with Outbox.open(
            self.outbox_path, max_items=self.cfg.outbox_max_items, max_bytes=self.cfg.outbox_max_bytes
        ) as outbox:
            ids = outbox.start_session(self.robot_id)
            try:
                session = zenoh.open(zcfg)
            except zenoh.ZError as exc:
                raise WardmapError(
                    f"cannot connect to {', '.join(self.connect)}: {zenoh_error_line(exc)}"
                    f"{connect_hint(self.connect)}"
                ) from exc
            with session, contextlib.ExitStack() as decl:
                decl.enter_context(session.declare_subscriber(ack_key(self.robot_id), self._on_ack))
                decl.enter_context(
                    session.declare_subscriber(correction_key(self.robot_id), self._on_correction)
                )
                token = session.liveliness().declare_token(liveliness_key(self.robot_id))
                decl.callback(token.undeclare)
                sender = threading.Thread(
                    target=self._sender_main, args=(zenoh, session, outbox, ids), name="edge-sender"
                )
                sender.start()
                try:
                    if self.cfg.privacy == "off":  # once connected: a failed start stays one error line
                        log.warning("privacy is off: keyframe images leave this robot with people unredacted")
                    if on_ready is not None:
                        on_ready(ids.session_id, len(outbox))
                    self._stream = stream
                    if self._stop.is_set():
                        stream.close()
                    with stream, tracker:  # the tracker's bundle-adjustment worker stops with it
                        self._track_loop(stream, labels, mobility_lut, tracker, outbox, ids, track)
                    flushed = self._flush(outbox)
                finally:
                    self._stop.set()
                    self._sender_stop.set()
                    self._enqueue(_KICK)
                    sender.join()
            pending = len(outbox)
        if self._sender_error is not None:
            raise WardmapError(f"edge sender failed: {self._sender_error}") from self._sender_error
        s = self._sender_stats
        lat = np.asarray(s.latencies_ms, np.float64)
        return {
            "robot_id": self.robot_id,
            "session_id": ids.session_id,
            "frames": track.frames,
            "keyframes": track.keyframes,
            "lost_frames": track.lost,
            **{f"frames_{k}": v for k, v in stream.counters().items()},
            "reconnects": int(getattr(source, "reconnects", 0)),
            "sent": s.sent,
            "resent": s.resent,
            "acked": s.acked,
            "duplicates": s.duplicates,
            "rejected": dict(s.rejected),
            "retry_later": s.retry_later,
            "bad_acks": s.bad_acks,
            "inbox_dropped": self._inbox_dropped,
            "outbox_full_waits": track.outbox_full_waits,
            "pending": pending,
            "flushed": flushed,
            "bytes_per_keyframe": round(track.payload_bytes / track.keyframes) if track.keyframes else 0,
            "thermal_keyframes": track.thermal_sent,
            "privacy": self.cfg.privacy,
            "keyframes_with_people": track.with_people,
            "keyframes_unlabelled": track.unlabelled,
            "latency_ms": _percentiles(lat),
            **({"online_readout": self._online.summary()} if self._online is not None else {}),
            **self._corrections.summary(**self._pose_args()),  # the sender has stopped
            "seconds": round(time.monotonic() - t_start, 3),
        }

    # ------------------------------------------------------------------ tracking thread

    def _track_loop(
        self,
        stream: FrameStream,
        labels: LabelSource,
        mobility_lut: NDArray[np.uint8],
        tracker: Tracker,
        outbox: Outbox,
        ids: SessionIds,
        track: _TrackStats,
    ) -> None:
        calib = stream.source.calibration
        intrinsics = Intrinsics.from_camera(calib.rgb, calib.depth_scale)
        # no readout time known: estimated from the first turning frames in a child process
        online = OnlineReadout(calib, self.tracker_cfg) if OnlineReadout.wanted(tracker.readout) else None
        self._online = online
        for item in stream:
            if self._stop.is_set():
                break
            frame: Frame | None = item.frame
            T_odom_base = item.T_odom_base
            person: NDArray[np.bool_] | None = None  # people in the frame (None: no labels)
            if frame is None:
                inp = TrackInput(item.stamp, None, None, T_odom_base=T_odom_base,
                                 problem=item.problem or "cannot read frame")
            else:
                lab = labels.labels(frame)
                inp = TrackInput(
                    item.stamp, frame.rgb, frame.depth_m, frame.thermal_k, T_odom_base,
                    class_image=None if lab is None else lab.class_image,
                )
                person = None if lab is None else person_mask(lab.class_image, mobility_lut)
            res = tracker.track(inp)
            if online is not None and (found := online.offer(inp, res)) is not None:
                tracker.readout = found  # from the next frame on
            self._frame_pose = res.T_world_camera
            track.frames += 1
            track.lost += int(res.lost)
            if self._metrics is not None:
                self._metrics.frame(bool(res.lost))
            if res.keyframe and frame is not None:
                if self.cfg.privacy != "off":
                    track.with_people += int(person is not None and bool(person.any()))
                    if person is None:
                        track.unlabelled += 1
                        log.warning("no labels for keyframe at %.6f: its images are redacted whole",
                                    frame.stamp)
                msg = build_keyframe_msg(
                    frame, res, tracker, T_odom_base=T_odom_base, intrinsics=intrinsics,
                    robot_id=self.robot_id, session_id=ids.session_id, seq=ids.next_seq, config=self.cfg,
                    with_thermal=thermal_due(res.source, track.keyframes, self.cfg.thermal_every),
                    T_map_odom=self.T_map_odom, person=person,
                )
                track.thermal_sent += int(msg.thermal is not None)
                if not self._put_with_backpressure(ids, msg, track):
                    break
                track.keyframes += 1
            self._progress = (track.frames, track.keyframes, track.lost)
        self._progress = (track.frames, track.keyframes, track.lost)
        if online is not None:
            online.close()

    def _put_with_backpressure(self, ids: SessionIds, msg: KeyframeMsg, track: _TrackStats) -> bool:
        """Put ``msg`` into the outbox; while it is full, wait for acks (never drop); True if stored.

        Only a stop request ends the wait; that keyframe is then not stored (logged, False).
        """
        payload = encode(msg)
        track.payload_bytes += len(payload)
        while True:
            self._space.clear()
            try:
                seq = ids.put(msg.stamp, payload)
            except OutboxFull:
                track.outbox_full_waits += 1
                log.warning("outbox full: tracking waits for acks")
                while not self._space.wait(self.cfg.poll_s):
                    if self._stop.is_set():
                        log.warning("stopped with the outbox full: keyframe %.6f not stored", msg.stamp)
                        return False
                continue
            if seq != msg.seq:  # only this thread puts into this session
                raise WardmapError(f"outbox seq {seq} differs from the message's {msg.seq}")
            self._latest_pose = (msg.T_odom_base, msg.T_odom_camera)
            self._drained.clear()
            self._enqueue(_KICK)
            return True

    def _flush(self, outbox: Outbox) -> bool:
        """Wait up to ``flush_timeout_s`` for the outbox to empty; True if it did."""
        deadline = time.monotonic() + self.cfg.flush_timeout_s
        while len(outbox):
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._sender_stop.is_set():
                log.info("flush: %d items stay in the outbox for the next start", len(outbox))
                return False
            self._drained.wait(min(remaining, self.cfg.poll_s))
        return True

    # ------------------------------------------------------------------ zenoh callback

    def _on_ack(self, sample: Any) -> None:
        """Ack subscriber callback: enqueue the raw payload, nothing else."""
        self._enqueue(sample.payload.to_bytes())

    def _on_correction(self, sample: Any) -> None:
        """Correction subscriber callback: enqueue the raw payload, nothing else."""
        self._enqueue(_Correction(sample.payload.to_bytes()))

    def _on_correction_reply(self, reply: Any) -> None:
        """Correction query callback: enqueue an answer's raw payload (an error reply is logged)."""
        if reply.ok is not None:
            self._enqueue(_Correction(reply.ok.payload.to_bytes()))
        else:
            log.warning("correction query answered with an error: %r", reply.err.payload.to_bytes()[:200])

    # ------------------------------------------------------------------ sender thread

    def _sender_main(self, zenoh: Any, session: Any, outbox: Outbox, ids: SessionIds) -> None:
        try:
            self._sender_loop(zenoh, session, outbox, ids)
        except BaseException as exc:  # reported by run(); the tracker must not wait forever
            log.exception("edge sender failed")
            self._sender_error = exc
            self._stop.set()
            self._sender_stop.set()

    def _sender_loop(self, zenoh: Any, session: Any, outbox: Outbox, ids: SessionIds) -> None:
        cfg = self.cfg
        stats = self._sender_stats
        with contextlib.ExitStack() as decl:
            publishers: dict[str, Any] = {}

            def publisher(robot_id: str) -> Any:
                # One publisher per robot id in the outbox (normally just ours).
                if robot_id not in publishers:
                    publishers[robot_id] = decl.enter_context(
                        session.declare_publisher(
                            keyframe_key(robot_id),
                            reliability=zenoh.Reliability.RELIABLE,
                            congestion_control=zenoh.CongestionControl.BLOCK,
                        )
                    )
                return publishers[robot_id]

            heartbeat = decl.enter_context(
                session.declare_publisher(
                    heartbeat_key(self.robot_id),
                    reliability=zenoh.Reliability.RELIABLE,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            )
            next_heartbeat = next_query = time.monotonic()
            while not self._sender_stop.is_set():
                if time.monotonic() >= next_query or self._query_correction.is_set():
                    self._query_correction.clear()
                    self._request_correction(zenoh, session, ids)
                    period = cfg.correction_query_s
                    next_query = time.monotonic() + period if period > 0 else float("inf")
                self._apply_acks(outbox, ids, stats)
                due = outbox.pending(cfg.send_batch, resend_after_s=cfg.resend_after_s)
                if due:
                    self._publish(publisher, outbox, due, stats)
                if not len(outbox):
                    self._drained.set()
                now = time.monotonic()
                if now >= next_heartbeat:
                    self._heartbeat(heartbeat, outbox, ids, stats)
                    next_heartbeat = now + cfg.heartbeat_period_s
                if len(due) == cfg.send_batch:
                    continue  # more are due: keep sending
                now = time.monotonic()
                wait = max(0.0, min(cfg.poll_s, next_heartbeat - now, next_query - now))
                try:
                    entry = self._inbox.get(timeout=wait)
                except queue.Empty:
                    continue
                self._handle_entry(entry, outbox, ids, stats)
            self._apply_acks(outbox, ids, stats)
            self._heartbeat(heartbeat, outbox, ids, stats)

    def _request_correction(self, zenoh: Any, session: Any, ids: SessionIds) -> None:
        """Ask the server for this session's latest correction; replies reach the inbox."""
        selector = f"{correction_key(self.robot_id)}?session_id={ids.session_id}"
        try:
            session.get(selector, self._on_correction_reply)
        except zenoh.ZError as exc:  # the next period asks again
            log.warning("cannot query %s: %s", selector, str(exc).split(" at /", 1)[0])

    def _apply_acks(self, outbox: Outbox, ids: SessionIds, stats: _SenderStats) -> None:
        while True:
            try:
                entry = self._inbox.get_nowait()
            except queue.Empty:
                return
            self._handle_entry(entry, outbox, ids, stats)

    def _handle_entry(self, entry: bytes | _Correction, outbox: Outbox, ids: SessionIds,
                      stats: _SenderStats) -> None:
        if isinstance(entry, _Correction):
            self._corrections.handle(entry.payload, ids.session_id)
            return
        if entry == _KICK:
            return
        try:
            ack = decode_ack(entry)
        except WireError as exc:
            stats.bad_acks += 1
            log.warning("ignoring a bad ack: %s", exc)
            return
        if ack.robot_id != self.robot_id:
            stats.bad_acks += 1
            log.warning("ignoring an ack for robot %r on robot %r's key", ack.robot_id, self.robot_id)
            return
        if ack.status == "retry":
            # The server could not store it (its storage failed): keep it; pending() resends it
            # resend_after_s after the send this answers.
            stats.retry_later += 1
            if not stats.retrying:
                log.warning("the server cannot store keyframes now (%s); keeping them to resend", ack.reason)
            stats.retrying = True
            return
        stats.retrying = False
        if ack.status == "rejected":
            # The server will never accept this payload: resending is pointless; drop it, count why.
            stats.rejected[ack.reason or "(no reason)"] += 1
            log.warning("keyframe %s/%d rejected by the server: %s", ack.session_id, ack.seq, ack.reason)
            outbox.ack(ack.robot_id, ack.session_id, ack.seq)
        elif outbox.ack(ack.robot_id, ack.session_id, ack.seq):
            stats.acked += 1
            stats.duplicates += int(ack.status == "duplicate")
            first = stats.first_sent.pop((ack.robot_id, ack.session_id, ack.seq), None)
            if first is not None and self._metrics is not None:
                self._metrics.ack_seconds.observe(time.monotonic() - first)
            if first is not None and len(stats.latencies_ms) < MAX_LATENCY_SAMPLES:
                stats.latencies_ms.append((time.monotonic() - first) * 1e3)
        self._space.set()
        if not len(outbox):
            self._drained.set()

    def _publish(
        self, publisher: Callable[[str], Any], outbox: Outbox, items: list[OutboxItem], stats: _SenderStats
    ) -> None:
        for item in items:
            if item.attempts == 0:
                stats.first_sent[item.key] = time.monotonic()
            publisher(item.robot_id).put(item.payload)
            stats.sent += 1
            stats.resent += int(item.attempts > 0)
            if item.attempts > 0:
                log.info("re-sent %s/%s/%d (attempt %d)", *item.key, item.attempts + 1)
        outbox.mark_sent([item.key for item in items])

    def _heartbeat(self, pub: Any, outbox: Outbox, ids: SessionIds, stats: _SenderStats) -> None:
        frames, keyframes, lost = self._progress
        pending = len(outbox)
        if self._metrics is not None:
            self._metrics.outbox_depth.set(pending)
        msg = HeartbeatMsg(
            robot_id=self.robot_id,
            session_id=ids.session_id,
            stamp=time.time(),
            stats={
                "frames": frames,
                "keyframes": keyframes,
                "lost": lost,
                **self._stream_stats(),
                "pending": pending,
                "sent": stats.sent,
                "acked": stats.acked,
                "resent": stats.resent,
                "rejected": sum(stats.rejected.values()),
                "retry_later": stats.retry_later,
                "inbox_dropped": self._inbox_dropped,
                **self._corrections.stats(**self._pose_args()),
            },
        )
        pub.put(encode(msg))
        stats.heartbeats += 1

    def _stream_stats(self) -> dict[str, int | float]:
        """The heartbeat's source numbers: frames the source gave (``received``), those dropped
        because tracking was behind or came out of order (``dropped``), frames with a measured pose
        (``tracked``), the live source's ``reconnects``, ``source_up`` (0 while it is lost) and
        ``source_dropped`` (frames it let go before they reached the stream: a full subscription
        queue, a camera SDK's frame drops), and
        the latest frame's camera pose in the odometry frame ``odom_x odom_y odom_z`` (m) and
        ``odom_yaw_deg`` (heading of its optical axis about z) once a frame was tracked."""
        frames, _, lost = self._progress
        out: dict[str, int | float] = {"received": 0, "dropped": 0, "tracked": frames - lost,
                                       "reconnects": int(getattr(self.source, "reconnects", 0)),
                                       "source_up": int(bool(getattr(self.source, "up", True))),
                                       "source_dropped": 0}
        stream = self._stream
        if stream is not None:
            counted = stream.counters()
            out.update(received=counted["received"], dropped=counted["dropped"] + counted["late"],
                       source_dropped=counted["source_dropped"])
        T = self._frame_pose
        if T is not None:
            x, y, z = (round(float(v), 3) for v in T[:3, 3])
            yaw = round(math.degrees(math.atan2(float(T[1, 2]), float(T[0, 2]))), 2)
            out.update(odom_x=x, odom_y=y, odom_z=z, odom_yaw_deg=yaw)
        return out

    def _pose_args(self) -> dict[str, NDArray[np.float64] | None]:
        """The latest keyframe's odom-frame poses as keyword arguments of the map-pose methods."""
        latest = self._latest_pose
        if latest is None:
            return {}
        return {"T_odom_base": latest[0], "T_odom_camera": latest[1]}


def _percentiles(values: NDArray[np.float64]) -> dict[str, float] | None:
    """p50/p95/p99/max of ``values`` (milliseconds), rounded to 0.1; None when empty."""
    if not len(values):
        return None
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"n": len(values), "p50": round(float(p50), 1), "p95": round(float(p95), 1),
            "p99": round(float(p99), 1), "max": round(float(values.max()), 1)}


def run_agent(agent: EdgeAgent, on_ready: Callable[[str, int], None] | None = None) -> dict[str, Any]:
    """Run ``agent`` until its data set ends or a SIGTERM/SIGINT arrives; return its summary."""
    with on_stop_signals(agent.stop, "the edge agent"):
        return agent.run(on_ready)
