"""Option values of the wrong kind are one error line naming the option, for every typed option of
every dataset format, on the command line and in the library."""

from __future__ import annotations

import pytest

from planarloc.cli.main import main
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import FORMATS, format_options, option_kind, read_dataset

TYPED = [
    (fmt, key, option_kind(fmt, key))
    for fmt in sorted(FORMATS)
    for key in format_options(fmt)
    if option_kind(fmt, key) != "text"
]
BAD = {
    "int": ["abc", "1.5", "9" * 40, "0x10"],
    "float": ["fast", "nan", "inf", "1_0"],
    "bool": ["maybe", "2"],
}


def test_every_format_has_typed_options() -> None:
    assert {kind for _, _, kind in TYPED} == {"int", "float", "bool"}
    assert ("rosbag", "every", "int") in TYPED and ("tum", "max_dt", "float") in TYPED


@pytest.mark.parametrize("fmt,key,kind", TYPED)
def test_a_bad_value_names_the_option(fmt, key, kind, tmp_path, capsys) -> None:
    for value in BAD[kind]:
        code = main(
            [
                "map",
                "build",
                str(tmp_path / "data"),
                "-f",
                fmt,
                "--dataset-option",
                f"{key}={value}",
                "--out",
                str(tmp_path / "m.db"),
            ]
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1, err
        assert (
            err[0].startswith(f"planarloc map build: error: --dataset-option {key}=") and "expected" in err[0]
        )
        with pytest.raises(InputError, match=f"{key}="):
            read_dataset(tmp_path / "data", fmt, **{key: value})
    assert not (tmp_path / "m.db").exists()


def test_unknown_options_list_the_format_options(tmp_path, capsys) -> None:
    assert (
        main(
            [
                "map",
                "build",
                str(tmp_path),
                "-f",
                "rosbag",
                "--dataset-option",
                "evry=2",
                "--out",
                str(tmp_path / "m.db"),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "--dataset-option evry=2: format rosbag has no option 'evry'" in err and "every" in err
