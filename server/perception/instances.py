"""Instances: found in a segmentation network's class map or read from the simulator's
ground truth, then split into one instance per object.

From a network's class map (:class:`~wardmap.server.perception.models.OnnxSegmenter`):

- :func:`instances_from_classes`: per-class connected components of the class map, split
  where the depth jumps: two chairs of the same class that overlap in the image but stand at
  different depths become two instances;
- :func:`off_background_planes`: the pixels of a mask that lie on the wall or floor around
  it; :func:`instances_from_classes` drops them for the classes it is told to trim, which
  splits chairs that the network's bleed onto the wall joined into one region.

Ground truth (the simulator's label images, ``docs/dataset.md``):

- :func:`oracle_instances`: one instance per simulator instance id, confidence 1, class
  from ``objects.json`` (:func:`id_to_class`);
- :func:`attach_gt_instances`: the simulator id most of each mask covers, for scoring
  model or detector instances against ground truth.

One instance per object (:func:`split_instances`, the network's instances only):

- :func:`split_side_by_side`: an instance as wide as two or more objects of its class
  (touching chairs in a row) cut into side-by-side pieces at the gaps, using depth and the
  camera; doors also where the mask drops below their common top line, and from the far end
  when the mask is cut by the image border;
- :func:`merge_stacked`: pieces of one object that trimming cut apart one above the other (a
  chair's open back above its seat) joined again.

Pixel boxes follow ``shared/detection.py`` (``masks.box_of_mask``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.stats import siegelslopes

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.masks import (
    Mask,
    box_of_mask,
    clipped_side,
    densest_window,
    fit_inverse_depth_plane,
    principal_direction,
    ring_around,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import DatasetError, GeometryError

__all__ = [
    "attach_gt_instances",
    "gt_instance_of",
    "id_to_class",
    "instances_from_classes",
    "merge_stacked",
    "off_background_planes",
    "oracle_instances",
    "split_instances",
    "split_side_by_side",
]

log = logging.getLogger(__name__)



def instances_from_classes(
    class_map: NDArray[np.uint8],
    depth_m: NDArray[np.float32],
    class_names: Sequence[str],
    confidences: NDArray[np.float32] | None = None,
    *,
    depth_jump_m: float = 0.15,
    depth_jump_relative: float = 0.05,
    min_pixels: int = 200,
    min_confidence: float = 0.0,
    trim_classes: Sequence[int] = (),
) -> list[Instance]:
    """Instances of a per-pixel class map: per-class connected components split at depth jumps.

    A pixel is cut from its class region when a 4-neighbour of the same class is nearer
    by more than ``max(depth_jump_m, depth_jump_relative * depth)`` (the far side of a
    discontinuity; the relative term follows the depth noise of structured-light
    sensors). The remaining pixels form 4-connected components; cut pixels then join a
    neighbouring component of similar depth. Pixels without depth (0) never cut.

    Args:
        class_map: uint8 (H, W) class index per pixel, 0 = background.
        depth_m: float32 (H, W) depth along the camera z axis in metres, 0 = no data.
        class_names: index -> class name; ``class_names[0]`` is the background.
        confidences: float32 (H, W) per-pixel score in 0..1 (e.g. softmax max), or None
            for confidence 1. An instance's confidence is the mean over its mask.
        depth_jump_m: smallest depth step (metres) that separates instances.
        depth_jump_relative: the step threshold as a fraction of depth, when larger.
        min_pixels: components with fewer pixels are left out (logged at debug).
        min_confidence: components whose mean confidence is lower are left out (logged at
            debug): the ragged fringes a network leaves where it hesitates between classes.
        trim_classes: class indices whose components lose the pixels on the planes around
            them (:func:`off_background_planes`; chairs, carts, not doors flush with a wall);
            what remains is split into 4-connected pieces, each one instance when it has
            ``min_pixels``.

    Returns:
        Instances ordered by class index, then by component size (largest first).

    Raises:
        GeometryError: shapes or dtypes do not match, or a class index has no name.
    """
    classes = _check_image("instances_from_classes: class_map", class_map, (np.uint8,))
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.shape != classes.shape:
        raise GeometryError(f"instances_from_classes: depth {depth.shape} != class map {classes.shape}")
    conf = None
    if confidences is not None:
        conf = np.asarray(confidences, dtype=np.float32)
        if conf.shape != classes.shape:
            raise GeometryError(
                f"instances_from_classes: confidences {conf.shape} != class map {classes.shape}"
            )
    if not (depth_jump_m > 0 and depth_jump_relative >= 0):
        raise GeometryError("instances_from_classes: depth_jump_m must be > 0, depth_jump_relative >= 0")
    if not 0.0 <= min_confidence <= 1.0:
        raise GeometryError(f"instances_from_classes: min_confidence must lie in 0..1, got {min_confidence}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
    jump = np.maximum(np.float32(depth_jump_m), np.float32(depth_jump_relative) * depth)
    present = np.unique(classes)
    if present.size and int(present[-1]) >= len(class_names):
        raise GeometryError(
            f"instances_from_classes: class index {int(present[-1])} but only {len(class_names)} class names"
        )
    cut = _far_side_of_jump(classes, depth, jump)
    labels = np.zeros(classes.shape, np.int32)
    class_of: list[int] = [0]  # class index of each label
    for index in present.tolist():
        if index == 0:
            continue
        region = classes == index
        rows = np.flatnonzero(region.any(axis=1))
        cols = np.flatnonzero(region.any(axis=0))
        window = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        inside = (region[window] & ~cut[window]).astype(np.uint8)
        count, comp = cv2.connectedComponents(inside, connectivity=4)
        comp = comp.astype(np.int32)
        comp[comp > 0] += len(class_of) - 1
        labels[window] = np.where(comp > 0, comp, labels[window])
        class_of.extend([index] * (count - 1))
    _grow_into(labels, classes, depth, cut & (labels == 0), jump)
    sizes = np.bincount(labels.ravel(), minlength=len(class_of))
    out: list[Instance] = []
    small = unsure = 0
    for index in present.tolist():
        if index == 0:
            continue
        ks = [k for k in range(1, len(class_of)) if class_of[k] == index]
        for k in sorted(ks, key=lambda k: -sizes[k]):
            if sizes[k] < min_pixels:
                small += 1 if sizes[k] > 0 else 0
                continue
            mask = labels == k
            pieces = [mask]
            if index in trim_classes:
                pieces = _pieces(mask & ~off_background_planes(mask, depth), min_pixels)
                small += not pieces
            for piece in pieces:
                score = float(conf[piece].mean()) if conf is not None else 1.0
                if score < min_confidence:
                    unsure += 1
                    continue
                out.append(Instance(class_names[index], score, piece, box_of_mask(piece)))
    if small or unsure:
        log.debug("instances_from_classes: left out %d component(s) below %d pixels and %d below "
                  "confidence %.2f", small, min_pixels, unsure, min_confidence)
    return out


_NEIGHBOURS = (
    # (p, q) slices pairing every pixel p with its left, right, upper and lower neighbour q.
    (np.s_[:, 1:], np.s_[:, :-1]),
    (np.s_[:, :-1], np.s_[:, 1:]),
    (np.s_[1:, :], np.s_[:-1, :]),
    (np.s_[:-1, :], np.s_[1:, :]),
)


def _far_side_of_jump(classes: NDArray[np.uint8], depth_m: NDArray[np.float32],
                      jump: NDArray[np.float32]) -> Mask:
    """Pixels that have a 4-neighbour of the same (non-background) class nearer by more than their jump."""
    cut = np.zeros(depth_m.shape, dtype=bool)
    valid = (depth_m > 0) & (classes > 0)
    for p, q in _NEIGHBOURS:
        ok = valid[p] & valid[q] & (classes[p] == classes[q])
        cut[p] |= ok & (depth_m[p] - depth_m[q] > jump[p])
    return cut


def _grow_into(labels: NDArray[np.int32], classes: NDArray[np.uint8], depth_m: NDArray[np.float32],
               todo: Mask, jump: NDArray[np.float32]) -> None:
    """Give each ``todo`` pixel the label of a same-class labelled 4-neighbour within its jump (in place)."""
    for _ in range(2):
        if not todo.any():
            return
        for p, q in _NEIGHBOURS:
            take = todo[p] & (labels[q] > 0) & (classes[p] == classes[q])
            take &= np.abs(depth_m[p] - depth_m[q]) <= jump[p]
            labels[p][take] = labels[q][take]
            todo[p] &= ~take


def off_background_planes(
    mask: Mask,
    depth_m: NDArray[np.float32],
    *,
    ring_px: int = 8,
    tolerance_m: float = 0.03,
    tolerance_relative: float = 0.01,
    min_share: float = 0.25,
    max_planes: int = 2,
    iterations: int = 48,
    max_ring_samples: int = 600,
    seed: int = 0,
) -> Mask:
    """Pixels of ``mask`` that lie on a plane of the surfaces around it (wall, floor).

    A network's mask bleeds a few pixels onto the wall and floor an object stands by; where
    identical chairs stand in a row, the bleed joins them into one region. The surroundings
    are a ring of pixels ``ring_px`` wide starting 2 px outside the mask. Up to ``max_planes``
    planes are fitted to the ring's depth by RANSAC, each one explaining at least
    ``min_share`` of the ring. A plane is affine in inverse depth over the image
    (``1/z = a u + b v + c`` for a pinhole camera; lens distortion is ignored), so no
    intrinsics are needed. A mask pixel lies on a plane when its depth is within
    ``max(tolerance_m, tolerance_relative * z)`` of the plane's. At most
    ``max_ring_samples`` ring pixels (a seeded random subset) are used for the fit.

    Args:
        mask: bool (H, W) one instance.
        depth_m: float32 (H, W) metres, 0 = no data (such pixels are never on a plane).

    Returns:
        bool (H, W): the mask's pixels on a background plane (all False when the ring has
        too little depth or no plane explains enough of it).
    """
    out = np.zeros(mask.shape, dtype=bool)
    around = ring_around(mask, ring_px)
    if around is None:
        return out
    window, m, ring = around
    d = depth_m[window].astype(np.float64)
    ring &= d > 0
    rr, rc = np.nonzero(ring)
    if rr.size < 50:
        return out
    rng = np.random.default_rng(seed)
    if rr.size > max_ring_samples:
        keep = rng.choice(rr.size, size=max_ring_samples, replace=False)
        rr, rc = rr[keep], rc[keep]
    z = d[rr, rc]
    u, v = rc.astype(np.float64), rr.astype(np.float64)
    tol = np.maximum(tolerance_m, tolerance_relative * z)
    mr, mc = np.nonzero(m & (d > 0))
    zm = d[mr, mc]
    tol_m = np.maximum(tolerance_m, tolerance_relative * zm)
    on = np.zeros(mr.size, dtype=bool)
    left = np.ones(rr.size, dtype=bool)
    for _ in range(max_planes):
        if left.sum() < max(50, min_share * rr.size):
            break
        idx = np.flatnonzero(left)
        coef, inl = fit_inverse_depth_plane(u[idx], v[idx], z[idx], tol[idx], rng, iterations)
        if coef is None or inl.sum() < min_share * rr.size:
            break
        left[idx[inl]] = False
        wp = coef[0] * mc + coef[1] * mr + coef[2]
        on |= (wp > 0) & (np.abs(1.0 / np.where(wp > 0, wp, 1.0) - zm) <= tol_m)
    out[window][mr[on], mc[on]] = True
    return out


def _pieces(mask: Mask, min_pixels: int) -> list[Mask]:
    """4-connected pieces of ``mask`` with at least ``min_pixels`` pixels, largest first."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return []
    window = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    count, comp = cv2.connectedComponents(mask[window].astype(np.uint8), connectivity=4)
    sizes = np.bincount(comp.ravel(), minlength=count)
    out = []
    for k in np.argsort(-sizes[1:], kind="stable") + 1:
        if sizes[k] < min_pixels:
            break
        piece = np.zeros(mask.shape, dtype=bool)
        piece[window] = comp == k
        out.append(piece)
    return out


def _check_image(name: str, image: ArrayLike, dtypes: tuple[type, ...]) -> NDArray[Any]:
    a = np.asarray(image)
    if a.ndim != 2 or 0 in a.shape or a.dtype.type not in dtypes:
        want = "/".join(np.dtype(d).name for d in dtypes)
        raise GeometryError(f"{name}: expected a non-empty {want} (H, W) image, got {a.dtype} {a.shape}")
    return a


def id_to_class(objects_document: Mapping[str, Any]) -> dict[int, str]:
    """Instance id -> class name from a parsed ``objects.json`` (``DatasetReader.objects()``).

    Raises:
        DatasetError: the document has no ``objects`` list or an object lacks ``id``/``class``.
    """
    objects = objects_document.get("objects")
    if not isinstance(objects, list):
        raise DatasetError("objects.json: 'objects' must be a list")
    out: dict[int, str] = {}
    for i, obj in enumerate(objects):
        try:
            out[int(obj["id"])] = str(obj["class"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"objects.json: objects[{i}] needs an integer 'id' and a 'class'") from exc
    return out


def oracle_instances(
    instance_ids: NDArray[np.uint16],
    id_to_class: Mapping[int, str],
    *,
    min_pixels: int = 200,
) -> list[Instance]:
    """Ground-truth instances of one simulator label image.

    Args:
        instance_ids: uint16 (H, W) simulator instance ids, 0 = no object.
        id_to_class: instance id -> knowledge-graph class (:func:`id_to_class`).
        min_pixels: instances covering fewer pixels are left out (logged at debug).

    Returns:
        One :class:`Instance` per id with at least ``min_pixels`` pixels, in increasing id
        order, every class included (callers filter ``person`` etc.); confidence 1 and
        ``gt_instance`` = the id.

    Raises:
        GeometryError: ``instance_ids`` is not a 2-D integer image.
        DatasetError: an id in the image has no class in ``id_to_class``.
    """
    ids = _check_image("oracle_instances", instance_ids, (np.uint16, np.uint8, np.int32, np.int64))
    values, counts = np.unique(ids, return_counts=True)
    out: list[Instance] = []
    small = 0
    for value, count in zip(values.tolist(), counts.tolist(), strict=True):
        if value == 0:
            continue
        category = id_to_class.get(int(value))
        if category is None:
            raise DatasetError(f"label image: instance id {value} has no object in objects.json")
        if count < min_pixels:
            small += 1
            continue
        mask = ids == value
        out.append(Instance(category, 1.0, mask, box_of_mask(mask), gt_instance=int(value)))
    if small:
        log.debug("oracle_instances: %d instance(s) below %d pixels left out", small, min_pixels)
    return out


def gt_instance_of(mask: Mask, instance_ids: NDArray[np.uint16], min_fraction: float = 0.5) -> int | None:
    """The most frequent non-zero simulator id under ``mask`` if it covers ``min_fraction`` of it, else None.

    Pixels with id 0 ("no object") count in the denominator, so a mask mostly on the wall gives None.
    """
    if mask.shape != instance_ids.shape:
        raise GeometryError(f"gt_instance_of: mask {mask.shape} != labels {instance_ids.shape}")
    under = instance_ids[mask]
    if under.size == 0:
        return None
    values, counts = np.unique(under[under != 0], return_counts=True)
    if values.size == 0:
        return None
    best = int(np.argmax(counts))
    if counts[best] < min_fraction * under.size:
        return None
    return int(values[best])


def attach_gt_instances(
    instances: Sequence[Instance], instance_ids: NDArray[np.uint16], min_fraction: float = 0.5
) -> list[Instance]:
    """Copies of ``instances`` with ``gt_instance`` set by :func:`gt_instance_of` (model or detector)."""
    ids = _check_image("attach_gt_instances", instance_ids, (np.uint16, np.uint8, np.int32, np.int64))
    return [
        dataclasses.replace(inst, gt_instance=gt_instance_of(inst.mask, ids, min_fraction))
        for inst in instances
    ]


def split_instances(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                    config: PerceptionConfig, spec: str) -> list[Instance]:
    """One instance per object: the segmentation network's (``model`` specs) instances of the
    ``split_width_m`` classes cut into side-by-side objects (:func:`split_side_by_side`), then
    pieces of the ``stack_gap_m`` classes one above the other joined (:func:`merge_stacked`: a
    chair's open back and its seat); other segmenters' instances are returned unchanged (a
    detector boxes each chair). ``depth_m``: float32 (H, W) metres, registered to the colour
    image of ``camera``."""
    out = list(instances)
    if not spec.strip().startswith("model"):
        return out
    usual = dict(config.measure.clipped_width_m)
    for name, width in config.split_width_m:
        out = split_side_by_side(out, depth_m, camera, classes=(name,), width_m=width,
                                 min_pixels=config.min_pixels, usual_width_m=usual.get(name))
    for name, gap in config.stack_gap_m:
        out = merge_stacked(out, depth_m, camera, classes=(name,), max_gap_m=gap)
    return out


_LEAST_PART: float = 1 / 3
"""``split_side_by_side`` with a usual width: the least share of that width a piece at a side
border of the image must span to be cut off and kept; a narrower piece is a sliver (a door
frame, a cabinet's side) that would be widened beyond the border into a door of its own."""


def split_side_by_side(
    instances: Sequence[Instance],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    *,
    classes: Sequence[str],
    width_m: float,
    min_pixels: int,
    one_object_share: float = 0.8,
    usual_width_m: float | None = None,
) -> list[Instance]:
    """Instances of ``classes`` as wide as two or more such objects, cut into side-by-side pieces.

    A network's mask often joins touching objects of one class (a row of chairs), and the
    depth does not separate them. The mask pixels with depth are back-projected onto the
    camera's horizontal x-z plane (metres; distortion ignored) and spread along their first
    principal axis; an extent (2-98 % quantiles) of k * ``width_m`` (k >= 2, rounded) is cut
    into k pieces, each cut at the sparsest 2 cm bin within ``width_m / 4`` of its even
    position (the gap between two chairs); not when one ``width_m``-wide window holds
    ``one_object_share`` of the pixels (one object and a thin spill beyond it). Pixels
    without depth belong to no piece. A piece keeps the class and confidence; pieces under
    ``min_pixels`` are dropped, and an instance cut so is replaced by the pieces left, even
    when only one or none is left: whole, it would be measured as one object as wide as
    several, on none of them (a row of chairs far away, each under ``min_pixels``).

    Args:
        instances: instances of one colour image (H, W).
        depth_m: float32 (H, W) depth, metres, registered to the colour image; 0 = none.
        camera: the colour camera (``fx``, ``cx``).
        classes: class names to split.
        width_m: typical width of one object of those classes, metres (> 0).
        min_pixels: fewest pixels of a piece.
        one_object_share: an instance is not cut when a ``width_m``-wide window along the
            axis holds at least this share of its pixels with depth: one object, with a thin
            spill beyond it (a door's mask run along the flush wall at a grazing view), which
            the measurement's widest-object bound handles better than a cut through the object.
        usual_width_m: the usual width of one object (a site's doors, metres; None: the even
            cut above only). The mask is first cut at its gap columns, where it is a low strip
            below the objects' common top line (the wall between two doors; see
            ``_runs_between_gaps``). A run that reaches one side border of the image has only
            one true end, so the even cut would place its cuts wrongly: it is cut into objects
            of this width laid from that end, while a third of the width or more is left towards
            the border (two doors side by side, the nearer one half out of view).

    Returns:
        The instances in order, split ones replaced by their pieces (left to right along
        the axis).
    """
    if width_m <= 0:
        raise GeometryError(f"split_side_by_side: width_m must be > 0, got {width_m}")
    if not 0.0 < one_object_share <= 1.0:
        raise GeometryError(
            f"split_side_by_side: one_object_share must lie in (0, 1], got {one_object_share}"
        )
    if usual_width_m is not None and not usual_width_m > 0:
        raise GeometryError(f"split_side_by_side: usual_width_m must be > 0, got {usual_width_m}")
    out: list[Instance] = []
    for inst in instances:
        pieces = (_side_by_side(inst.mask, depth_m, camera, width_m, min_pixels, one_object_share,
                                usual_width_m)
                  if inst.category in classes else None)
        if pieces is None:
            out.append(inst)
            continue
        out.extend(dataclasses.replace(inst, mask=p, box_xyxy=box_of_mask(p), gt_instance=None)
                   for p in pieces)
    return out


def merge_stacked(
    instances: Sequence[Instance],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    *,
    classes: Sequence[str],
    max_gap_m: float = 0.1,
    max_depth_step_m: float = 0.6,
    min_overlap: float = 0.6,
) -> list[Instance]:
    """Instances of ``classes`` stacked one above the other in the image joined into one.

    An open chair back stands on thin posts above the seat; the wall shows through the gap
    between them, and trimming the wall from a network's mask
    (:func:`off_background_planes`) leaves the back and the seat as two pieces: a
    measurement of the seat alone is half the chair's height and 20 cm too low. A piece
    whose box lies just above another's (its bottom edge within ``max_gap_m``, converted to
    pixels at their depth, of the other's top edge) is joined to it when their columns
    overlap by at least ``min_overlap`` of the narrower box and their median depths differ
    by at most ``max_depth_step_m`` (a chair in the row behind is farther; the back of a chair
    by the wall and its seat differ by 0.4 m at 7 m in simulated depth). Each piece joins
    at most one other, the one with the largest overlap; the join keeps the class and the
    pixel-weighted confidence.

    Args:
        instances: instances of one colour image (H, W).
        depth_m: float32 (H, W) depth, metres, registered to the colour image; 0 = none.
        camera: the colour camera (``fy``).
        classes: class names to join.

    Returns:
        The instances in order, a joined pair in the place of its lower piece.
    """
    if not (max_gap_m >= 0 and max_depth_step_m > 0 and 0 < min_overlap <= 1):
        raise GeometryError("merge_stacked: need max_gap_m >= 0, max_depth_step_m > 0, 0 < min_overlap <= 1")
    depth = np.asarray(depth_m, dtype=np.float32)
    med: dict[int, float] = {}
    for i, inst in enumerate(instances):
        if inst.category in classes:
            z = depth[inst.mask]
            z = z[np.isfinite(z) & (z > 0)]
            if z.size:
                med[i] = float(np.median(z))
    pairs: list[tuple[float, int, int]] = []
    for a in med:
        for b in med:
            ia, ib = instances[a], instances[b]
            if a == b or ia.category != ib.category:
                continue
            ax1, ay1, ax2, ay2 = ia.box_xyxy
            bx1, by1, bx2, _ = ib.box_xyxy
            gap_px = max_gap_m * camera.fy / max(med[a], med[b])
            if not (ay1 < by1 and abs(ay2 - by1) <= gap_px):
                continue  # a is not just above b
            narrow = min(ax2 - ax1, bx2 - bx1)
            overlap = min(ax2, bx2) - max(ax1, bx1)
            if overlap < min_overlap * narrow or abs(med[a] - med[b]) > max_depth_step_m:
                continue
            pairs.append((overlap / narrow, a, b))
    upper_of: dict[int, int] = {}
    used: set[int] = set()
    for _, a, b in sorted(pairs, reverse=True):
        if a not in used and b not in used:
            used.update((a, b))
            upper_of[b] = a
    uppers = set(upper_of.values())
    out: list[Instance] = []
    for i, inst in enumerate(instances):
        if i in uppers:
            continue
        if i in upper_of:
            top = instances[upper_of[i]]
            mask = inst.mask | top.mask
            na, nb = int(inst.mask.sum()), int(top.mask.sum())
            conf = (inst.confidence * na + top.confidence * nb) / max(na + nb, 1)
            inst = dataclasses.replace(inst, confidence=conf, mask=mask, box_xyxy=box_of_mask(mask),
                                       gt_instance=None)
        out.append(inst)
    return out


def _side_by_side(mask: Mask, depth: NDArray[np.float32], camera: PinholeCamera, width_m: float,
                  min_pixels: int, one_object_share: float, usual_width_m: float | None = None
                  ) -> list[Mask] | None:
    """The pieces of one mask (``split_side_by_side``); None when it stays whole. Without
    ``usual_width_m``: cut evenly, and a mask cut so is replaced by the pieces of at least
    ``min_pixels`` (maybe one or none). With it: cut at gaps, then each run cut from its far
    end when it reaches one side border, else evenly; a run at a side border narrower than
    ``_LEAST_PART`` of a width is a sliver (a door frame, the side of a cabinet) and is
    dropped, since its measurement would be widened beyond the border into a door of its
    own."""
    if usual_width_m is None:
        return _even_pieces(mask, depth, camera, width_m, min_pixels, one_object_share)
    runs, solid = _runs_between_gaps(mask)
    pieces: list[Mask] = []
    changed = len(runs) > 1
    for run in runs:
        side = clipped_side(run)
        cut = (_pieces_from_far_end(run, solid, depth, camera, usual_width_m, side, min_pixels) if side
               else _even_pieces(run, depth, camera, width_m, min_pixels, one_object_share) or [])
        if len(cut) >= 2 or (side and cut):
            pieces.extend(cut)
            changed = True
        elif int(run.sum()) >= min_pixels and (
                len(runs) == 1 or not side or _extent_m(run, depth, camera) >= _LEAST_PART * usual_width_m):
            pieces.append(run)
    return pieces if changed and pieces else None


def _along_axis(mask: Mask, depth: NDArray[np.float32], camera: PinholeCamera, least: int
                ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]] | None:
    """Rows, columns and positions (metres, centred) along the first principal axis of the
    mask's pixels with depth, back-projected onto the camera's horizontal x-z plane
    (distortion ignored); None with fewer than ``least`` such pixels."""
    v, u = np.nonzero(mask)
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    if int(ok.sum()) < max(least, 2):
        return None
    v, u, z = v[ok], u[ok], z[ok]
    xz = np.stack([(u - camera.cx) * z / camera.fx, z], axis=1)
    return v, u, (xz - xz.mean(axis=0)) @ principal_direction(xz)


def _extent_m(mask: Mask, depth: NDArray[np.float32], camera: PinholeCamera) -> float:
    """Extent (metres, 2-98 % quantiles) of the mask's pixels with depth along their first
    principal axis on the camera's x-z plane; 0 without two such pixels."""
    axis = _along_axis(mask, depth, camera, 2)
    if axis is None:
        return 0.0
    lo, hi = np.quantile(axis[2], [0.02, 0.98])
    return float(hi - lo)


def _even_pieces(mask: Mask, depth: NDArray[np.float32], camera: PinholeCamera, width_m: float,
                 min_pixels: int, one_object_share: float) -> list[Mask] | None:
    """``mask`` cut into k pieces of even width along its extent (``split_side_by_side``)."""
    axis = _along_axis(mask, depth, camera, 2 * min_pixels)
    if axis is None:
        return None
    v, u, along = axis
    lo, hi = (float(q) for q in np.quantile(along, [0.02, 0.98]))
    k = int((hi - lo) / width_m + 0.5)
    if k < 2 or densest_window(along, width_m).sum() >= one_object_share * along.size:
        return None
    edges = np.arange(lo, hi + 0.02, 0.02)
    counts = np.histogram(along, edges)[0]
    mids = 0.5 * (edges[:-1] + edges[1:])
    cuts = []
    for i in range(1, k):
        near = np.flatnonzero(np.abs(mids - (lo + i * (hi - lo) / k)) <= width_m / 4)
        cuts.append(float(mids[near[np.argmin(counts[near])]]) if near.size else lo + i * (hi - lo) / k)
    return _pieces_at(mask, v, u, along, cuts, min_pixels)


def _pieces_at(mask: Mask, v: NDArray[np.intp], u: NDArray[np.intp], along: NDArray[np.float64],
               cuts: Sequence[float], min_pixels: int) -> list[Mask]:
    """The pixels ``(v, u)`` grouped by which of the sorted ``cuts`` their ``along`` falls
    between; groups under ``min_pixels`` are dropped."""
    piece = np.searchsorted(np.sort(np.asarray(cuts, dtype=np.float64)), along)
    masks = []
    for i in range(len(cuts) + 1):
        sel = piece == i
        if int(sel.sum()) >= min_pixels:
            m = np.zeros_like(mask)
            m[v[sel], u[sel]] = True
            masks.append(m)
    return masks


def _runs_between_gaps(mask: Mask, min_gap_px: int = 2) -> tuple[list[Mask], NDArray[np.bool_]]:
    """``mask`` cut at its gap columns, and its solid columns (W,).

    Objects of one class side by side on a wall (doors) share a top line and a bottom line in
    the image (their tops are at one height on one plane, so the line is straight); a robust
    line (Siegel's repeated medians) through the columns' first and last mask rows gives both,
    and the band between them is the objects' height in each column. Where the network's mask
    runs over the wall between two doors it is a strip along the floor, whose top lies well
    below the top line: a run of at least ``min_gap_px`` columns whose mask begins more than a
    fifth of the band below it, with object columns on both sides, is a gap, and its pixels
    belong to no run. A person or a chair in front of a door hides its lower part and leaves
    its top: not a gap. A solid column has mask over at least 60 % of the band (an object's
    column, not the spill beside it).
    """
    h, w = mask.shape
    solid = np.zeros(w, dtype=bool)
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size < 3:
        solid[cols] = True
        return [mask], solid
    top = mask[:, cols].argmax(axis=0).astype(np.float64)
    bottom = (h - 1 - mask[::-1, cols].argmax(axis=0)).astype(np.float64)
    top_line = _siegel_line(cols.astype(np.float64), top)
    band = np.maximum(_siegel_line(cols.astype(np.float64), bottom) - top_line, 1.0)
    solid[cols] = mask[:, cols].sum(axis=0) >= 0.6 * band
    runs, n_runs = ndimage.label(top > top_line + 0.2 * band)
    gap = np.zeros(cols.size, dtype=bool)
    for run in ndimage.find_objects(runs, n_runs):
        i0, i1 = run[0].start, run[0].stop
        if i0 > 0 and i1 < cols.size and i1 - i0 >= min_gap_px:  # object columns on both sides
            gap[i0:i1] = True
    kept = np.flatnonzero(~gap)
    groups = np.split(kept, np.flatnonzero(np.diff(cols[kept]) > 1) + 1)
    if len(groups) < 2:
        return [mask], solid
    return [_columns(mask, int(cols[g[0]]), int(cols[g[-1]]) + 1) for g in groups], solid


def _siegel_line(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Siegel's repeated-medians line through (x, y), evaluated at x (robust to half outliers)."""
    fit = siegelslopes(y, x)
    return np.asarray(fit.intercept + fit.slope * x, dtype=np.float64)


def _columns(mask: Mask, u0: int, u1: int) -> Mask:
    """``mask`` with only the columns ``u0 <= u < u1`` kept."""
    out = np.zeros_like(mask)
    out[:, u0:u1] = mask[:, u0:u1]
    return out


def _pieces_from_far_end(mask: Mask, solid: NDArray[np.bool_], depth: NDArray[np.float32],
                         camera: PinholeCamera, usual_width_m: float, side: int,
                         min_pixels: int) -> list[Mask]:
    """A mask cut by the image border on ``side`` cut into objects ``usual_width_m`` wide laid
    from its other end (the only end that is an object's end; the 98th percentile of its pixels
    in ``solid`` columns along the mask's axis, so a spill onto the wall beyond it does not
    move it), while at least a third of that width is left towards the border; [] when
    nothing is cut."""
    axis = _along_axis(mask, depth, camera, 2 * min_pixels)
    if axis is None:
        return []
    v, u, along = axis
    at_border = u <= u.min() + 2 if side < 0 else u >= u.max() - 2
    if along[at_border].mean() > along.mean():
        along = -along  # along grows away from the border
    in_solid = solid[u]
    if int(in_solid.sum()) < min_pixels:
        return []
    start = float(np.quantile(along, 0.02))
    end = float(np.quantile(along[in_solid], 0.98))
    cuts = []
    while end - usual_width_m - start >= _LEAST_PART * usual_width_m:
        end -= usual_width_m
        cuts.append(end)
    if not cuts:
        return []
    rest = along < cuts[-1]
    if rest.any() and np.ptp(np.quantile(along[rest], [0.02, 0.98])) < _LEAST_PART * usual_width_m:
        v, u, along = v[~rest], u[~rest], along[~rest]  # a sliver at the border: dropped
    return _pieces_at(mask, v, u, along, cuts, min_pixels)
