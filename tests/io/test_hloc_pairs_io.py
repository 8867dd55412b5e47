"""hloc pairs files: order-preserving round trip and errors."""

from __future__ import annotations

import pytest

from planarloc.geometry.validation import InputError
from planarloc.io import FormatError, read_hloc_pairs, write_hloc_pairs


def test_round_trip_preserves_order(tmp_path):
    pairs = {"q/b.png": ["db/3.png", "db/1.png", "db/2.png"], "q/a.png": ["db/9.png"]}
    path = tmp_path / "pairs" / "pairs-netvlad.txt"
    write_hloc_pairs(path, pairs)
    assert path.read_text().splitlines()[:2] == ["q/b.png db/3.png", "q/b.png db/1.png"]
    got = read_hloc_pairs(path)
    assert got == pairs and list(got) == ["q/b.png", "q/a.png"]


def test_read_skips_comments_and_duplicates(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_text("# pairs\nq1 d1\n\nq2 d1\nq1 d2\nq1 d1\n")
    assert read_hloc_pairs(path) == {"q1": ["d1", "d2"], "q2": ["d1"]}


def test_errors(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_text("q1 d1\nq2\n")
    with pytest.raises(FormatError, match=r"pairs\.txt:2: expected 2 names 'query_name db_name', found 1"):
        read_hloc_pairs(path)
    with pytest.raises(FormatError, match=r"missing\.txt: file not found"):
        read_hloc_pairs(tmp_path / "missing.txt")
    with pytest.raises(InputError, match="whitespace"):
        write_hloc_pairs(tmp_path / "out.txt", {"q 1": ["d"]})
