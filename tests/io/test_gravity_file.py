"""Per-image gravity files 'name gx gy gz'."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.io import FormatError, read_gravity_file


def test_read_normalises_and_skips_comments(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("# name gx gy gz\n\nq/1.png 0 2 0\n  q/2.png 0.0 -3 4  \n")
    g = read_gravity_file(path)
    assert list(g) == ["q/1.png", "q/2.png"]
    np.testing.assert_allclose(g["q/1.png"], [0, 1, 0])
    np.testing.assert_allclose(g["q/2.png"], [0, -0.6, 0.8])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a.png 0 1 0\na.png 0 1 0\n", r"g.txt:2: expected unique names, found 'a.png' again \(line 1\)"),
        ("a.png 0 1 x\n", r"g.txt:1: expected a number in column 4 \(gravity component\), found 'x'"),
        ("a.png 0 1 0 0\n", r"g.txt:1: expected 4 fields 'name gx gy gz', found 5"),
        ("a.png 0 0 0\n", r"g.txt:1: expected a non-zero gravity direction"),
        ("a.png inf 1 0\n", r"g.txt:1: expected a finite number in column 2"),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, message):
    (tmp_path / "g.txt").write_text(text)
    with pytest.raises(FormatError, match=message):
        read_gravity_file(tmp_path / "g.txt")
    with pytest.raises(FormatError, match="file not found"):
        read_gravity_file(tmp_path / "missing.txt")
