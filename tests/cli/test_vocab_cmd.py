"""``wardmap vocab train``: a vocabulary from a real recording; bad input in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from procs import one_line_error, wardmap

from wardmap.tools.vocabulary import load_vocabulary

TUM = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"


@pytest.mark.skipif(not TUM.is_dir(), reason="../shared TUM excerpt absent")
def test_train_on_tum_excerpt_then_refuse_to_overwrite(tmp_path: Path) -> None:
    """Every 25th frame of the TUM excerpt (4 frames) into a k=4, L=2 tree: the file loads back
    with at most 16 words and the JSON summary agrees; a second run without --force refuses and
    leaves the file as it was."""
    out = tmp_path / "voc.txt"
    args = ("vocab", "train", str(TUM), "--every", "25", "--k", "4", "--depth", "2", "--out", str(out))
    p = wardmap(*args)
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout.strip().splitlines()[-1])
    voc = load_vocabulary(out)
    assert summary["images"] == 4 and summary["descriptors"] > 1000
    assert summary["words"] == voc.words.shape[0] and 1 < summary["words"] <= 16
    assert (voc.k, voc.depth) == (4, 2)
    before = out.read_text()
    one_line_error(wardmap(*args), "add --force", "vocab")
    assert out.read_text() == before


@pytest.mark.parametrize(
    ("extra", "needle"),
    [(("--k", "30"), "--k must be 2-20"), (("--depth", "0"), "--depth must be 1-10"),
     (("--every", "0"), "--every must be at least 1")],
)
def test_bad_options(tmp_path: Path, extra: tuple[str, str], needle: str) -> None:
    """Out-of-range options: one line, exit 1, nothing written."""
    out = tmp_path / "voc.txt"
    one_line_error(wardmap("vocab", "train", str(tmp_path), "--out", str(out), *extra), needle, "vocab")
    assert not out.exists()


def test_missing_dataset(tmp_path: Path) -> None:
    """A data-set folder that does not exist: one line naming it."""
    one_line_error(wardmap("vocab", "train", str(tmp_path / "nope"), "--out", str(tmp_path / "v.txt")),
                   "not a data-set folder", "vocab")
