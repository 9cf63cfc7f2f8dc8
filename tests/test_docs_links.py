"""The user docs point at files that exist.

Every relative markdown link (`[text](path)`, images included) in README.md, CHANGELOG.md and docs/*.md
must name an existing file or folder, resolved from the linking file's folder; and every path of the
form docs/NAME.md or benchmarks/results/NAME named in their text (code spans included) must exist in the
repository. Links to web pages and in-page anchors are not checked.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
NAMED_PATH = re.compile(r"(?<![\w/.-])((?:docs/[\w.-]+\.md)|(?:benchmarks/results/[\w.-]+))")


def user_docs() -> list[Path]:
    return [REPO / "README.md", REPO / "CHANGELOG.md"] + sorted((REPO / "docs").glob("*.md"))


def relative_links(text: str) -> list[str]:
    """The link targets of `text` that are files of this repository (no scheme, no bare anchor), anchors cut."""
    out = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue
        out.append(target.split("#", 1)[0])
    return out


def test_the_link_pattern_finds_relative_links_and_skips_web_pages_and_anchors():
    text = ("see [a](docs/a.md), ![fig](figures/x.png \"title\"), [web](https://example.org/x.md), "
            "[here](#section), [b](../b.md#part)")
    assert relative_links(text) == ["docs/a.md", "figures/x.png", "../b.md"]


@pytest.mark.parametrize("doc", user_docs(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(doc):
    assert doc.is_file(), f"{doc} is missing"
    missing = [t for t in relative_links(doc.read_text(encoding="utf-8")) if not (doc.parent / t).exists()]
    assert not missing, f"{doc.relative_to(REPO)} links to missing files: {missing}"


@pytest.mark.parametrize("doc", user_docs(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_named_docs_or_results_path_exists(doc):
    text = doc.read_text(encoding="utf-8")
    named = {m.rstrip(".,;:") for m in NAMED_PATH.findall(text)}
    missing = sorted(p for p in named if not (REPO / p).exists())
    assert not missing, f"{doc.relative_to(REPO)} names missing files: {missing}"
