"""The scalar option checks of planarloc.geometry.validation: what passes, and a one-line
message that names the option, says what was expected and shows what was passed."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.validation import InputError, check_integer, check_positive


@pytest.mark.parametrize("value", [3, 7, np.int64(3), np.int32(100)])
def test_integers_at_the_minimum_or_above_pass(value: object) -> None:
    check_integer("Opts.count", value, 3)


@pytest.mark.parametrize("value", [2, -1, True, 3.0, "3", None, np.float64(4.0)])
def test_other_values_name_the_option(value: object) -> None:
    with pytest.raises(InputError) as info:
        check_integer("Opts.count", value, 3)
    assert str(info.value) == f"Opts.count: expected an integer >= 3, got {value!r}"


def test_an_optional_integer_accepts_none_and_says_so() -> None:
    check_integer("Opts.size", None, 16, allow_none=True)
    check_integer("Opts.size", 16, 16, allow_none=True)
    with pytest.raises(InputError, match=r"^Opts\.size: expected None or an integer >= 16, got 8$"):
        check_integer("Opts.size", 8, 16, allow_none=True)


@pytest.mark.parametrize("value", [1e-9, 2, 0.5, np.float32(0.1), np.int64(1)])
def test_finite_positive_numbers_pass(value: object) -> None:
    check_positive("Opts.scale", value)


@pytest.mark.parametrize("value", [0, 0.0, -1.5, np.inf, np.nan, True, "1", None])
def test_zero_negative_non_finite_and_non_numbers_are_refused(value: object) -> None:
    with pytest.raises(InputError) as info:
        check_positive("Opts.scale", value)
    assert str(info.value) == f"Opts.scale: expected a finite number > 0, got {value!r}"


def test_an_optional_positive_number_accepts_none_and_says_so() -> None:
    check_positive("Opts.tau", None, allow_none=True)
    with pytest.raises(InputError, match=r"^Opts\.tau: expected None or a finite number > 0, got inf$"):
        check_positive("Opts.tau", float("inf"), allow_none=True)
