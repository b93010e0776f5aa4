"""A site's own labelled images for ``wardmap train-seg`` (fine-tuning on real cameras).

Pure numpy/OpenCV (and pycocotools for COCO masks); no torch. Three sources, each optional
(``[train_seg.site]``, :class:`SiteDataConfig`):

- **COCO-style JSON** (``coco_json``, images under ``coco_images``, default the JSON's folder):
  ``images`` ``{id, file_name, width, height}``, ``annotations`` ``{image_id, category_id,
  segmentation, iscrowd?}`` with polygons or RLE (compressed or not), ``categories`` ``{id,
  name}``. Annotations are painted largest first, so an object on another keeps its pixels;
  pixels under no annotation are background. Images without annotations are negatives.
- **Mask PNGs** (``mask_dir``, the "Segmentation mask 1.1" export of CVAT, also what
  LabelMe's ``labelme2voc`` writes): ``labelmap.txt`` (``name:r,g,b:...`` per line, ``#``
  comments), ``SegmentationClass/<stem>.png`` (one colour per class) and the image
  ``JPEGImages/<stem>.jpg|.png``. A colour missing from the label map fails with one line.
- **Negatives** (``negatives_dir``): photographs with no hospital object in them (an office,
  a corridor of another building), every pixel background, so real scenes without hospital
  objects stay background.

Site class names become our classes by ``class_map`` (``[[site name, our name]], ...``; our
name may be ``background`` or ``ignore``, pixels the loss skips); names that are our classes
already (case and spaces aside: ``IV pole`` -> ``iv_pole``) map to themselves. Any other name
fails with one line naming it.

Depth: the packaged network is RGB-D (decision 0020). With ``depth_dir`` a 16-bit PNG of depth
in millimetres named like the image (``<stem>.png``) is used; without it depth is 0, "no data"
in the ONNX contract, for every pixel: the network learns the site images from colour alone.
Images are area-resized to the network input (``width`` x ``height`` of the data config;
labels nearest), so a 4:3 camera keeps its shape at 320x240.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.tools.training.segdata import IGNORE_INDEX, SegSamples, SiteDataConfig, TrainingError

__all__ = ["SiteDataConfig", "check_site_paths", "load_site_samples", "site_class_lut"]

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]
IMAGE_SUFFIXES: Final = (".jpg", ".jpeg", ".png", ".bmp")
SITE_WORLD: Final = -1
"""``SegSamples.world`` of site images (simulated worlds count from 0)."""


def _key(name: str) -> str:
    return "_".join(name.strip().lower().replace("-", " ").split())


def site_class_lut(site_names: list[str], names: tuple[str, ...], class_map: tuple[tuple[str, str], ...],
                   where: str) -> dict[str, int]:
    """Site class name -> our class index (``IGNORE_INDEX`` for ``ignore``).

    Raises:
        TrainingError: a site name with no class, or a ``class_map`` target that is none of ours.
    """
    ours = {n: i for i, n in enumerate(names)}
    ours["ignore"] = IGNORE_INDEX
    explicit = {_key(a): b for a, b in class_map}
    bad = sorted({b for b in explicit.values() if b not in ours})
    if bad:
        raise TrainingError(f"[train_seg.site] class_map maps to {', '.join(bad)}, not our classes; use "
                            f"one of {', '.join(ours)}")
    lut: dict[str, int] = {}
    unknown = []
    for name in site_names:
        target = explicit.get(_key(name), _key(name))
        if target not in ours:
            unknown.append(name)
        else:
            lut[name] = ours[target]
    if unknown:
        raise TrainingError(f"{where}: class(es) {', '.join(map(repr, unknown))} are none of ours; map "
                            f"them in [train_seg.site] class_map (to a class, background or ignore)")
    return lut


def _read_image(path: Path) -> U8:
    """RGB uint8 (H, W, 3) of an image file; TrainingError naming it when unreadable."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise TrainingError(f"cannot read image {path}")
    return np.ascontiguousarray(bgr[..., ::-1])


def _depth_for(cfg: SiteDataConfig, stem: str, shape: tuple[int, int]) -> U16:
    """Depth in millimetres (H, W) of image ``stem``, zeros without one."""
    if cfg.depth_dir:
        path = Path(cfg.depth_dir) / f"{stem}.png"
        if path.is_file():
            depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.dtype != np.uint16 or depth.shape != shape:
                raise TrainingError(f"{path}: expected a 16-bit depth PNG in millimetres of size "
                                    f"{shape[1]}x{shape[0]}")
            return np.asarray(depth, np.uint16)
    return np.zeros(shape, np.uint16)


def _resized(rgb: U8, classes: U8, depth: U16, width: int, height: int) -> tuple[U8, U8, U16]:
    if rgb.shape[:2] == (height, width):
        return rgb, classes, depth
    return (
        np.asarray(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA), np.uint8),
        np.asarray(cv2.resize(classes, (width, height), interpolation=cv2.INTER_NEAREST), np.uint8),
        np.asarray(cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST), np.uint16),
    )


def _coco_masks(path: Path, names: tuple[str, ...], cfg: SiteDataConfig) -> list[tuple[str, U8, U8]]:
    """``(stem, rgb, classes)`` of every image of a COCO-style file."""
    try:
        from pycocotools import mask as coco_mask
    except ImportError as exc:
        raise TrainingError("COCO labels need pycocotools: pip install -e '.[train]'") from exc
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        images = {int(im["id"]): im for im in doc["images"]}
        categories = {int(c["id"]): str(c["name"]) for c in doc["categories"]}
        annotations = list(doc.get("annotations", []))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TrainingError(f"{path}: not a COCO-style instances file ({exc})") from exc
    lut = site_class_lut(sorted(set(categories.values())), names, cfg.class_map, str(path))
    folder = Path(cfg.coco_images) if cfg.coco_images else path.parent
    by_image: dict[int, list[dict[str, Any]]] = {i: [] for i in images}
    for k, ann in enumerate(annotations):
        if ann.get("image_id") not in by_image or ann.get("category_id") not in categories:
            raise TrainingError(f"{path}: annotation {k} names an unknown image or category")
        by_image[ann["image_id"]].append(ann)
    out = []
    for image_id, im in images.items():
        rgb = _read_image(folder / im["file_name"])
        h, w = rgb.shape[:2]
        if (int(im.get("height", h)), int(im.get("width", w))) != (h, w):
            raise TrainingError(f"{path}: image {im['file_name']} is {w}x{h}, the file says "
                                f"{im.get('width')}x{im.get('height')}")
        classes = np.zeros((h, w), np.uint8)
        painted = []
        for ann in by_image[image_id]:
            seg = ann.get("segmentation")
            try:
                if isinstance(seg, list):  # polygons [[x, y, x, y, ...], ...]
                    rle = coco_mask.merge(coco_mask.frPyObjects(seg, h, w))
                elif isinstance(seg, dict) and isinstance(seg.get("counts"), list):  # uncompressed RLE
                    rle = coco_mask.frPyObjects(seg, h, w)
                elif isinstance(seg, dict):  # compressed RLE
                    rle = dict(seg)
                    if isinstance(rle["counts"], str):
                        rle["counts"] = rle["counts"].encode("ascii")
                else:
                    raise TypeError(f"segmentation is neither polygons nor RLE: {type(seg).__name__}")
                with warnings.catch_warnings():  # pycocotools 2.0 on numpy 2: a copy= deprecation
                    warnings.simplefilter("ignore", DeprecationWarning)
                    mask = coco_mask.decode(rle).astype(bool)
            except (TypeError, ValueError, KeyError, IndexError) as exc:
                raise TrainingError(
                    f"{path}: annotation of image {im['file_name']}: bad segmentation ({exc})"
                ) from exc
            if mask.shape != (h, w):
                raise TrainingError(
                    f"{path}: a mask of image {im['file_name']} is {mask.shape}, not {(h, w)}"
                )
            painted.append((int(mask.sum()), lut[categories[ann["category_id"]]], mask))
        for _, index, mask in sorted(painted, key=lambda item: -item[0]):  # largest first
            classes[mask] = index
        out.append((Path(im["file_name"]).stem, rgb, classes))
    return out


def _labelmap(path: Path) -> dict[tuple[int, int, int], str]:
    """RGB colour -> class name of a CVAT ``labelmap.txt`` (``name:r,g,b:parts:actions``)."""
    colours: dict[tuple[int, int, int], str] = {}
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise TrainingError(f"cannot read {path}: {exc.strerror or exc}") from exc
    for n, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(":")
        try:
            rgb = tuple(int(v) for v in parts[1].split(","))
        except (IndexError, ValueError):
            rgb = ()
        if len(rgb) != 3 or not all(0 <= v <= 255 for v in rgb):
            raise TrainingError(f"{path}:{n}: expected name:r,g,b:..., got {line!r}")
        colours[(rgb[0], rgb[1], rgb[2])] = parts[0]
    if not colours:
        raise TrainingError(f"{path}: no labels in it")
    return colours


def _mask_pngs(folder: Path, names: tuple[str, ...], cfg: SiteDataConfig) -> list[tuple[str, U8, U8]]:
    """``(stem, rgb, classes)`` of every mask of a CVAT segmentation-mask export."""
    colours = _labelmap(folder / "labelmap.txt")
    lut = site_class_lut(sorted(set(colours.values())), names, cfg.class_map, str(folder / "labelmap.txt"))
    masks = sorted((folder / "SegmentationClass").glob("*.png"))
    if not masks:
        raise TrainingError(f"{folder}: no SegmentationClass/*.png masks")
    code = {(r << 16) | (g << 8) | b: lut[name] for (r, g, b), name in colours.items()}
    out = []
    for mask_path in masks:
        images = [folder / "JPEGImages" / f"{mask_path.stem}{s}" for s in IMAGE_SUFFIXES]
        image = next((p for p in images if p.is_file()), None)
        if image is None:
            raise TrainingError(f"{mask_path}: no image JPEGImages/{mask_path.stem}.jpg or .png")
        rgb = _read_image(image)
        bgr = cv2.imread(str(mask_path), cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[:2] != rgb.shape[:2]:
            raise TrainingError(f"{mask_path}: unreadable, or not the size of {image.name}")
        channels = bgr.astype(np.int32)
        packed = (channels[..., 2] << 16) | (channels[..., 1] << 8) | channels[..., 0]
        found = np.unique(packed)
        strange = [int(v) for v in found if int(v) not in code]
        if strange:
            rgb_text = ", ".join(f"({v >> 16},{(v >> 8) & 255},{v & 255})" for v in strange[:3])
            raise TrainingError(f"{mask_path}: colour(s) {rgb_text} are not in labelmap.txt")
        lut_array = np.array([code[int(v)] for v in found], np.uint8)
        classes = lut_array[np.searchsorted(found, packed)]
        out.append((mask_path.stem, rgb, np.ascontiguousarray(classes, np.uint8)))
    return out


def _negatives(folder: Path) -> list[tuple[str, U8, U8]]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise TrainingError(f"{folder}: no images (.jpg, .png) for negatives")
    out = []
    for p in files:
        rgb = _read_image(p)
        out.append((p.stem, rgb, np.zeros(rgb.shape[:2], np.uint8)))
    return out


def check_site_paths(cfg: SiteDataConfig) -> None:
    """Fail early (before torch is imported or frames rendered) on a site file or folder that is
    not there.

    Raises:
        TrainingError: naming the setting and the path.
    """
    for key, want_dir in (("coco_json", False), ("coco_images", True), ("mask_dir", True),
                          ("negatives_dir", True), ("depth_dir", True)):
        value = getattr(cfg, key)
        if not value:
            continue
        path = Path(value)
        if not (path.is_dir() if want_dir else path.is_file()):
            kind = "folder" if want_dir else "file"
            raise TrainingError(f"[train_seg.site] {key}: {path} not found (expected a {kind})")


def load_site_samples(
    cfg: SiteDataConfig, names: tuple[str, ...], width: int, height: int
) -> SegSamples | None:
    """The site's labelled images as samples of ``width`` x ``height`` (None when none are set),
    each ``cfg.repeat`` times, ``world`` = :data:`SITE_WORLD`, off the robot track.

    Raises:
        TrainingError: a missing folder or file, an unreadable image, an unknown class or colour.
    """
    if not cfg.used:
        return None
    check_site_paths(cfg)
    items: list[tuple[str, U8, U8]] = []
    for value, load in ((cfg.coco_json, lambda p: _coco_masks(p, names, cfg)),
                        (cfg.mask_dir, lambda p: _mask_pngs(p, names, cfg)),
                        (cfg.negatives_dir, _negatives)):
        if value:
            items += load(Path(value))
    rgbs, clss, depths = [], [], []
    for stem, rgb, classes in items:
        depth = _depth_for(cfg, stem, classes.shape)
        r, c, d = _resized(rgb, classes, depth, width, height)
        rgbs.append(r)
        clss.append(c)
        depths.append(d)
    n = len(rgbs) * cfg.repeat
    log.info("site data: %d image(s) (%d with depth), each %d time(s)", len(rgbs),
             sum(bool(d.any()) for d in depths), cfg.repeat)
    return SegSamples(
        np.tile(np.stack(rgbs), (cfg.repeat, 1, 1, 1)),
        np.tile(np.stack(clss), (cfg.repeat, 1, 1)),
        np.tile(np.stack(depths), (cfg.repeat, 1, 1)),
        np.full(n, SITE_WORLD, np.int32),
        np.zeros(n, bool),
        names,
    )
