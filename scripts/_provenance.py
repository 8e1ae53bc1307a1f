"""Provenance of benchmark results: which library commit produced them (shared by the scripts)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
from pathlib import Path

# the checkout these scripts belong to (git runs there, whatever the working directory)
_ROOT = Path(__file__).resolve().parent.parent


# set by scripts/sweep.py --ray for its jobs: their scripts are a copy outside the checkout (Ray's working_dir)
REVISION_ENV = "CFD_TORCH_REVISION"


def git_revision() -> str | None:
    """Short commit of this checkout's HEAD, with "+dirty" when the library (cfd_torch/, envs/) or the scripts have
    uncommitted changes; when the scripts are not in a git checkout, ``$CFD_TORCH_REVISION`` (the sweep's
    checkout's, for a copy shipped to Ray) or None."""
    fallback = os.environ.get(REVISION_ENV) or None
    try:
        top = subprocess.run(
            ["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, check=True, cwd=_ROOT
        ).stdout.strip()
        if Path(top).resolve() != _ROOT:  # the scripts sit in some other repository's tree
            return fallback
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True, cwd=_ROOT
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "cfd_torch", "envs", "scripts"], capture_output=True, text=True,
            cwd=_ROOT,
        ).stdout  # fmt: skip
        return rev.stdout.strip() + ("+dirty" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return fallback


def git_commit(rev: str) -> str:
    """An argparse ``type=`` for a revision to compare with (``--baseline REV``): ``rev`` as given, once it names a
    commit of this checkout, else an ``argparse.ArgumentTypeError`` (before a run it would otherwise end)."""
    try:
        found = subprocess.run(
            ["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"], capture_output=True, text=True,
            cwd=_ROOT,
        )  # fmt: skip
    except OSError as e:
        raise argparse.ArgumentTypeError(f"cannot run git to find {rev!r}: {e}") from None
    if found.returncode != 0 or rev.startswith("-"):
        raise argparse.ArgumentTypeError(f"{rev!r} is not a commit of the checkout at {_ROOT}")
    return rev


def json_args(args: argparse.Namespace) -> dict:
    """A script's parsed options as JSON values (lists and numbers as such; paths and other objects as text)."""
    return json.loads(json.dumps(vars(args), default=str))
