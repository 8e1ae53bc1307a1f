"""Provenance of benchmark results: which library commit produced them (shared by the scripts)."""

from __future__ import annotations

import subprocess


def git_revision() -> str | None:
    """Short commit of HEAD, with "+dirty" when cfd_torch/ has uncommitted changes; None outside a git checkout."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "cfd_torch"], capture_output=True, text=True
        ).stdout
        return rev.stdout.strip() + ("+dirty" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return None
