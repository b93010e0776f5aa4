"""The ORB vocabulary trainer (tools/vocabulary.py): tree shape, leaves, idf, DBoW2 text."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.shared.errors import DatasetError
from wardmap.tools.vocabulary import (
    bitwise_median,
    hamming,
    kmedians,
    parse_vocabulary,
    train_vocabulary,
)


def _flip(d: np.ndarray, n_bits: int, rng: np.random.Generator) -> np.ndarray:
    """``d`` (32,) uint8 with ``n_bits`` distinct random bits flipped."""
    bits = np.unpackbits(d)
    bits[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits)


def _hierarchy(k: int, depth: int, per_leaf: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors in ``k ** depth`` known clusters nested like a tree: each child centre is its
    parent's with 40 bits flipped, each descriptor its leaf centre with 4 bits flipped.
    Returns (M, 32) descriptors and (M,) their true cluster."""
    level = [rng.integers(0, 256, 32, dtype=np.uint8)]
    for _ in range(depth):
        level = [_flip(c, 40, rng) for c in level for _ in range(k)]
    desc = np.stack([_flip(c, 4, rng) for c in level for _ in range(per_leaf)])
    return desc, np.repeat(np.arange(len(level)), per_leaf)


def test_hamming_and_majority_median() -> None:
    """Hamming counts differing bits; the median sets a bit when more than half the inputs do."""
    a = np.zeros((1, 32), np.uint8)
    b = np.zeros((2, 32), np.uint8)
    b[0, 0] = 0b1011
    b[1, 31] = 0xFF
    assert hamming(a, b).tolist() == [[3, 8]]
    d = np.zeros((3, 32), np.uint8)
    d[0, 5] = 0b111
    d[1, 5] = 0b011
    d[2, 5] = 0b001
    m = bitwise_median(d)
    assert m[5] == 0b011 and np.count_nonzero(m) == 1


def test_kmedians_labels_are_nearest_centres() -> None:
    """Every label is the nearest of the returned centres, and no group is empty."""
    rng = np.random.default_rng(3)
    desc = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    centres, labels = kmedians(desc, 8, rng)
    d = hamming(desc, centres)
    assert np.array_equal(labels, np.argmin(d, axis=1))
    assert set(labels.tolist()) == set(range(centres.shape[0]))


def test_tree_shape_and_leaves_recover_known_clusters() -> None:
    """On nested synthetic clusters the tree has k children per inner node and k**L words at
    depth L; each descriptor lands in the word of its own cluster, one word per cluster."""
    rng = np.random.default_rng(7)
    k, depth = 3, 2
    desc, truth = _hierarchy(k, depth, 12, rng)
    images = np.array_split(desc, 6)
    voc = train_vocabulary(images, k=k, depth=depth, seed=1)
    inner = np.flatnonzero(~voc.is_leaf)
    assert all(voc.children(int(i)).shape[0] == k for i in inner)
    assert voc.words.shape[0] == k**depth
    assert np.all(voc.node_depth()[voc.words] == depth)
    leaf = voc.leaf_of(desc)
    for c in range(k**depth):
        assert np.unique(leaf[truth == c]).shape[0] == 1
    assert np.unique(leaf).shape[0] == k**depth
    # A fresh noisy copy of a cluster's descriptor still lands in that cluster's word.
    probe = np.stack([_flip(d, 3, rng) for d in desc[::12]])
    assert np.array_equal(voc.leaf_of(probe), leaf[::12])


def test_training_descriptors_land_in_their_training_leaf_and_idf() -> None:
    """On random descriptors (no structure) descending the tree reproduces each training
    descriptor's partition, and a word's weight is ln(N / images holding it)."""
    rng = np.random.default_rng(11)
    images = [rng.integers(0, 256, (n, 32), dtype=np.uint8) for n in (120, 80, 0, 150)]
    voc = train_vocabulary(images, k=4, depth=3, seed=2)
    assert voc.words.shape[0] <= 4**3
    leaf = voc.leaf_of(np.concatenate(images))
    assert np.all(voc.is_leaf[leaf])
    image_of = np.repeat(np.arange(4), [120, 80, 0, 150])
    for w in voc.words:
        holders = np.unique(image_of[leaf == w]).shape[0]
        assert holders >= 1
        assert voc.weights[w] == pytest.approx(np.log(4 / holders))
    assert np.all(voc.weights[~voc.is_leaf] == 0)


def test_same_seed_same_tree() -> None:
    """Training is deterministic for a seed."""
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(3)]
    assert train_vocabulary(images, k=5, depth=2, seed=9).to_text() == train_vocabulary(
        images, k=5, depth=2, seed=9).to_text()


def test_text_round_trip_and_format() -> None:
    """The DBoW2 text: header 'k L 0 0', one line per non-root node with 35 fields whose
    parent precedes it; parsing it gives the same tree and the same text."""
    rng = np.random.default_rng(13)
    images = [rng.integers(0, 256, (90, 32), dtype=np.uint8) for _ in range(5)]
    voc = train_vocabulary(images, k=3, depth=3, seed=0)
    text = voc.to_text()
    lines = text.splitlines()
    assert lines[0] == "3 3 0 0"
    assert len(lines) == voc.parents.shape[0]
    for i, line in enumerate(lines[1:], start=1):
        f = line.split()
        assert len(f) == 35 and int(f[0]) < i and f[1] in ("0", "1")
    back = parse_vocabulary(text)
    assert np.array_equal(back.parents, voc.parents)
    assert np.array_equal(back.descriptors, voc.descriptors)
    assert np.array_equal(back.is_leaf, voc.is_leaf)
    assert np.array_equal(back.weights, voc.weights)
    assert back.to_text() == text


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty"),
        ("10 6\n", "k L scoring weighting"),
        ("30 2 0 0\n0 1" + " 0" * 32 + " 0.5\n", "k <= 20"),
        ("2 1 0 0\n0 1" + " 0" * 31 + " 0.5\n", "expected 35 fields"),
        ("2 1 0 0\n0 1" + " 0" * 31 + " 256 0.5\n", "0-255"),
        ("2 1 0 0\n5 1" + " 0" * 32 + " 0.5\n", "parent must precede"),
        ("2 1 0 0\n0 0" + " 0" * 32 + " 0\n", "exactly when it has no children"),
    ],
)
def test_malformed_text_is_refused(text: str, match: str) -> None:
    """Each kind of malformed file raises DatasetError saying what is wrong."""
    with pytest.raises(DatasetError, match=match):
        parse_vocabulary(text)


def test_bad_training_input_is_refused() -> None:
    """Wrong descriptor shapes or too few descriptors raise DatasetError."""
    with pytest.raises(DatasetError, match="uint8 ORB descriptors"):
        train_vocabulary([np.zeros((4, 16), np.uint8)])
    with pytest.raises(DatasetError, match="at least 2"):
        train_vocabulary([np.zeros((1, 32), np.uint8)])
