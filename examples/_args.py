"""Argument types shared by the example scripts: a bad value ends in argparse's own one-line
usage error (exit 2) before any work, never in a traceback after minutes of solving
(issue 51). Imported as `from _args import folder, number` (a script's folder is on
`sys.path` when it runs)."""

import argparse
import math
import os


def number(kind, low, high=None, *, above=False, finite=True):
    """An argparse `type`: a `kind` (int or float) >= `low` (> with `above`), <= `high`, and
    finite unless `finite=False`; anything else ends in argparse's one-line usage error
    (exit 2) before any work, never in a traceback of the run."""
    show = (lambda v: f"{v:,}") if kind is int else (lambda v: f"{v:g}")

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an int' if kind is int else 'a number'}; got {text!r}"
            ) from None
        ok = kind is int or not (math.isnan(value) or (finite and math.isinf(value)))
        ok = ok and (value > low if above else value >= low) and (high is None or value <= high)
        if not ok:
            if kind is int and high is not None:
                bound = f"in {show(low)}..{show(high)}"
            else:
                bound = f"{'>' if above else '>='} {show(low)}" + ("" if high is None else f" and <= {show(high)}")
            finite_text = "finite and " if kind is float and finite and high is None else ""
            raise argparse.ArgumentTypeError(f"must be {finite_text}{bound}; got {text}")
        return value

    return parse


def folder(text):
    """An argparse `type`: a folder to write into (created if missing); not empty, not a file."""
    if not text:
        raise argparse.ArgumentTypeError("must not be empty")
    if os.path.exists(text) and not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a file, not a folder")
    return text
