"""Argument types for the command line: each turns an option's text into a value or raises
``argparse.ArgumentTypeError`` naming the range it expected and the text it got."""

import argparse
import math
from collections.abc import Callable


def number(text: str) -> float:
    """``text`` as a float, NaN when it is not a number (the callers' range checks reject NaN)."""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def positive_float(text: str) -> float:
    """A finite number above zero."""
    value = number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number above 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number of at least zero."""
    value = number(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number of at least 0, got {text!r}")
    return value


def unit_fraction(text: str) -> float:
    """A number in [0, 1]."""
    value = number(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1], got {text!r}")
    return value


def whole_number(text: str, least: int, words: str) -> int:
    """``text`` as a whole number of at least ``least``; ``words`` names the range in the error."""
    try:
        value = int(text)
    except ValueError:
        value = least - 1
    if value < least:
        raise argparse.ArgumentTypeError(f"expected a whole number {words}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """A whole number, 1 or more."""
    return whole_number(text, 1, "above 0")


def non_negative_int(text: str) -> int:
    """A whole number, 0 or more."""
    return whole_number(text, 0, ">= 0")


def whole_number_at_least(least: int) -> Callable[[str], int]:
    """The argument type of a whole number of at least ``least``."""
    return lambda text: whole_number(text, least, f"of at least {least}")


DEVICE_HELP = "auto (CUDA when present), cpu, cuda or cuda:N"


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device``, as every command that runs a model takes it (``runtime.pick_device`` reads it)."""
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
