"""The scripts' presets (``--quick``) fill only the options the command line does not give (scripts/_cli.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


@pytest.fixture
def scripts_path():
    sys.path.insert(0, str(SCRIPTS))
    yield
    sys.path.remove(str(SCRIPTS))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--phases", type=int, default=16)
    p.add_argument("--schemes", nargs="+", default=["plain"])
    p.add_argument("--out", type=Path, default=Path("results/x"))
    return p


def test_a_preset_keeps_an_option_given_with_its_default_value(scripts_path):
    from _cli import apply_preset, given

    p = _parser()
    argv = ["--quick", "--phases", "16"]  # the default value, given explicitly
    assert given(p, argv) == {"quick", "phases"}
    args = p.parse_args(argv)
    apply_preset(p, args, {"phases": 8, "schemes": ["sub:4"]}, argv)
    assert args.phases == 16 and args.schemes == ["sub:4"] and args.out == Path("results/x")
    # the parser's defaults are restored after the probe
    assert p.parse_args([]).phases == 16 and p.get_default("schemes") == ["plain"]


def test_stacked_books_quick_keeps_an_explicit_board_count(scripts_path, monkeypatch):
    import stacked_books

    monkeypatch.setattr(sys, "argv", ["stacked_books.py", "--quick", "--boards", "20"])
    assert stacked_books.parse_args().boards == 20
    monkeypatch.setattr(sys, "argv", ["stacked_books.py", "--quick"])
    assert stacked_books.parse_args().boards == 5
