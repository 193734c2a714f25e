"""argparse types of the command line's numbers: a bad value gets the usage line and exit status 2.

Standard library only, so that the parser (`cli_parser`) builds without importing numpy.
"""

from __future__ import annotations

import argparse
import math

__all__ = ["finite_number", "positive_number", "nonnegative_number", "seed_number", "count_number", "zero_or_count"]


def finite_number(text: str) -> float:
    """A finite real number (argparse type): `nan`, `inf`, `1e999` and `0.1+1j` are refused."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_number(text: str) -> float:
    """A finite number above zero (argparse type), e.g. a noise standard deviation."""
    value = finite_number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}")
    return value


def nonnegative_number(text: str) -> float:
    """A finite number of at least zero (argparse type), e.g. a simulated error's standard deviation."""
    value = finite_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number of at least 0, got {text!r}")
    return value


def _whole(text: str, minimum: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{what}, got {value}")
    return value


def seed_number(text: str) -> int:
    """A random seed (argparse type): a whole number of at least 0."""
    return _whole(text, 0, "a seed is a whole number of at least 0")


def count_number(text: str) -> int:
    """A count of at least 1 (argparse type): poses, iterations, candidates."""
    return _whole(text, 1, "expected at least 1")


def zero_or_count(text: str) -> int:
    """A count of at least 0 (argparse type)."""
    return _whole(text, 0, "expected at least 0")
