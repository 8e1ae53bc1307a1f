"""Command-line helpers shared by the scripts."""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path


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


def _checked(text: str, kind: type, ok, what: str):
    """``kind(text)``, or an ``argparse.ArgumentTypeError`` saying it must be ``what`` unless ``ok`` holds for it."""
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not ok(value):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An argparse ``type=``: an integer > 0."""
    return _checked(text, int, lambda x: x > 0, "an integer > 0")


def nonnegative_int(text: str) -> int:
    """An argparse ``type=``: an integer >= 0."""
    return _checked(text, int, lambda x: x >= 0, "an integer >= 0")


def positive_float(text: str) -> float:
    """An argparse ``type=``: a finite number > 0."""
    return _checked(text, float, lambda x: 0 < x < math.inf, "a finite number > 0")


def nonnegative_float(text: str) -> float:
    """An argparse ``type=``: a finite number >= 0."""
    return _checked(text, float, lambda x: 0 <= x < math.inf, "a finite number >= 0")


def int_range(lo: int, hi: int):
    """An argparse ``type=`` accepting an integer in [lo, hi]."""

    def parse(text: str) -> int:
        return _checked(text, int, lambda x: lo <= x <= hi, f"an integer from {lo} to {hi}")

    return parse


def torch_device(text: str):
    """An argparse ``type=``: a torch device this machine can use, cpu, cuda or cuda:N."""
    import torch

    try:
        device = torch.device(text)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"must be cpu, cuda or cuda:N, got {text!r}")
    from cfd_torch._validate import usable_device

    try:
        return usable_device(device)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not available here ({err.__cause__ or err})") from None


def folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be an output folder (it, or the nearest of its parents that exists, is not a folder or
    not one this process can write in: a folder made there and removed at once tells; or it is a link to nothing),
    else None."""
    if path.is_symlink() and not path.exists():
        return f"{path}: a link to {os.readlink(path)}, which does not exist"
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                return f"{path}: {p} is a file; give a folder"
            try:
                os.rmdir(tempfile.mkdtemp(prefix=".write-check-", dir=p))
            except OSError as e:
                return f"{path}: cannot write in {p} ({e.strerror or e})"
            return None
    return None


def read_sweep(path: Path) -> dict:
    """``scripts/sweep.py``'s ``sweep.json`` at ``path``: a JSON object whose "runs" is a list of runs, each an
    object with a "config" object naming its task, model and seed; a ValueError saying what is wrong otherwise."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable JSON file ({e})") from None
    runs = data.get("runs") if isinstance(data, dict) else None
    if not isinstance(runs, list):
        raise ValueError(f'{path}: not a sweep.json (a JSON object with a list of runs under "runs")')
    for k, r in enumerate(runs):
        c = r.get("config") if isinstance(r, dict) else None
        if not (isinstance(c, dict) and all(key in c for key in ("task", "model", "seed"))):
            raise ValueError(f"{path}: run {k} has no config naming its task, model and seed")
    return data


def interrupted(e: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in the chain of ``e`` (numba re-raises one inside its kernels as a
    SystemError "returned a result with an exception set"): a script that keeps going past a failed run stops."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False
