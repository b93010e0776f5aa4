"""Procedural textures for the simulated hospital.

Every texture is an RGB uint8 image (S, S, 3), S = :data:`TEXTURE_SIZE`, drawn
deterministically from a seeded generator. They carry the corners and blobs that ORB
and SIFT need: tiles, posters with print, door numbers, signs, fabric weave.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
Img = NDArray[Any]  # a texture being drawn: float while noise is added, uint8 for cv2 text

TEXTURE_SIZE = 256
_WORDS = (
    "WARD",
    "EXIT",
    "ICU",
    "RADIOLOGY",
    "PHARMACY",
    "WASH HANDS",
    "QUIET",
    "NURSE",
    "STATION",
    "LAB",
    "X-RAY",
    "ONCOLOGY",
    "CARDIO",
    "STAFF ONLY",
    "LIFT",
    "STAIRS",
    "CLEAN",
    "OXYGEN",
    "FIRE",
    "MATERNITY",
    "THEATRE",
    "CAFE",
    "RECEPTION",
    "SURGERY",
)
_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX)


def _c(rgb: tuple[float, float, float] | NDArray[np.float64]) -> tuple[int, int, int]:
    """An RGB colour as the int tuple cv2 drawing wants."""
    return (int(rgb[0]), int(rgb[1]), int(rgb[2]))


def _noise(rng: np.random.Generator, amp: float, scale: int) -> Img:
    """Smooth value noise (S, S) in about [-amp, amp], feature size ``scale`` pixels."""
    n = max(2, TEXTURE_SIZE // scale)
    coarse = rng.uniform(-amp, amp, size=(n, n)).astype(np.float32)
    tiled = np.tile(coarse, (2, 2))  # wrap-around so the texture repeats seamlessly
    big = cv2.resize(tiled, (2 * TEXTURE_SIZE, 2 * TEXTURE_SIZE), interpolation=cv2.INTER_CUBIC)
    h = TEXTURE_SIZE // 2
    return big[h : h + TEXTURE_SIZE, h : h + TEXTURE_SIZE]


def _base(color: tuple[int, int, int] | NDArray[np.float64]) -> Img:
    img = np.empty((TEXTURE_SIZE, TEXTURE_SIZE, 3), np.float32)
    img[:] = np.asarray(color, np.float32)
    return img


def _u8(img: Img) -> U8:
    """Clip to 0..255 as uint8 (cv2 draws text only on 8-bit images)."""
    return np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8))


def _finish(img: Img, blur: float = 0.7) -> U8:
    out = _u8(np.asarray(img, np.float32))
    if blur > 0:
        return _u8(cv2.GaussianBlur(out, (0, 0), blur, borderType=cv2.BORDER_REFLECT))
    return out


def _text(
    img: Img,
    text: str,
    org: tuple[int, int],
    scale: float,
    color: tuple[int, int, int],
    thick: int,
    font: int = cv2.FONT_HERSHEY_DUPLEX,
) -> None:
    cv2.putText(img, text, org, font, scale, color, thick, cv2.LINE_AA)


def speckled(
    rng: np.random.Generator,
    color: tuple[int, int, int],
    *,
    speckle: int = 900,
    grid: int = 0,
    grout: tuple[int, int, int] = (150, 150, 150),
    amp: float = 14.0,
) -> U8:
    """Terrazzo-like floor or wall: base colour, cloudy noise, speckles, optional tile grid."""
    img = _base(color) + _noise(rng, amp, 32)[..., None]
    img = _u8(img)
    for _ in range(speckle):
        x, y = rng.integers(0, TEXTURE_SIZE, size=2)
        r = int(rng.integers(1, 4))
        shade = rng.uniform(-90, 70)
        col = np.clip(np.asarray(color, np.float64) + shade + rng.uniform(-25, 25, 3), 0, 255)
        cv2.circle(img, (int(x), int(y)), r, _c(col), -1, cv2.LINE_AA)
    if grid:
        for k in range(0, TEXTURE_SIZE, TEXTURE_SIZE // grid):
            cv2.line(img, (k, 0), (k, TEXTURE_SIZE), _c(grout), 3)
            cv2.line(img, (0, k), (TEXTURE_SIZE, k), _c(grout), 3)
    return _finish(img)


def painted_wall(rng: np.random.Generator, color: tuple[int, int, int]) -> U8:
    """Painted plaster: soft noise, scuffs and small marks (fixtures, pins, stains)."""
    img = _base(color) + _noise(rng, 10.0, 24)[..., None] + _noise(rng, 6.0, 6)[..., None]
    img = _u8(img)
    for _ in range(40):
        x, y = (int(v) for v in rng.integers(0, TEXTURE_SIZE, size=2))
        kind = rng.integers(0, 3)
        col = _c(np.clip(np.asarray(color, np.float64) * rng.uniform(0.45, 0.85), 0, 255))
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(1, 4)), col, -1, cv2.LINE_AA)
        elif kind == 1:
            dx, dy = (int(v) for v in rng.integers(-14, 15, size=2))
            cv2.line(img, (x, y), (x + dx, y + dy), col, 1, cv2.LINE_AA)
        else:
            w, h = (int(v) for v in rng.integers(3, 10, size=2))
            cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
    return _finish(img)


def ceiling_tiles(rng: np.random.Generator) -> U8:
    """Acoustic ceiling tiles with perforation dots and a metal grid."""
    img = _base((226, 226, 220)) + _noise(rng, 6.0, 16)[..., None]
    img = _u8(img)
    for _ in range(700):
        x, y = (int(v) for v in rng.integers(0, TEXTURE_SIZE, size=2))
        cv2.circle(img, (x, y), 1, (150, 150, 145), -1)
    for k in (0, TEXTURE_SIZE // 2):
        cv2.line(img, (k, 0), (k, TEXTURE_SIZE), (180, 180, 185), 4)
        cv2.line(img, (0, k), (TEXTURE_SIZE, k), (180, 180, 185), 4)
    return _finish(img)


def poster(rng: np.random.Generator) -> U8:
    """A poster: coloured shapes, a headline and lines of small print."""
    bg = rng.uniform(150, 250, 3)
    img = _base(_c(bg))
    img = _u8(img)
    for _ in range(int(rng.integers(5, 11))):
        col = _c(rng.uniform(0, 255, 3))
        x, y = (int(v) for v in rng.integers(10, TEXTURE_SIZE - 10, size=2))
        r = int(rng.integers(8, 50))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), r, col, -1, cv2.LINE_AA)
        else:
            cv2.rectangle(img, (x - r, y - r // 2), (x + r, y + r // 2), col, -1)
    dark = _c(rng.uniform(0, 70, 3))
    _text(img, str(rng.choice(_WORDS)), (12, 52), 1.1, dark, 3, _FONTS[int(rng.integers(0, 3))])
    for k in range(6):
        words = " ".join(str(w).lower() for w in rng.choice(_WORDS, size=3))
        _text(img, words, (12, 120 + 20 * k), 0.5, dark, 1, cv2.FONT_HERSHEY_SIMPLEX)
    cv2.rectangle(img, (2, 2), (TEXTURE_SIZE - 3, TEXTURE_SIZE - 3), dark, 4)
    return _finish(img, 0.6)


def sign(rng: np.random.Generator, text: str, bg: tuple[int, int, int], fg: tuple[int, int, int]) -> U8:
    """A wall sign with one or two lines of bold text and an arrow."""
    img = _base(bg)
    img = _u8(img)
    lines = text.split("\n")
    for k, line in enumerate(lines):
        scale = min(1.6, 200.0 / max(1, 22 * len(line)))
        _text(img, line, (14, 90 + 70 * k), scale, fg, 3)
    y = 220
    cv2.arrowedLine(img, (40, y), (200 if rng.random() < 0.5 else 20, y), fg, 8, cv2.LINE_AA, 0, 0.3)
    cv2.rectangle(img, (4, 4), (TEXTURE_SIZE - 5, TEXTURE_SIZE - 5), fg, 5)
    return _finish(img, 0.6)


def door(rng: np.random.Generator, color: tuple[int, int, int], number: str) -> U8:
    """A door leaf mapped onto the whole texture: panel, wired glass window, plate, kick plate."""
    img = _base(color) + _noise(rng, 8.0, 12)[..., None]
    img = _u8(img)
    for k in range(0, TEXTURE_SIZE, 6):  # wood grain / laminate lines
        shade = _c(np.clip(np.asarray(color, np.float64) * rng.uniform(0.82, 0.97), 0, 255))
        cv2.line(img, (k, 0), (k + int(rng.integers(-3, 4)), TEXTURE_SIZE), shade, 1)
    cv2.rectangle(img, (80, 28), (176, 100), (70, 80, 90), -1)
    for k in range(84, 176, 12):
        cv2.line(img, (k, 28), (k, 100), (150, 160, 170), 1)
        cv2.line(img, (80, k - 56), (176, k - 56), (150, 160, 170), 1)
    cv2.rectangle(img, (80, 28), (176, 100), (40, 40, 40), 3)
    cv2.rectangle(img, (96, 110), (160, 134), (245, 245, 245), -1)
    _text(img, number, (100, 130), 0.7, (20, 20, 120), 2)
    cv2.rectangle(img, (12, 222), (244, 250), (180, 180, 185), -1)
    cv2.rectangle(img, (200, 140), (240, 150), (200, 200, 200), -1)
    cv2.circle(img, (206, 145), 7, (120, 120, 120), -1, cv2.LINE_AA)
    cv2.rectangle(img, (0, 0), (TEXTURE_SIZE - 1, TEXTURE_SIZE - 1), (60, 60, 60), 4)
    return _finish(img, 0.6)


def fabric(rng: np.random.Generator, color: tuple[int, int, int], *, pattern: bool = False) -> U8:
    """Woven fabric; with ``pattern`` a printed check or dot pattern (sheets, clothes)."""
    yy, xx = np.mgrid[0:TEXTURE_SIZE, 0:TEXTURE_SIZE]
    weave = (6.0 * np.sin(xx * 1.6) * np.sin(yy * 1.6)).astype(np.float32)
    img = _u8(_base(color) + _noise(rng, 12.0, 16)[..., None] + weave[..., None])
    if pattern:
        col = _c(np.clip(np.asarray(color, np.float64) * rng.uniform(0.4, 0.7), 0, 255))
        step = int(rng.integers(24, 48))
        if rng.random() < 0.5:
            for k in range(0, TEXTURE_SIZE, step):
                cv2.line(img, (k, 0), (k, TEXTURE_SIZE), col, 4)
                cv2.line(img, (0, k), (TEXTURE_SIZE, k), col, 4)
        else:
            for y in range(step // 2, TEXTURE_SIZE, step):
                for x in range(step // 2, TEXTURE_SIZE, step):
                    cv2.circle(img, (x, y), step // 5, col, -1, cv2.LINE_AA)
    return _finish(img)


def panelled(rng: np.random.Generator, color: tuple[int, int, int], rows: int, cols: int) -> U8:
    """Cabinet or cart front: a grid of panels with handles and a label."""
    img = _base(color) + _noise(rng, 6.0, 16)[..., None]
    img = _u8(img)
    dark = _c(np.clip(np.asarray(color, np.float64) * 0.5, 0, 255))
    h, w = TEXTURE_SIZE // rows, TEXTURE_SIZE // cols
    for r in range(rows):
        for c in range(cols):
            x0, y0 = c * w + 4, r * h + 4
            cv2.rectangle(img, (x0, y0), (x0 + w - 8, y0 + h - 8), dark, 2)
            cx = x0 + w // 2 - 4
            cv2.rectangle(img, (cx - 14, y0 + 10), (cx + 14, y0 + 16), (90, 90, 95), -1)
    x, y = (int(v) for v in rng.integers(20, TEXTURE_SIZE - 60, size=2))
    cv2.rectangle(img, (x, y), (x + 40, y + 16), (250, 250, 250), -1)
    _text(img, str(int(rng.integers(10, 99))), (x + 4, y + 13), 0.45, (0, 0, 0), 1)
    return _finish(img)


def metal(rng: np.random.Generator, color: tuple[int, int, int] = (170, 172, 178)) -> U8:
    """Brushed metal: streaks along one axis and a few bolts."""
    img = _base(color)
    streak = rng.uniform(-18, 18, size=(TEXTURE_SIZE, 1)).astype(np.float32)
    img = _u8(img + cv2.GaussianBlur(np.repeat(streak, TEXTURE_SIZE, axis=1), (0, 0), 1.0)[..., None])
    for _ in range(8):
        x, y = (int(v) for v in rng.integers(8, TEXTURE_SIZE - 8, size=2))
        cv2.circle(img, (x, y), 4, (90, 90, 95), -1, cv2.LINE_AA)
    return _finish(img)


def screen(rng: np.random.Generator) -> U8:
    """A patient monitor: dark glass, vital-sign traces, numbers."""
    img = _base((12, 14, 18))
    img = _u8(img)
    cols = ((60, 230, 90), (240, 220, 60), (90, 200, 250), (250, 80, 80))
    for k, col in enumerate(cols):
        y0 = 30 + 55 * k
        pts = [
            (x, int(y0 + 14 * np.sin(x * rng.uniform(0.05, 0.2)) * (1 + (x % 40 < 4) * 2)))
            for x in range(10, 170, 3)
        ]
        cv2.polylines(img, [np.array(pts, np.int32)], False, col, 2, cv2.LINE_AA)
        _text(img, str(int(rng.integers(40, 140))), (180, y0 + 12), 1.0, col, 2)
    cv2.rectangle(img, (0, 0), (TEXTURE_SIZE - 1, TEXTURE_SIZE - 1), (50, 50, 55), 8)
    return _finish(img, 0.5)


def skin_face(rng: np.random.Generator, tone: tuple[int, int, int]) -> U8:
    """Skin with a simple face (eyes, brows, mouth) so heads have features."""
    img = _base(tone) + _noise(rng, 6.0, 32)[..., None]
    img = _u8(img)
    dark = _c(np.asarray(tone, np.float64) * 0.35)
    cv2.circle(img, (90, 110), 12, (250, 250, 250), -1)
    cv2.circle(img, (166, 110), 12, (250, 250, 250), -1)
    cv2.circle(img, (90, 110), 6, dark, -1)
    cv2.circle(img, (166, 110), 6, dark, -1)
    cv2.line(img, (72, 88), (108, 84), dark, 4)
    cv2.line(img, (148, 84), (184, 88), dark, 4)
    cv2.ellipse(img, (128, 180), (34, 12), 0, 0, 180, dark, 4)
    return _finish(img)


def hair(rng: np.random.Generator, color: tuple[int, int, int]) -> U8:
    img = _base(color) + _noise(rng, 20.0, 8)[..., None]
    img = _u8(img)
    for _ in range(150):
        x, y = (int(v) for v in rng.integers(0, TEXTURE_SIZE, size=2))
        cv2.line(img, (x, y), (x + int(rng.integers(-6, 7)), y + 20), _c(np.asarray(color) * 0.6), 1)
    return _finish(img)


def scrubs(rng: np.random.Generator, color: tuple[int, int, int]) -> U8:
    """Staff scrubs: fabric with a pocket, a badge and seams."""
    img = fabric(rng, color).copy()
    dark = _c(np.asarray(color, np.float64) * 0.6)
    cv2.rectangle(img, (40, 60), (100, 120), dark, 3)
    cv2.rectangle(img, (150, 50), (200, 80), (245, 245, 245), -1)
    _text(img, "RN", (156, 74), 0.7, (20, 20, 160), 2)
    cv2.line(img, (128, 0), (128, TEXTURE_SIZE), dark, 2)
    return _finish(img, 0.5)


class TextureBank:
    """Named textures of one world, in insertion order (the order fixes texture ids)."""

    def __init__(self) -> None:
        self._names: dict[str, int] = {}
        self._images: list[U8] = []

    def add(self, name: str, image: U8) -> int:
        """Store ``image`` (S, S, 3) RGB under ``name``; returns its id. Names are unique."""
        if name in self._names:
            raise ValueError(f"texture {name!r} already exists")
        if image.shape != (TEXTURE_SIZE, TEXTURE_SIZE, 3) or image.dtype != np.uint8:
            raise ValueError(f"texture {name!r}: expected uint8 {TEXTURE_SIZE}x{TEXTURE_SIZE}x3")
        self._names[name] = len(self._images)
        self._images.append(image)
        return self._names[name]

    def id(self, name: str) -> int:
        return self._names[name]

    def __contains__(self, name: str) -> bool:
        return name in self._names

    def __len__(self) -> int:
        return len(self._images)

    def stack(self) -> U8:
        """All textures as one array (n, S, S, 3)."""
        return np.stack(self._images)
