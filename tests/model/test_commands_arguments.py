"""The command line's number types: what each accepts and what it rejects, with a message."""

import argparse
import re

import pytest

from visnerf.arg_types import non_negative_float, non_negative_int, positive_float, positive_int, unit_fraction


@pytest.mark.parametrize(
    ("parse", "text", "expected"),
    [
        (positive_float, "0.5", 0.5),
        (positive_float, "1e-3", 1e-3),
        (non_negative_float, "0", 0.0),
        (non_negative_float, "0.01", 0.01),
        (unit_fraction, "0", 0.0),
        (unit_fraction, "1", 1.0),
        (positive_int, "3", 3),
        (non_negative_int, "0", 0),
    ],
)
def test_accepts(parse, text, expected) -> None:
    assert parse(text) == expected


@pytest.mark.parametrize(
    ("parse", "text"),
    [
        (positive_float, "0"),
        (positive_float, "-1"),
        (positive_float, "inf"),
        (positive_float, "nan"),
        (positive_float, "abc"),
        (non_negative_float, "-0.01"),
        (non_negative_float, "inf"),
        (non_negative_float, "nan"),
        (non_negative_float, ""),
        (unit_fraction, "1.5"),
        (unit_fraction, "nan"),
        (positive_int, "0"),
        (non_negative_int, "-1"),
        (non_negative_int, "1.5"),
    ],
)
def test_rejects_naming_the_value(parse, text) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=rf"^expected .*, got {re.escape(repr(text))}$"):
        parse(text)
