"""Command-line helpers shared by the scripts."""

from __future__ import annotations

import argparse
from collections.abc import Sequence


def given(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> set[str]:
    """The destinations of the options that the command line ``argv`` (default ``sys.argv[1:]``) gives, whatever
    their values: a preset such as ``--quick`` fills only the others, so an option given with its default value is
    kept."""
    saved = [a.default for a in parser._actions]
    try:
        for a in parser._actions:
            a.default = argparse.SUPPRESS
        return set(vars(parser.parse_args(argv)))
    finally:
        for a, d in zip(parser._actions, saved, strict=True):
            a.default = d


def apply_preset(
    parser: argparse.ArgumentParser, args: argparse.Namespace, preset: dict, argv: Sequence[str] | None = None
) -> None:
    """Set each option of ``preset`` (destination -> value) on ``args`` unless the command line gave it."""
    explicit = given(parser, argv)
    for name, value in preset.items():
        if name not in explicit:
            setattr(args, name, value)
