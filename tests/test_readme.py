"""The Python examples of the README and of the manual's pages in docs/ run as written (each in a fresh namespace): a
newcomer copies them first. Every relative link of those pages points at a file of the repository."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]


def _examples(page: Path) -> list[tuple[str, str]]:
    """(the section heading above it, the code) of every ```python block of a page, in order."""
    out, heading = [], ""
    for part in re.split(r"(^```python\n.*?^```)", page.read_text(), flags=re.S | re.M):
        if part.startswith("```python"):
            out.append((heading, part[len("```python\n") : -3]))
        else:
            titles = re.findall(r"^#+ (.+)$", part, flags=re.M)
            heading = titles[-1] if titles else heading
    return out


EXAMPLES = [(page, heading, code) for page in PAGES for heading, code in _examples(page)]


def test_the_readme_has_its_examples():
    headings = [h for p, h, _ in EXAMPLES if p == README]
    assert len(headings) >= 5 and "Using it: the pair potential" in headings, headings
    assert "Articulated bodies" in headings and "Environments: `cfd_torch.envs`" in headings, headings


@pytest.mark.parametrize(
    "page, code", [(p, c) for p, _, c in EXAMPLES], ids=[f"{p.name}: {h}" for p, h, _ in EXAMPLES]
)
def test_an_example_runs(page, code):
    namespace = {"__name__": "readme_example"}
    exec(compile(code, str(page), "exec"), namespace)
    assert len(namespace) > 2  # it defined what it shows


def _links(page: Path) -> list[str]:
    """The relative targets of a page's markdown links and images (anchors and web addresses left out)."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)  # not inside code blocks
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t.split("#")[0] for t in targets if not re.match(r"(https?:|mailto:|#)", t)]


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_every_relative_link_resolves(page):
    links = _links(page)
    missing = [t for t in links if not (page.parent / t).exists()]
    assert not missing, f"{page.name}: links to missing files {missing}"
