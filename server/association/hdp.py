"""Association across keyframe groups: HDP with Gibbs sampling (paper 000 Sec. III-A-2).

As in HDP-SLAM, a keyframe group is a document, a global landmark is a topic and a
group-level landmark ``O^G_{n,i}`` (the result of the in-group tracker) is a word to
assign. The Chinese-restaurant-franchise prior weighs an existing landmark by the number
of group landmarks already assigned to it and a new landmark by the concentration
``gamma``. The likelihood is paper 000 Eq. 2-3: a Gaussian mixture over the 6-DoF poses
of the candidate landmark's measurements (one component per measurement, equal weights
``lambda_z = 1/Z``, covariance ``diag(sigma_p^2 I3, sigma_r^2 I3)``), evaluated at each
measurement of the group landmark, the maximum taken. A candidate that already holds a
measurement of the group landmark (the same measurement, from a keyframe shared by two
overlapping groups) has its weight multiplied by ``overlap_boost`` (paper: 1.5).

Constraints: one keyframe never holds two measurements of one landmark, so a group
landmark cannot join a landmark (or share a new landmark with another group landmark)
that has a different measurement in one of its keyframes, unless (``join_fragments``) the
two fit in one object's box of their class, fragments of one object. Candidates are the nearby,
co-visible landmarks of the same class (chosen by the caller with a spatial index).

Only the new group's assignments are sampled (online HDP, as in HDP-SLAM); assignments
of earlier groups stay fixed. The returned assignment is the most frequent joint state
after burn-in; the sampler is seeded, so results are deterministic.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import logsumexp

from wardmap.server.association.geometry import (
    Symmetry,
    partial_view_slack,
    pose_residuals,
    symmetry_rotations,
)
from wardmap.server.perception.types import CLASS_SIZE_M

__all__ = ["HdpConfig", "HdpItem", "HdpTopic", "gibbs_associate", "gmm_log_density"]

F64 = NDArray[np.float64]
Likelihood = Literal["gmm", "first_pose"]


@dataclass(frozen=True)
class HdpConfig:
    """Parameters of the across-group association."""

    concentration: float = 1.0
    """gamma: prior weight of a new landmark (CRP concentration)."""
    sigma_position_m: float = 0.12
    """Standard deviation of each GMM component along x, y, z (metres), Eq. 3."""
    sigma_position_partial_m: float = 0.3
    """... for measurements whose box touches the image border (partly seen, centre biased)."""
    border_px: float = 3.0
    """A box within this many pixels of the image border marks a partly seen object."""
    sigma_angle_rad: float = 0.5
    """Standard deviation of each GMM component for each rotation axis (radians), Eq. 3."""
    size_slack: float = 1.0
    """Partial-view slack: position residuals shrink by this times half the extent difference
    (``geometry.partial_view_slack``); 0 turns it off."""
    new_landmark_mahalanobis: float = 3.0
    """A new landmark's likelihood: one Eq. 3 component's density at this Mahalanobis distance."""
    overlap_boost: float = 1.5
    """Factor for candidates sharing a measurement of an overlapping keyframe (paper: 1.5)."""
    sweeps: int = 30
    """Gibbs sweeps over the group's landmarks."""
    burn_in: int = 5
    """Sweeps discarded before counting joint states."""
    candidate_radius_m: float = 1.5
    """Only landmarks whose centre is this close to the group landmark are candidates."""
    covisibility_max_depth_m: float = 12.0
    """A candidate's box must appear in the image of one of the group's keyframes, its centre at
    most this far from that camera (metres) ..."""
    covisibility_margin_px: float = 100.0
    """... where the image is grown by this margin on every side (boxes of partly seen
    objects are biased, so the landmark's box may fall just outside)."""
    symmetry: Symmetry = "quarter_turn"
    """Box symmetry about z used when comparing orientations."""
    class_size_m: tuple[tuple[str, float, float], ...] = CLASS_SIZE_M
    """Largest horizontal extent and height (metres) of a class (``geometry.partial_view_slack``,
    here and in the in-group tracker): a measurement larger than this holds more than one object
    and gets no more partial-view slack than a full view; two partial views of one object may
    lie this far apart; candidates are looked for within the larger of this and
    ``candidate_radius_m``. Classes not listed get no bound."""
    parts_min_m: float = 0.8
    """Two partial views may lie ``S - (E_a + E_b) / 2`` apart (``class_size_m``) across groups
    only for classes at least this large horizontally (beds, doors, carts; the in-group tracker,
    whose keyframes are consecutive, uses it for every listed class), metres. Two partial views
    of a chair in different groups are as often two of a row of chairs (docs/decisions/0011)."""
    join_fragments: bool = True
    """Two different measurements of one keyframe stop a landmark (or two group landmarks) from
    holding both, unless their joint box fits within the class's size bound: then they may be
    fragments of one object (a chair's back cut off its seat by an occluder) and the
    constraint does not apply. False: every keyframe holds at most one measurement of a
    landmark, as in the paper. Beyond the paper."""

    def __post_init__(self) -> None:
        if not (self.concentration > 0 and self.sigma_position_m > 0 and self.sigma_angle_rad > 0
                and self.sigma_position_partial_m > 0 and self.border_px >= 0):
            raise ValueError("concentration and sigmas must be > 0")
        if self.new_landmark_mahalanobis < 0 or self.overlap_boost < 1:
            raise ValueError("need new_landmark_mahalanobis >= 0 and overlap_boost >= 1")
        if self.sweeps < 1 or not 0 <= self.burn_in < self.sweeps:
            raise ValueError("need sweeps >= 1 and 0 <= burn_in < sweeps")
        if (self.candidate_radius_m <= 0 or self.covisibility_max_depth_m <= 0
                or self.covisibility_margin_px < 0):
            raise ValueError("candidate radius and co-visibility depth must be > 0, the margin >= 0")
        if self.parts_min_m < 0:
            raise ValueError(f"parts_min_m must be >= 0, got {self.parts_min_m}")
        for entry in self.class_size_m:
            if len(entry) != 3 or not (entry[1] > 0 and entry[2] > 0):
                raise ValueError(
                    f"class_size_m entries are [class, horizontal m > 0, height m > 0], got {entry!r}"
                )

    def class_extent(self, category: str) -> F64 | None:
        """World-axis extent bound (3,) ``(S, S, H)`` of ``category``, or None when not listed."""
        for name, horizontal, height in self.class_size_m:
            if name == category:
                return np.array([horizontal, horizontal, height])
        return None

    def seen_in_parts(self, category: str) -> bool:
        """True when two partial views of ``category`` in different groups get the both-partial
        slack (its horizontal bound is at least ``parts_min_m``)."""
        ext = self.class_extent(category)
        return ext is not None and float(ext[0]) >= self.parts_min_m

    def search_radius(self, category: str) -> float:
        """Candidate search radius for ``category`` (metres)."""
        ext = self.class_extent(category)
        return self.candidate_radius_m if ext is None else max(self.candidate_radius_m, float(ext[0]))


@dataclass(frozen=True, eq=False)
class HdpItem:
    """A group landmark to assign.

    Attributes:
        category: its class.
        poses: (K, 4, 4) its measurement poses in ``world``.
        keyframes: (K,) keyframe index of each measurement.
        mids: (K,) measurement ids.
        sigmas: (K,) position standard deviation of each measurement (metres), or None
            for ``sigma_position_m``.
        extents: (K, 3) world-axis extents of the measured boxes (metres), or None (no slack).
    """

    category: str
    poses: F64
    keyframes: tuple[int, ...]
    mids: tuple[int, ...]
    sigmas: F64 | None = None
    extents: F64 | None = None


@dataclass(frozen=True, eq=False)
class HdpTopic:
    """An existing global landmark as a candidate.

    Attributes:
        id: landmark id (> 0).
        category: its class.
        poses: (Z, 4, 4) the poses that define its likelihood: all measurement poses for
            ``gmm`` (Eq. 2), the first measurement's pose only for ``first_pose`` (HDP-SLAM).
        tables: number of group landmarks assigned to it so far (CRP count).
        keyframe_mids: keyframe index -> ids of its measurements in that keyframe.
        sigmas: (Z,) position standard deviation per pose (metres), or None for
            ``sigma_position_m``.
        extents: (Z, 3) world-axis extents per pose (metres), or None (no slack).
    """

    id: int
    category: str
    poses: F64
    tables: int
    keyframe_mids: dict[int, frozenset[int]] = field(default_factory=dict)
    sigmas: F64 | None = None
    extents: F64 | None = None


def _log_norm(sigma_p: float, sigma_r: float) -> float:
    # log of the normalisation of a 6-D Gaussian with diag(sigma_p^2 I3, sigma_r^2 I3).
    return -3.0 * math.log(2.0 * math.pi) - 3.0 * math.log(sigma_p) - 3.0 * math.log(sigma_r)


def gmm_log_density(
    query: F64,
    components: F64,
    config: HdpConfig | None = None,
    query_sigmas: F64 | None = None,
    component_sigmas: F64 | None = None,
    query_extents: F64 | None = None,
    component_extents: F64 | None = None,
    class_extent: F64 | None = None,
    both_partial: bool = True,
) -> F64:
    """``log sum_z phi(O_q | Theta_z)`` (Q,) for query poses (Q, 4, 4), components (Z, 4, 4).

    Eq. 3 per component: mean = the component's pose, covariance ``diag(sigma^2 I3,
    sigma_r^2 I3)`` over the 6-D residual of
    :func:`~wardmap.server.association.geometry.pose_residuals`, where the position
    sigma of a (query, component) pair is ``sqrt((sigma_q^2 + sigma_z^2) / 2)`` (each
    ``sigma_position_m``, or larger for partly seen objects) and the position residual
    shrunk by the partial-view slack when extents are given. Summed over components
    without the ``1/Z`` weights of Eq. 2 (the caller adds ``-log Z``). The paper prints
    ``sqrt(2 pi)`` as the normaliser; the 6-D Gaussian's ``(2 pi)^3`` is used here.
    """
    cfg = config or HdpConfig()
    r = pose_residuals(query, components, symmetry_rotations(cfg.symmetry))  # (Q, Z, 6)
    if query_extents is not None and component_extents is not None and cfg.size_slack > 0:
        r[..., :3] = partial_view_slack(r[..., :3], query_extents, component_extents, cfg.size_slack,
                                        class_extent, both_partial=both_partial)
    sq = np.full(len(query), cfg.sigma_position_m) if query_sigmas is None else query_sigmas
    sz = np.full(len(components), cfg.sigma_position_m) if component_sigmas is None else component_sigmas
    sigma = np.sqrt((sq[:, None] ** 2 + sz[None, :] ** 2) / 2.0)  # (Q, Z)
    sr = cfg.sigma_angle_rad
    m2 = np.sum(r[..., :3] ** 2, axis=-1) / sigma**2 + np.sum(r[..., 3:] ** 2, axis=-1) / sr**2
    log_phi = -0.5 * m2 - 3.0 * math.log(2.0 * math.pi) - 3.0 * np.log(sigma) - 3.0 * math.log(sr)
    return np.asarray(logsumexp(log_phi, axis=1), dtype=np.float64)


Boxes = Mapping[int, tuple[F64, F64]]
"""Measurement id -> its world-axis box (lower and upper corner, (3,) each, metres)."""


def _fragments(mids: frozenset[int], boxes: Boxes, bound: F64) -> bool:
    """True when the joint box of measurements ``mids`` fits within ``bound`` (3,) metres."""
    if any(mid not in boxes for mid in mids):
        return False
    lo = np.min([boxes[mid][0] for mid in mids], axis=0)
    hi = np.max([boxes[mid][1] for mid in mids], axis=0)
    return bool(np.all(hi - lo <= bound))


def _conflict(kf_a: dict[int, frozenset[int]], kf_b: dict[int, frozenset[int]],
              boxes: Boxes | None = None, bound: F64 | None = None) -> bool:
    """True when some keyframe holds different measurements of the two sides (with ``boxes`` and
    a class ``bound``: measurements that do not fit in one object's box together)."""
    small, large = (kf_a, kf_b) if len(kf_a) <= len(kf_b) else (kf_b, kf_a)
    for k in small:
        if k not in large or small[k] == large[k]:
            continue
        if boxes is None or bound is None or not _fragments(small[k] | large[k], boxes, bound):
            return True
    return False


def _keyframe_mids(item: HdpItem) -> dict[int, frozenset[int]]:
    out: dict[int, set[int]] = {}
    for k, mid in zip(item.keyframes, item.mids, strict=True):
        out.setdefault(k, set()).add(mid)
    return {k: frozenset(v) for k, v in out.items()}


def gibbs_associate(
    items: Sequence[HdpItem],
    candidates: Sequence[Sequence[HdpTopic]],
    config: HdpConfig | None = None,
    *,
    rng: np.random.Generator,
    likelihood: Likelihood = "gmm",
    boxes: Boxes | None = None,
) -> list[int]:
    """Assign a group's landmarks to existing or new global landmarks by Gibbs sampling.

    Args:
        items: the group landmarks (words of this document).
        candidates: for each item, the nearby co-visible landmarks of its class.
        config: prior, likelihood and sampler parameters.
        rng: the seeded generator to draw from.
        likelihood: ``gmm`` (paper 000 Eq. 2-3, max over the item's measurements) or
            ``first_pose`` (HDP-SLAM: one Gaussian at the landmark's first pose).
        boxes: world boxes of the measurements in the items' and candidates' keyframes; with
            ``join_fragments``, measurements of one keyframe that fit in one object's box do
            not conflict. None: every keyframe holds at most one measurement of a landmark.

    Returns:
        One entry per item: an existing landmark id (> 0), or ``-k`` (k = 1, 2, ...) for
        the k-th new landmark; items with the same ``-k`` form one new landmark.
    """
    cfg = config or HdpConfig()
    n = len(items)
    if n == 0:
        return []
    if len(candidates) != n:
        raise ValueError(f"gibbs_associate: {n} items but {len(candidates)} candidate lists")
    kf = [_keyframe_mids(it) for it in items]
    mids = [set(it.mids) for it in items]
    log_new = math.log(cfg.concentration) - 0.5 * cfg.new_landmark_mahalanobis**2 + _log_norm(
        cfg.sigma_position_m, cfg.sigma_angle_rad)
    log_boost = math.log(cfg.overlap_boost)

    # Sources of mixture components: existing topics (by id) and items (by index).
    topics: dict[int, HdpTopic] = {}
    for cands in candidates:
        for t in cands:
            topics[t.id] = t
    boxes = boxes if cfg.join_fragments else None
    bounds = [cfg.class_extent(it.category) for it in items]
    # Allowed existing topics per item: same class, no keyframe conflict.
    allowed: list[list[int]] = []
    for i, it in enumerate(items):
        allowed.append([t.id for t in candidates[i] if t.category == it.category
                        and not _conflict(kf[i], t.keyframe_mids, boxes, bounds[i])])
    item_conflict = np.array(
        [[a != b and (items[a].category != items[b].category or _conflict(kf[a], kf[b], boxes, bounds[a]))
          for b in range(n)] for a in range(n)], dtype=bool)
    # Component log-sums: per item i, per source -> (K_i,) log sum_z phi.
    first_pose = likelihood == "first_pose"

    def source_poses(src: tuple[str, int]) -> F64:
        poses = topics[src[1]].poses if src[0] == "t" else items[src[1]].poses
        return poses[:1] if first_pose else poses

    def source_sigmas(src: tuple[str, int]) -> F64 | None:
        sig = topics[src[1]].sigmas if src[0] == "t" else items[src[1]].sigmas
        return sig if sig is None or not first_pose else sig[:1]

    def source_extents(src: tuple[str, int]) -> F64 | None:
        ext = topics[src[1]].extents if src[0] == "t" else items[src[1]].extents
        return ext if ext is None or not first_pose else ext[:1]

    cache: dict[tuple[int, tuple[str, int]], F64] = {}

    def logsum(i: int, src: tuple[str, int]) -> F64:
        key = (i, src)
        if key not in cache:
            cache[key] = gmm_log_density(items[i].poses, source_poses(src), cfg, items[i].sigmas,
                                         source_sigmas(src), items[i].extents, source_extents(src),
                                         cfg.class_extent(items[i].category),
                                         cfg.seen_in_parts(items[i].category))
        return cache[key]

    def loglik(i: int, sources: list[tuple[str, int]]) -> float:
        # Eq. 2 over the union of the sources' components; max over the item's measurements.
        if first_pose:
            sources = sources[:1]  # the landmark's first pose only
        parts = np.stack([logsum(i, s) for s in sources])
        count = sum(len(source_poses(s)) for s in sources)
        return float(np.max(logsumexp(parts, axis=0) - math.log(count)))

    shares = [{t: bool(mids[i] & {m for v in topics[t].keyframe_mids.values() for m in v})
               for t in allowed[i]} for i in range(n)]

    z: list[int] = [0] * n  # existing id (> 0), new-topic label (< 0), 0 = unassigned
    next_label = -1

    def members(label: int, exclude: int) -> list[int]:
        return [j for j in range(n) if j != exclude and z[j] == label]

    def sample(i: int) -> int:
        nonlocal next_label
        options: list[int] = []
        logw: list[float] = []
        for t in allowed[i]:
            others = members(t, i)
            if any(item_conflict[i, j] for j in others):
                continue
            srcs = [("t", t)] + [("i", j) for j in others]
            w = math.log(topics[t].tables + len(others)) + loglik(i, srcs)
            if shares[i][t]:
                w += log_boost
            options.append(t)
            logw.append(w)
        for label in sorted({v for v in z if v < 0}, reverse=True):
            others = members(label, i)
            if not others or any(item_conflict[i, j] for j in others):
                continue
            others.sort()
            options.append(label)
            logw.append(math.log(len(others)) + loglik(i, [("i", j) for j in others]))
        options.append(0)  # a fresh landmark
        logw.append(log_new)
        w_arr = np.asarray(logw)
        p = np.exp(w_arr - w_arr.max())
        choice = options[int(rng.choice(len(options), p=p / p.sum()))]
        if choice == 0:
            choice = next_label
            next_label -= 1
        return choice

    def canonical() -> tuple[int, ...]:
        relabel: dict[int, int] = {}
        out = []
        for v in z:
            if v < 0:
                v = relabel.setdefault(v, -(len(relabel) + 1))
            out.append(v)
        return tuple(out)

    for i in range(n):  # sequential initialisation (CRP seating in order)
        z[i] = sample(i)
    counts: Counter[tuple[int, ...]] = Counter()
    first_seen: dict[tuple[int, ...], int] = {}
    for sweep in range(cfg.sweeps):
        for i in range(n):
            z[i] = 0
            z[i] = sample(i)
        if sweep >= cfg.burn_in:
            state = canonical()
            counts[state] += 1
            first_seen.setdefault(state, sweep)
    best = max(counts, key=lambda s: (counts[s], -first_seen[s]))
    return list(best)
