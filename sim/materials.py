"""Materials of the simulated hospital: how a surface looks to each sensor.

Temperatures follow paper 003's thermal set-up (people ~34 C, monitors warm, walls
ambient). ``thermal_contrast_k`` scales the texture's grey level into a temperature
variation (emissivity differences of paint, print and fabric), which gives thermal
images the structure SIFT needs. ``depth_dropout`` is the probability that a pixel of
this material has no depth (dark or specular surfaces defeat the depth sensor).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Material:
    """One surface material.

    Attributes:
        name: unique name.
        temperature_c: mean surface temperature in degrees Celsius.
        thermal_contrast_k: kelvin per unit texture grey level (grey in 0..1, centred at 0.5).
        depth_dropout: probability 0..1 that a pixel of this material has no depth.
        emissive: glows by itself (screens, signs): visible in RGB when the lights are off.
    """

    name: str
    temperature_c: float
    thermal_contrast_k: float
    depth_dropout: float = 0.0
    emissive: bool = False


MATERIALS: tuple[Material, ...] = (
    Material("none", 21.0, 0.0),
    Material("wall", 22.0, 2.5),
    Material("floor", 21.0, 3.0),
    Material("ceiling", 23.5, 2.0),
    Material("ceiling_light", 38.0, 4.0, emissive=True),
    Material("poster", 22.2, 4.0),
    Material("sign", 22.5, 2.0, emissive=True),
    Material("door", 21.5, 3.0),
    Material("wood", 21.8, 2.5),
    Material("fabric", 23.0, 1.5),
    Material("plastic", 22.0, 2.0),
    Material("metal", 21.0, 1.0, depth_dropout=0.25),
    Material("black_plastic", 22.5, 0.8, depth_dropout=0.5),
    Material("screen", 36.0, 3.0, depth_dropout=0.9, emissive=True),
    Material("ceramic", 20.5, 1.0, depth_dropout=0.1),
    Material("skin", 34.0, 1.5),
    Material("clothing", 30.5, 2.0),
    Material("hair", 31.0, 1.0, depth_dropout=0.2),
    Material("radiator", 45.0, 4.0),
    Material("glass", 20.0, 0.5, depth_dropout=0.7),
)

MATERIAL_INDEX: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}


def material_id(name: str) -> int:
    """Index of a material by name (KeyError names the unknown material)."""
    try:
        return MATERIAL_INDEX[name]
    except KeyError:
        raise KeyError(f"unknown material {name!r}; known: {', '.join(MATERIAL_INDEX)}") from None
