"""The README and docs/: a user's README (short, no lab notebook), links and cited files that exist, real
set-up commands."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
README_MAX_LINES = 350

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
# a repository path in code spans or prose: bench/x.py, services/a/b.py, scripts/..., examples/..., tests/...
CITED_PATH = re.compile(
    r"(?<![\w./-])((?:bench|services|scripts|examples|tests|deploy|migrations)/[\w./-]*[\w/])"
)
# what a lab notebook says and a user's page does not
NARRATIVE = [
    re.compile(r"\bround \d+", re.IGNORECASE),
    re.compile(r"\brounds \d+", re.IGNORECASE),
    re.compile(r"\bissue \d+", re.IGNORECASE),
    re.compile(r"\bwe tried\b", re.IGNORECASE),
    re.compile(r"\bbefore ?(?:->|/) ?after\b", re.IGNORECASE),
]


def _page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


def _slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    anchors: set[str] = set()
    in_code = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and line.startswith("#"):
            anchors.add(_slug(line.lstrip("#")))
    return anchors


def _prose(page: Path) -> str:
    return page.read_text()


def test_docs_folder_has_pages() -> None:
    assert DOCS, "docs/ holds no Markdown page"


def test_readme_is_short() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, at most {README_MAX_LINES}"


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            broken.append(f"{target} (no {dest})")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target} (no heading #{anchor} in {dest.name})")
    assert not broken, f"{_page_id(page)}: broken links: {broken}"


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_cited_repository_paths_exist(page: Path) -> None:
    missing = sorted(
        {
            p
            for p in CITED_PATH.findall(page.read_text())
            if "*" not in p and not (ROOT / p.rstrip("/")).exists()
        }
    )
    assert not missing, f"{_page_id(page)} cites paths that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_no_round_narrative(page: Path) -> None:
    text = _prose(page)
    found = [m.group(0) for pattern in NARRATIVE for m in pattern.finditer(text)]
    assert not found, f"{_page_id(page)} narrates history (git keeps it): {found}"


def _makefile_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([A-Za-z][\w-]*)\s*:(?!=)", text, re.MULTILINE))


@pytest.mark.parametrize("target", ["demo", "test"])
def test_setup_commands_are_real_make_targets(target: str) -> None:
    text = README.read_text()
    assert re.search(rf"^make {target}\b", text, re.MULTILINE), (
        f"README.md lost its set-up command `make {target}`"
    )
    assert target in _makefile_targets(), f"`make {target}` is no Makefile target"
