"""The README's Python examples run as written (each in a fresh namespace): a newcomer copies them first."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _examples() -> list[tuple[str, str]]:
    """(the section heading above it, the code) of every ```python block of the README, in order."""
    out, heading = [], ""
    for part in re.split(r"(^```python\n.*?^```)", README.read_text(), flags=re.S | re.M):
        if part.startswith("```python"):
            out.append((heading, part[len("```python\n") : -3]))
        else:
            titles = re.findall(r"^#+ (.+)$", part, flags=re.M)
            heading = titles[-1] if titles else heading
    return out


EXAMPLES = _examples()


def test_the_readme_has_its_examples():
    headings = [h for h, _ in EXAMPLES]
    assert len(EXAMPLES) >= 5 and "Using it" in headings and "Articulated bodies" in headings, headings


@pytest.mark.parametrize("code", [c for _, c in EXAMPLES], ids=[h for h, _ in EXAMPLES])
def test_a_readme_example_runs(code):
    namespace = {"__name__": "readme_example"}
    exec(compile(code, str(README), "exec"), namespace)
    assert len(namespace) > 2  # it defined what it shows
