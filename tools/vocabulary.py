"""ORB vocabulary trainer: hierarchical k-medians over binary descriptors, DBoW2 text format.

A bag-of-words vocabulary tree as in DBoW2 (Galvez-Lopez and Tardos, "Bags of Binary Words
for Fast Place Recognition in Image Sequences", T-RO 2012, Sec. IV-A), written from the
paper's description: the training descriptors are clustered into ``k`` groups by k-medians
(Hamming distance, the bitwise majority of a group as its centre, k-means++ seeding); each
group is clustered again, down to ``depth`` levels, giving at most ``k ** depth`` leaves, the
*words*. A leaf's weight is its inverse document frequency ``idf_i = ln(N / n_i)`` (N training
images, n_i of them with a descriptor in word i); inner nodes weigh 0.

The file format is the text vocabulary ORB-SLAM2/3 load (``ORBvoc.txt``,
``ORBVocabulary::loadFromTextFile``): a first line ``k L scoring weighting`` (scoring 0 = L1
norm, weighting 0 = TF-IDF, what ORB-SLAM uses), then one line per node other than the root,
in node-id order (node 0 is the root and has no line): ``parent_id is_leaf d0 d1 ... d31
weight``, the descriptor as 32 byte values. A node's parent always comes before it; words
are numbered in the order their lines appear.

Use ORB-SLAM's shape, ``k = 10`` and ``L = 6``, for ORB-SLAM: it matches the features of two
frames only within the same node 4 levels above the words (its ``FeatureVector``, level
``L - 4``, at least 1); with ``L = 4`` that is one of only 10 nodes, and its ratio test then
rejects most matches (bench/orbslam3.py lost track on the aisles with it).

Training runs on images we own (simulated frames, our recordings): ORB-SLAM's published
vocabulary is neither shipped with wardmap nor downloadable where it runs.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import DatasetError

log = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32
"""ORB (rBRIEF) descriptors: 256 bits."""
MAX_K = 20
MAX_DEPTH = 10
"""ORB-SLAM's loader refuses ``k > 20`` and ``L`` outside 1..10."""
SCORING_L1 = 0
WEIGHTING_TF_IDF = 0

U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A vocabulary tree of ``N`` nodes; node 0 is the root.

    Attributes:
        k: branching factor (children per inner node, at most).
        depth: levels below the root (DBoW2's ``L``).
        parents: (N,) int64 parent node id; -1 for the root. ``parents[i] < i``.
        descriptors: (N, 32) uint8 node centres (the root's is zeros).
        is_leaf: (N,) bool, True for words.
        weights: (N,) float64 idf of a word, 0 for inner nodes.
        scoring, weighting: DBoW2's enum values written in the header (L1, TF-IDF).
    """

    k: int
    depth: int
    parents: I64
    descriptors: U8
    is_leaf: NDArray[np.bool_]
    weights: F64
    scoring: int = SCORING_L1
    weighting: int = WEIGHTING_TF_IDF

    def __post_init__(self) -> None:
        if not (1 < self.k <= MAX_K and 1 <= self.depth <= MAX_DEPTH):
            raise DatasetError(
                f"vocabulary: need 2 <= k <= {MAX_K} and 1 <= depth <= {MAX_DEPTH}, got k={self.k}, "
                f"depth={self.depth}"
            )
        n = self.parents.shape[0]
        if self.parents.shape != (n,) or n < 2:
            raise DatasetError(f"vocabulary: parents must be (N,) with N >= 2, got {self.parents.shape}")
        if self.descriptors.shape != (n, DESCRIPTOR_BYTES) or self.descriptors.dtype != np.uint8:
            raise DatasetError(
                f"vocabulary: descriptors must be ({n}, {DESCRIPTOR_BYTES}) uint8, "
                f"got {self.descriptors.shape} {self.descriptors.dtype}"
            )
        if self.is_leaf.shape != (n,) or self.weights.shape != (n,):
            raise DatasetError(f"vocabulary: is_leaf and weights must be ({n},)")
        later = self.parents[1:] >= np.arange(1, n)
        if self.parents[0] != -1 or np.any(self.parents[1:] < 0) or np.any(later):
            raise DatasetError("vocabulary: node 0 must be the root and every parent must precede its child")
        if self.is_leaf[0] or not np.all(np.isfinite(self.weights)):
            raise DatasetError("vocabulary: the root cannot be a word and weights must be finite")
        has_child = np.zeros(n, bool)
        has_child[self.parents[1:]] = True
        if np.any(has_child & self.is_leaf) or np.any(~has_child & ~self.is_leaf):
            raise DatasetError("vocabulary: a node is a word exactly when it has no children")

    @property
    def words(self) -> I64:
        """(W,) node ids of the words, in word-id order (DBoW2 numbers words by node order)."""
        return np.flatnonzero(self.is_leaf).astype(np.int64)

    def children(self, node: int) -> I64:
        """Node ids of ``node``'s children, in order."""
        return np.flatnonzero(self.parents == node).astype(np.int64)

    def node_depth(self) -> I64:
        """(N,) depth of each node (root 0)."""
        d = np.zeros(self.parents.shape[0], np.int64)
        for i in range(1, d.shape[0]):
            d[i] = d[self.parents[i]] + 1
        return d

    def leaf_of(self, descriptors: U8) -> I64:
        """(M,) node id of the word each (M, 32) uint8 descriptor falls in.

        Descends from the root to the child with the smallest Hamming distance (the first
        one on a tie), as DBoW2's ``transform`` does.
        """
        desc = _check_descriptors(descriptors, "descriptors")
        kids = dict(_groups(self.parents, np.arange(1, self.parents.shape[0])))
        node = np.zeros(desc.shape[0], np.int64)
        for _ in range(self.depth):
            inner = ~self.is_leaf[node]
            if not inner.any():
                break
            for parent, rows in _groups(node, np.flatnonzero(inner)):
                c = kids[parent]
                node[rows] = c[np.argmin(hamming(desc[rows], self.descriptors[c]), axis=1)]
        return node

    def to_text(self) -> str:
        """The DBoW2 / ORB-SLAM text format (module docstring)."""
        lines = [f"{self.k} {self.depth} {self.scoring} {self.weighting}"]
        for i in range(1, self.parents.shape[0]):
            d = " ".join(str(int(b)) for b in self.descriptors[i])
            lines.append(f"{int(self.parents[i])} {int(self.is_leaf[i])} {d} {float(self.weights[i])!r}")
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_text` to ``path`` (a temporary file renamed into place)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".part")
        try:
            tmp.write_text(self.to_text())
            tmp.replace(path)
        except OSError as exc:
            raise DatasetError(f"cannot write vocabulary {path}: {exc}") from exc


def parse_vocabulary(text: str, source: str = "vocabulary") -> Vocabulary:
    """Read the DBoW2 text format; a malformed line raises :class:`DatasetError` naming it."""
    lines = text.splitlines()
    if not lines:
        raise DatasetError(f"{source}: empty file")
    head = lines[0].split()
    try:
        k, depth, scoring, weighting = (int(x) for x in head)
    except ValueError:
        raise DatasetError(f"{source}:1: expected 'k L scoring weighting', got {lines[0]!r}") from None
    if not (0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise DatasetError(f"{source}:1: scoring must be 0-5 and weighting 0-3, got {scoring} {weighting}")
    body = [ln for ln in lines[1:] if ln.strip()]
    n = len(body) + 1
    parents = np.full(n, -1, np.int64)
    desc = np.zeros((n, DESCRIPTOR_BYTES), np.uint8)
    leaf = np.zeros(n, bool)
    weights = np.zeros(n, np.float64)
    for i, ln in enumerate(body, start=1):
        f = ln.split()
        if len(f) != DESCRIPTOR_BYTES + 3:
            raise DatasetError(f"{source}:{i + 1}: expected {DESCRIPTOR_BYTES + 3} fields, got {len(f)}")
        try:
            parents[i], leaf_flag = int(f[0]), int(f[1])
            values = [int(x) for x in f[2:-1]]
            weights[i] = float(f[-1])
        except ValueError:
            raise DatasetError(f"{source}:{i + 1}: not a number in {ln[:60]!r}") from None
        if leaf_flag not in (0, 1) or not all(0 <= v <= 255 for v in values):
            raise DatasetError(f"{source}:{i + 1}: is_leaf must be 0/1 and descriptor bytes 0-255")
        leaf[i] = leaf_flag == 1
        desc[i] = values
    try:
        return Vocabulary(k, depth, parents, desc, leaf, weights, scoring, weighting)
    except DatasetError as exc:
        raise DatasetError(f"{source}: {exc}") from None


def load_vocabulary(path: str | Path) -> Vocabulary:
    """:func:`parse_vocabulary` of a file."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read vocabulary {path}: {exc}") from exc
    return parse_vocabulary(text, str(path))


def hamming(a: U8, b: U8) -> I64:
    """(M, K) Hamming distances (bits) between (M, 32) and (K, 32) uint8 descriptors."""
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(a64[:, None, :] ^ b64[None, :, :]).sum(axis=2, dtype=np.int64)


def bitwise_median(descriptors: U8) -> U8:
    """(32,) uint8 centre of (M, 32) binary descriptors: each bit set when more than half are."""
    bits = np.unpackbits(descriptors, axis=1)
    counts = bits.sum(axis=0, dtype=np.int64)
    return np.packbits((2 * counts > descriptors.shape[0]).astype(np.uint8))


def _seed_kmeanspp(desc: U8, k: int, rng: np.random.Generator) -> U8:
    """k-means++ seeds (Arthur and Vassilvitskii 2007): each next seed drawn with probability
    proportional to its squared Hamming distance to the nearest seed so far."""
    centres = [desc[rng.integers(desc.shape[0])]]
    nearest = hamming(desc, centres[0][None]).ravel().astype(np.float64)
    while len(centres) < k:
        w = nearest**2
        total = w.sum()
        if total <= 0:  # fewer distinct descriptors than k
            break
        c = desc[rng.choice(desc.shape[0], p=w / total)]
        centres.append(c)
        nearest = np.minimum(nearest, hamming(desc, c[None]).ravel())
    return np.stack(centres)


def kmedians(desc: U8, k: int, rng: np.random.Generator, max_iter: int = 10) -> tuple[U8, I64]:
    """Cluster (M, 32) descriptors into at most ``k`` groups (M > k).

    Returns (C, 32) centres and (M,) labels 0..C-1, every label the nearest centre (the
    first on a tie) of the centres returned, and no group empty.
    """
    centres = _seed_kmeanspp(desc, k, rng)
    labels = np.argmin(hamming(desc, centres), axis=1)
    for _ in range(max_iter):
        used = np.unique(labels)
        centres = np.stack([bitwise_median(desc[labels == c]) for c in used])
        new = np.argmin(hamming(desc, centres), axis=1)
        if np.array_equal(new, np.searchsorted(used, labels)):
            labels = new
            break
        labels = new
    used = np.unique(labels)  # a centre may have lost every member on the last assignment
    return centres[used], np.searchsorted(used, labels).astype(np.int64)


def train_vocabulary(
    images: Sequence[U8],
    *,
    k: int = 10,
    depth: int = 6,
    seed: int = 0,
    max_iter: int = 10,
    progress: Callable[[int, int], None] | None = None,
) -> Vocabulary:
    """Train a vocabulary tree on the ORB descriptors of some images.

    Args:
        images: one (n_i, 32) uint8 descriptor array per training image (n_i may be 0).
        k, depth: branching factor and levels (at most ``k ** depth`` words).
        seed: seeds k-means++; the same input and seed give the same tree.
        max_iter: k-medians rounds per node (it stops earlier once no label changes).
        progress: called as ``progress(level_done, depth)``.

    A group with at most ``k`` descriptors gets one child per descriptor; a group of one
    descriptor is a word above the last level, as in DBoW2.
    """
    sets = [_check_descriptors(d, f"images[{i}]") for i, d in enumerate(images)]
    if not (1 < k <= MAX_K and 1 <= depth <= MAX_DEPTH):
        raise DatasetError(f"vocabulary: need 2 <= k <= {MAX_K} and 1 <= depth <= {MAX_DEPTH}")
    desc = np.concatenate(sets) if sets else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if desc.shape[0] < 2:
        raise DatasetError(f"vocabulary: need at least 2 training descriptors, got {desc.shape[0]}")
    image_of = np.repeat(np.arange(len(sets)), [s.shape[0] for s in sets])
    rng = np.random.default_rng(seed)
    parents, centres = [-1], [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
    node_of = np.zeros(desc.shape[0], np.int64)  # every descriptor's node on the current level
    frontier = [0]
    for level in range(depth):
        next_frontier = []
        members = dict(_groups(node_of, np.arange(desc.shape[0])))
        for parent in frontier:
            rows = members.get(parent, np.zeros(0, np.int64))
            if rows.shape[0] <= 1:
                continue  # a word above the last level
            sub = desc[rows]
            if rows.shape[0] <= k:
                c, lab = sub, np.arange(rows.shape[0])
            else:
                c, lab = kmedians(sub, k, rng, max_iter)
            first = len(parents)
            for ci in range(c.shape[0]):
                parents.append(parent)
                centres.append(c[ci])
                next_frontier.append(first + ci)
            node_of[rows] = first + lab
        frontier = next_frontier
        if progress is not None:
            progress(level + 1, depth)
        log.debug("vocabulary level %d: %d nodes", level + 1, len(frontier))
    par = np.asarray(parents, np.int64)
    has_child = np.zeros(par.shape[0], bool)
    has_child[par[1:]] = True
    leaf = ~has_child
    leaf[0] = False
    # idf (DBoW2 Sec. IV-A): ln(N / n_i), n_i = training images with a descriptor in word i.
    n_i = np.zeros(par.shape[0], np.int64)
    pairs = np.unique(np.stack([node_of, image_of], axis=1), axis=0)
    np.add.at(n_i, pairs[:, 0], 1)
    weights = np.zeros(par.shape[0], np.float64)
    weights[leaf] = np.log(len(sets) / n_i[leaf])
    return Vocabulary(k, depth, par, np.stack(centres), leaf, weights)


def dataset_descriptors(
    folders: Sequence[str | Path],
    *,
    every: int = 1,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[U8]:
    """ORB descriptors of every ``every``-th frame of data-set folders, one array per frame.

    The extractor is the tracker's (``wardmap.edge.features.OrbExtractor``, default
    :class:`OrbConfig`: 1000 features on an 8-level grid), so the words are of the features
    wardmap matches. ``progress(folder, done, total)`` is called per frame.
    """
    import cv2

    from wardmap.edge.features import OrbExtractor
    from wardmap.shared.dataset import DatasetReader

    if every < 1:
        raise DatasetError(f"every must be at least 1, got {every}")
    extractor = OrbExtractor()
    out: list[U8] = []
    for folder in folders:
        reader = DatasetReader(folder)
        picks = range(0, len(reader), every)
        for done, i in enumerate(picks, start=1):
            gray = np.asarray(cv2.cvtColor(reader.frame(i).rgb, cv2.COLOR_RGB2GRAY), np.uint8)
            out.append(_check_descriptors(extractor.extract(gray).descriptors, "extracted descriptors"))
            if progress is not None:
                progress(str(folder), done, len(picks))
    return out


def _groups(node: I64, rows: I64) -> list[tuple[int, I64]]:
    """``rows`` grouped by ``node[rows]``: (node id, its rows) pairs, node ids ascending."""
    order = rows[np.argsort(node[rows], kind="stable")]
    ids, starts = np.unique(node[order], return_index=True)
    return list(zip(ids.tolist(), np.split(order, starts[1:]), strict=True))


def _check_descriptors(d: object, what: str) -> U8:
    a = np.asarray(d)
    if a.ndim != 2 or a.shape[1] != DESCRIPTOR_BYTES or a.dtype != np.uint8:
        raise DatasetError(f"{what}: expected (N, {DESCRIPTOR_BYTES}) uint8 ORB descriptors, got "
                           f"{a.shape} {a.dtype}")
    return np.ascontiguousarray(a)

