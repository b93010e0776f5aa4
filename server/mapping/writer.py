"""The map writer: measured keyframes -> association -> the object map.

:class:`MapWriter` feeds keyframes of anchored sessions, in the map frame, to the
:class:`~wardmap.server.association.associator.Associator` (paper 000: keyframe groups per
robot session, HDP across groups) and writes the landmarks it created or changed into the
:class:`~wardmap.server.objectmap.ObjectMap`, each with only the observations new to it, so
an update costs the same however often the object has been seen. Landmarks the associator
merged into another are deleted from the map, their observations moved. A landmark's colour
is the mean of the colour histograms of every measurement it ever took (a running sum per
landmark: the live associator keeps only each landmark's recent measurements).

A robot's new session ends its previous one: that session's last, incomplete keyframe group
is associated when the new session's first keyframe comes (decided from the keyframe order
alone, so a replay repeats it exactly). :meth:`MapWriter.close` does the same on request
(an idle session).

Not thread safe: one thread (the mapping stage's) owns a writer.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.objectmap import ObjectMap, from_landmark
from wardmap.server.perception.measure import MeasureConfig, mean_rgb
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.knowledge import KnowledgeGraph

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MappedKeyframe:
    """What association needs of one anchored keyframe.

    Attributes:
        stream: ``"<robot>/<session>"``: keyframe groups never span two sessions.
        T_map_camera: (4, 4) float64 colour-camera pose in the map frame.
        camera: the colour camera of the measurements' pixel boxes.
        measurements: the keyframe's object measurements (map frame).
    """

    stream: str
    T_map_camera: F64
    camera: PinholeCamera
    measurements: Sequence[ObjectMeasurement]


@dataclass
class WriterState:
    """A writer's association state (what the stage's checkpoint holds of it).

    Attributes:
        associator: the associator, with each landmark's recent measurements.
        hist_sum: per landmark id, the sum of its measurements' colour histograms.
        open_stream: per robot, its session being associated (``"<robot>/<session>"``).
    """

    associator: Associator
    hist_sum: dict[int, F64]
    open_stream: dict[str, str]


class MapWriter:
    """Associates measured keyframes and keeps the object map in step (see the module docstring).

    Args:
        objects: the object map it writes.
        association: association settings (default: :class:`AssociationConfig`).
        hist_bins: ``MeasureConfig.hist_bins`` of the measurements' colour histograms
            (others are left out of the colour).
        knowledge: the knowledge graph (default: the packaged one).
        state: continue from this state (a checkpoint) instead of an empty map.
    """

    def __init__(
        self,
        objects: ObjectMap,
        association: AssociationConfig | None = None,
        *,
        hist_bins: tuple[int, int, int] = MeasureConfig().hist_bins,
        knowledge: KnowledgeGraph | None = None,
        state: WriterState | None = None,
    ) -> None:
        self.objects = objects
        self.hist_bins = hist_bins
        if state is None:
            config = association or AssociationConfig()
            kg = knowledge if knowledge is not None else KnowledgeGraph.load()
            # The database holds every measurement; the live associator only each landmark's recent ones.
            state = WriterState(Associator(replace(config, keep_measurements=False), kg), {}, {})
        self._associator = state.associator
        self._hist_sum = state.hist_sum
        self._open_stream = state.open_stream
        # Changes collected by associate(), waiting for write().
        self._touched: dict[int, Landmark] = {}
        self._new: dict[int, list[ObjectMeasurement]] = {}
        # Landmarks the associator merged into another, in order, waiting to be written.
        self._merges: list[tuple[int, int]] = []

    # ------------------------------------------------------------------ feeding

    def add(self, keyframes: Iterable[MappedKeyframe]) -> None:
        """Associate ``keyframes`` in order, then write the changes to the object map."""
        for kf in keyframes:
            self.associate(kf)
        self.write()

    def associate(self, keyframe: MappedKeyframe) -> int:
        """Associate one keyframe (first closing its robot's previous session, if another);
        the changes wait for :meth:`write`.

        Returns:
            How many of its measurements association left out for lying farther than
            ``AssociationConfig.max_range_m`` from the camera.
        """
        robot = keyframe.stream.split("/", 1)[0]
        previous = self._open_stream.get(robot)
        if previous is not None and previous != keyframe.stream:
            self._collect(self._associator.flush(previous))
        self._open_stream[robot] = keyframe.stream
        far = self._associator.beyond_range
        changes = self._associator.add_keyframe(
            for_association(keyframe.measurements), keyframe.T_map_camera, keyframe.camera,
            stream=keyframe.stream,
        )
        self._collect(changes)
        return self._associator.beyond_range - far

    def close(self, streams: Iterable[str]) -> None:
        """Associate the open, incomplete keyframe group of each stream (``"<robot>/<session>"``)
        and write the changes; each of those robots then has no open session."""
        for stream in streams:
            self._collect(self._associator.flush(stream))
            robot = stream.split("/", 1)[0]
            if self._open_stream.get(robot) == stream:
                del self._open_stream[robot]
        self.write()

    def write(self) -> None:
        """Upsert the landmarks changed since the last write (their latest state) with only the
        observations new to them, then delete the landmarks merged into others."""
        touched, new = self._touched, self._new
        self._touched, self._new = {}, {}
        states, observations = [], []
        for lm in touched.values():
            total = self._hist_sum.get(lm.id)
            colour = None if total is None else mean_rgb([total], self.hist_bins)
            state, obs = from_landmark(lm.id, lm.category, lm.confidence, lm.T_world_object, lm.size,
                                       new.get(lm.id, []), colour, lm.confirmed)
            states.append(state)
            observations.extend(obs)
        if states:
            self.objects.upsert(states, observations)
        merges, self._merges = self._merges, []
        for gone, into in merges:
            # After the upsert: ``into`` may be new. ``gone`` exists: it was written when created.
            self.objects.delete(gone, merged_into=into)

    # ------------------------------------------------------------------ reading

    def landmarks(self) -> list[Landmark]:
        """Snapshots of the associator's landmarks, by id."""
        return self._associator.landmarks()

    @property
    def open_streams(self) -> dict[str, str]:
        """Per robot, its session being associated (``"<robot>/<session>"``); a copy."""
        return dict(self._open_stream)

    def colour_sums(self) -> dict[int, F64]:
        """Per landmark id, the sum of its measurements' colour histograms; copies."""
        return {k: np.array(v, np.float64) for k, v in self._hist_sum.items()}

    def state(self) -> WriterState:
        """The association state (not a copy: take it while the writer is idle)."""
        return WriterState(self._associator, self._hist_sum, self._open_stream)

    # ------------------------------------------------------------------ internals

    def _collect(self, changes: Iterable[LandmarkChange]) -> None:
        """Take the measurements each change added and add their colour histograms to the
        landmark's running sum; note merged landmarks (:meth:`write` deletes them)."""
        bins = self.hist_bins
        for change in changes:
            lm = change.landmark
            if change.kind == "merged":
                gone = self._hist_sum.pop(lm.id, None)
                if gone is not None:
                    self._hist_sum[change.into] = self._hist_sum.get(change.into, 0.0) + gone
                self._merges.append((lm.id, change.into))
                continue
            hists = [np.asarray(m.color_hist, np.float64) for m in change.added
                     if np.shape(m.color_hist) == (bins[0] * bins[1] * bins[2],)]
            if hists:
                self._hist_sum[lm.id] = self._hist_sum.get(lm.id, 0.0) + np.sum(hists, axis=0)
            self._new.setdefault(lm.id, []).extend(change.added)
            self._touched[lm.id] = lm


def for_association(measurements: Sequence[ObjectMeasurement]) -> list[ObjectMeasurement]:
    """The measurements without their (H, W) masks and 3D points, for long-lived association
    state: association never reads either, and the points (up to ``MeasureConfig.max_points``,
    36 kB) were most of a measurement's memory. Both stay in the stored measurement."""
    return [replace(m, mask=np.zeros((0, 0), bool), points_camera=np.zeros((0, 3), np.float32))
            for m in measurements]
