"""Box models of the knowledge graph's classes and of people.

A model is a tuple of :class:`~wardmap.sim.geometry.Part` in the model frame:
x forward (the side a user faces), y left, z up, origin on the floor under the model's
footprint centre. Texture names refer to the world's texture bank; the world builder
creates per-model texture variants (``bed_sheet``, ``door_<n>``, ...).
"""

from __future__ import annotations

import numpy as np

from wardmap.sim.geometry import Part


def bed(sheet: str) -> tuple[Part, ...]:
    """Hospital bed, long side along y: frame, mattress, pillow, head and foot boards, rails."""
    return (
        Part((0, 0, 0.25), (0.95, 2.0, 0.3), "bed_frame", "metal", 200.0),
        Part((0, 0, 0.48), (0.9, 1.95, 0.16), sheet, "fabric"),
        Part((0, 0.75, 0.6), (0.6, 0.35, 0.1), "pillow", "fabric"),
        Part((0, 1.0, 0.55), (0.95, 0.05, 0.9), "bed_board", "plastic"),
        Part((0, -1.0, 0.45), (0.95, 0.05, 0.6), "bed_board", "plastic"),
        Part((0.47, 0.2, 0.7), (0.03, 1.0, 0.2), "bed_frame", "metal", 200.0),
        Part((0, 0, 0.05), (0.7, 1.7, 0.1), "black", "black_plastic"),
    )


def chair(seat: str) -> tuple[Part, ...]:
    """Visitor chair facing +x: seat, back, four legs."""
    legs = tuple(
        Part((sx * 0.19, sy * 0.19, 0.22), (0.04, 0.04, 0.44), "chrome", "metal", 300.0)
        for sx in (-1, 1)
        for sy in (-1, 1)
    )
    return (
        Part((0, 0, 0.46), (0.46, 0.46, 0.06), seat, "fabric"),
        Part((-0.21, 0, 0.72), (0.05, 0.46, 0.42), seat, "fabric"),
        *legs,
    )


def wheelchair() -> tuple[Part, ...]:
    """Wheelchair facing +x: seat, back, two large wheels, footrest, push handles."""
    return (
        Part((0, 0, 0.5), (0.45, 0.45, 0.05), "wheelchair_seat", "fabric"),
        Part((-0.22, 0, 0.75), (0.04, 0.45, 0.45), "wheelchair_seat", "fabric"),
        Part((-0.05, 0.29, 0.3), (0.6, 0.04, 0.6), "wheel", "black_plastic"),
        Part((-0.05, -0.29, 0.3), (0.6, 0.04, 0.6), "wheel", "black_plastic"),
        Part((0.32, 0, 0.1), (0.15, 0.35, 0.03), "chrome", "metal", 300.0),
        Part((-0.28, 0.2, 0.95), (0.12, 0.03, 0.03), "black", "black_plastic"),
        Part((-0.28, -0.2, 0.95), (0.12, 0.03, 0.03), "black", "black_plastic"),
    )


def cart(front: str) -> tuple[Part, ...]:
    """Medical cart with drawers, a top tray and a push handle at -x."""
    return (
        Part((0, 0, 0.5), (0.5, 0.75, 0.8), front, "plastic"),
        Part((0, 0, 0.93), (0.55, 0.8, 0.05), "tray", "plastic", 400.0),
        Part((-0.3, 0, 0.95), (0.03, 0.5, 0.03), "chrome", "metal", 300.0),
        Part((0, 0, 0.05), (0.45, 0.7, 0.1), "black", "black_plastic"),
    )


def iv_pole() -> tuple[Part, ...]:
    """IV pole: wheeled base, tall pole, hook and a fluid bag."""
    return (
        Part((0, 0, 0.04), (0.5, 0.5, 0.06), "chrome", "metal", 300.0),
        Part((0, 0, 1.0), (0.03, 0.03, 1.9), "chrome", "metal", 300.0),
        Part((0, 0, 1.93), (0.03, 0.3, 0.03), "chrome", "metal", 300.0),
        Part((0, 0.12, 1.72), (0.05, 0.13, 0.25), "iv_bag", "plastic"),
    )


def temperature_gun() -> tuple[Part, ...]:
    """Hand-held infrared thermometer: body along +x and a grip."""
    return (
        Part((0.0, 0, 0.1), (0.16, 0.04, 0.05), "gun", "plastic"),
        Part((-0.05, 0, 0.04), (0.04, 0.035, 0.09), "gun", "plastic"),
    )


def cup() -> tuple[Part, ...]:
    return (Part((0, 0, 0.05), (0.08, 0.08, 0.1), "cup", "ceramic"),)


def cabinet(front: str) -> tuple[Part, ...]:
    """Tall storage cabinet, doors facing +x."""
    return (Part((0, 0, 0.95), (0.5, 1.0, 1.9), front, "wood"),)


def wall_monitor(screen: str) -> tuple[Part, ...]:
    """Wall-mounted patient monitor facing +x, its screen 1.4-1.9 m above the floor."""
    return (
        Part((0.04, 0, 1.65), (0.03, 0.62, 0.42), screen, "screen"),
        Part((0.0, 0, 1.65), (0.05, 0.68, 0.48), "black", "black_plastic"),
    )


def sink() -> tuple[Part, ...]:
    """Wall sink facing +x: basin, pedestal, tap."""
    return (
        Part((0.05, 0, 0.8), (0.45, 0.6, 0.18), "ceramic", "ceramic", 500.0),
        Part((-0.05, 0, 0.38), (0.2, 0.25, 0.7), "ceramic", "ceramic", 500.0),
        Part((-0.12, 0, 0.98), (0.12, 0.04, 0.18), "chrome", "metal", 300.0),
    )


def desk(front: str) -> tuple[Part, ...]:
    """Nurse-station counter facing +x, with a raised front panel."""
    return (
        Part((0, 0, 0.37), (0.75, 2.4, 0.74), front, "wood"),
        Part((0, 0, 0.76), (0.8, 2.45, 0.04), "desk_top", "wood", 300.0),
        Part((0.36, 0, 0.92), (0.06, 2.45, 0.28), front, "wood"),
    )


def door(leaf: str) -> tuple[Part, ...]:
    """A door in a wall, facing +x: the leaf (1.0 x 2.1 m) and its frame."""
    return (
        Part((0.02, 0, 1.05), (0.04, 1.0, 2.1), leaf, "door"),
        Part((0.03, 0.54, 1.08), (0.06, 0.08, 2.16), "door_frame", "metal", 300.0),
        Part((0.03, -0.54, 1.08), (0.06, 0.08, 2.16), "door_frame", "metal", 300.0),
        Part((0.03, 0, 2.14), (0.06, 1.16, 0.08), "door_frame", "metal", 300.0),
    )


def person(
    outfit: str, face: str, hair: str, phase: float, *, height: float = 1.75, arms_forward: bool = False
) -> tuple[Part, ...]:
    """A person facing +x at walk phase ``phase`` (radians): legs and arms swing.

    ``arms_forward`` holds both forearms out (pushing a cart or carrying something).
    """
    k = height / 1.75
    swing = 0.45 * np.sin(phase)
    leg_len, hip = 0.85 * k, 0.86 * k
    parts = []
    for side, sgn in ((0.1, 1.0), (-0.1, -1.0)):
        a = sgn * swing
        cx = -np.sin(a) * leg_len / 2
        parts.append(
            Part(
                (cx, side, hip - np.cos(a) * leg_len / 2),
                (0.13, 0.13, leg_len),
                outfit,
                "clothing",
                0.0,
                0.0,
                -a,
            )
        )
    parts.append(Part((0, 0, hip + 0.3 * k), (0.24, 0.42, 0.6 * k), outfit, "clothing"))
    parts.append(Part((0, 0, hip + 0.72 * k), (0.22, 0.19, 0.24 * k), face, "skin"))
    parts.append(Part((-0.03, 0, hip + 0.86 * k), (0.2, 0.2, 0.06), hair, "hair"))
    arm_len = 0.62 * k
    for side, sgn in ((0.27, -1.0), (-0.27, 1.0)):
        if arms_forward:
            parts.append(Part((0.2, side, hip + 0.38 * k), (0.42, 0.1, 0.1), outfit, "clothing"))
        else:
            a = sgn * swing
            parts.append(
                Part(
                    (-np.sin(a) * arm_len / 2, side, hip + 0.55 * k - np.cos(a) * arm_len / 2),
                    (0.1, 0.1, arm_len),
                    outfit,
                    "clothing",
                    0.0,
                    0.0,
                    -a,
                )
            )
    return tuple(parts)
