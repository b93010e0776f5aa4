"""Known RGB-D sensors' colour shutters, and which rolling-shutter readout time a recording uses.

A recording's readout time (first row to last, seconds) comes, in this order, from its
calibration (``[rgb] readout_s``, e.g. written by ``wardmap calibrate-readout``), from the
default of the sensor it names (``[rgb] sensor``, or a TUM RGB-D folder's name), or is
unknown. An unknown readout is treated as a global shutter until the tracker estimates it from
turning frames (``wardmap.edge.readout.OnlineReadout``), and :func:`readout_model` says so:
nothing downstream assumes a global shutter silently.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final


@dataclass(frozen=True)
class Sensor:
    """A colour camera model.

    Attributes:
        description: the product, for messages.
        rolling: the colour camera exposes its rows one after the other.
        readout_s: first-row-to-last readout time, seconds (0 for a global shutter); None
            for a rolling shutter whose readout time is not known here.
        origin: where ``readout_s`` comes from.
    """

    description: str
    rolling: bool
    readout_s: float | None
    origin: str


SENSORS: Final[Mapping[str, Sensor]] = MappingProxyType({
    "kinect_v1": Sensor(
        "Kinect v1 (PrimeSense; the TUM RGB-D fr1-fr3 sequences)", True, 0.0266,
        "wardmap calibrate-readout on the full TUM fr1/rpy recording (issue 41)",
    ),
    "realsense_d415": Sensor("Intel RealSense D415 colour", True, None, ""),
    "realsense_d435": Sensor("Intel RealSense D435/D435i colour", True, None, ""),
    "realsense_d455": Sensor("Intel RealSense D455 colour", False, 0.0, "global shutter"),
    "azure_kinect": Sensor("Azure Kinect DK colour", True, None, ""),
    "orbbec_femto_bolt": Sensor("Orbbec Femto Bolt colour", True, None, ""),
    "orbbec_astra": Sensor("Orbbec Astra colour", True, None, ""),
    "global_shutter": Sensor("a global-shutter colour camera", False, 0.0, "global shutter"),
})
"""Colour cameras by the name a calibration's ``[rgb] sensor`` gives."""

TUM_SENSOR: Final = "kinect_v1"
"""The sensor of a TUM RGB-D folder recognised by its name (``freiburg1``..``3``)."""


@dataclass(frozen=True)
class ReadoutModel:
    """The readout time a recording is tracked with, and why.

    Attributes:
        readout_s: seconds, first row to last (0 = global shutter).
        source: where it comes from, in words (for ``track`` and ``dataset info``).
        assumed: no calibration or known sensor gives it: 0 is a guess.
    """

    readout_s: float
    source: str
    assumed: bool


def readout_model(readout_s: float | None, sensor: str) -> ReadoutModel:
    """The readout time from a calibration's ``[rgb] readout_s`` (None = not given) and
    ``[rgb] sensor`` (a :data:`SENSORS` key, or "" for none); see the module docstring.

    Raises:
        KeyError: ``sensor`` is not a :data:`SENSORS` key (calibrations check it on load).
    """
    if readout_s is not None:
        return ReadoutModel(readout_s, "the calibration's [rgb] readout_s", False)
    if sensor:
        known = SENSORS[sensor]
        if known.readout_s is not None:
            return ReadoutModel(known.readout_s, f"default for {known.description} ({known.origin})", False)
        return ReadoutModel(
            0.0,
            f"{known.description} has a rolling shutter of unknown readout time: tracked as a "
            "global shutter until estimated online from turning frames (or run wardmap "
            "calibrate-readout and set [rgb] readout_s)",
            True,
        )
    return ReadoutModel(
        0.0,
        "no readout information (no [rgb] readout_s or sensor): tracked as a global shutter "
        "until estimated online from turning frames (or run wardmap calibrate-readout)",
        True,
    )


__all__ = ["SENSORS", "TUM_SENSOR", "ReadoutModel", "Sensor", "readout_model"]
