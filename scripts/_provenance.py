"""Provenance of benchmark results: which library commit produced them (shared by the scripts)."""

from __future__ import annotations

import subprocess
from pathlib import Path

# the checkout these scripts belong to (git runs there, whatever the working directory)
_ROOT = Path(__file__).resolve().parent.parent


def git_revision() -> str | None:
    """Short commit of this checkout's HEAD, with "+dirty" when the library (cfd_torch/, envs/) or the scripts have
    uncommitted changes; None when the scripts are not in a git checkout."""
    try:
        top = subprocess.run(
            ["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, check=True, cwd=_ROOT
        ).stdout.strip()
        if Path(top).resolve() != _ROOT:  # the scripts sit in some other repository's tree
            return None
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True, cwd=_ROOT
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "cfd_torch", "envs", "scripts"], capture_output=True, text=True,
            cwd=_ROOT,
        ).stdout  # fmt: skip
        return rev.stdout.strip() + ("+dirty" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return None
