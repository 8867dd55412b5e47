"""Every JSON planarloc writes is strict JSON: no NaN or Infinity, absent values are null (issue 32)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from planarloc.cli.report import write_json
from planarloc.io import strict_json
from planarloc.io.results import ResultsWriter


def test_non_finite_numbers_become_null_and_numpy_plain_types() -> None:
    record = {
        "std": float("inf"),
        "err": float("nan"),
        "neg": -np.inf,
        "ok": np.float32(0.5),
        "n": np.int64(3),
        "flag": np.bool_(True),
        "cov": np.array([[1.0, np.nan], [np.inf, 2.0]]),
        "pair": (1.5, float("nan")),
        7: "key",
    }
    text = strict_json.dumps(record)
    back = strict_json.loads_strict(text)
    assert back == {
        "std": None,
        "err": None,
        "neg": None,
        "ok": 0.5,
        "n": 3,
        "flag": True,
        "cov": [[1.0, None], [None, 2.0]],
        "pair": [1.5, None],
        "7": "key",
    }


def test_the_strict_reader_rejects_what_python_writes_by_default() -> None:
    loose = json.dumps({"std": float("inf"), "err": float("nan")})
    for bad in (loose, '{"a": -Infinity}'):
        with pytest.raises(ValueError, match="not strict JSON"):
            strict_json.loads_strict(bad)
    with pytest.raises(TypeError):  # an object JSON has no type for is an error, not a guess
        strict_json.dumps({"x": object()})


def test_a_failed_frames_record_file_is_strict_json(tmp_path: Path) -> None:
    writer = ResultsWriter(tmp_path / "poses.txt", tmp_path / "records")
    failed = {
        "name": "q.png",
        "status": "lost",
        "success": False,
        "position_std_m": float("inf"),
        "rotation_std_deg": float("nan"),
        "quat_wxyz": None,
        "t": None,
        "covariance": np.full((6, 6), np.inf),
    }
    writer.add(failed)
    writer.close()
    record = strict_json.loads_strict((tmp_path / "records" / "q.png.json").read_text())
    assert record["position_std_m"] is None and record["rotation_std_deg"] is None
    assert record["covariance"] == [[None] * 6] * 6


def test_report_json_is_strict(tmp_path: Path) -> None:
    path = tmp_path / "summary.json"
    write_json(
        path, {"median_translation_error_m": float("nan"), "stream": {"late": 2, "p99_ms": np.float64(7.5)}}
    )
    assert strict_json.loads_strict(path.read_text()) == {
        "median_translation_error_m": None,
        "stream": {"late": 2, "p99_ms": 7.5},
    }
