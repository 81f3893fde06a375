"""The documentation's pictures and links (#52): every figure or image a page shows is a committed file,
every committed figure a stage guide names is shown in it, and every relative link of the README and the
documentation leads to a file that exists (the Sphinx build, ``make docs -W``, checks the links between
its own pages; GitHub shows the README and the Markdown as they are)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from conftest import REPO

DOCS = REPO / "docs"
PAGES = [REPO / "README.md", *sorted(p for p in DOCS.rglob("*.md") if not {"_build", "gallery"} & set(p.parts))]
GUIDES = sorted((DOCS / "guide").glob("*.md"))

FIGURE = re.compile(r"^[ \t]*```\{(?:figure|image)\}[ \t]+(\S+)", re.MULTILINE)
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
CODE = re.compile(r"`[^`\n]*`")


def _prose(text: str) -> str:
    """The page without its code blocks (a directive's fence, a figure's, stays: its caption is prose)."""
    keep, fence = [], None
    for line in text.split("\n"):
        m = re.match(r"^[ \t]*(`{3,})(.*)$", line)
        if fence is None and m:
            fence = (m.group(1), m.group(2).startswith("{"))
            keep.append(line if fence[1] else "")
        elif fence is not None and m and m.group(1).startswith(fence[0]) and not m.group(2).strip():
            keep.append(line if fence[1] else "")
            fence = None
        else:
            keep.append(line if fence is None or fence[1] else "")
    return "\n".join(keep)


def _committed() -> set[str]:
    out = subprocess.run(["git", "-C", str(REPO), "ls-files"], check=False, capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip("not a git checkout")
    return set(out.stdout.splitlines())


def _shown(page: Path) -> list[str]:
    """The pictures a page shows: MyST figure/image directives and Markdown images."""
    text = page.read_text()
    return FIGURE.findall(text) + IMAGE.findall(_prose(text))


def _repo_path(page: Path, target: str) -> str:
    return (page.parent / target).resolve().relative_to(REPO.resolve()).as_posix()


def test_the_guides_show_their_figures():
    assert sum(len(_shown(p)) for p in GUIDES) >= 26


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_picture_a_page_shows_is_committed(page):
    committed = _committed()
    for target in _shown(page):
        assert not target.startswith(("http:", "https:")), f"{page.name}: {target}: an image off the repository"
        path = _repo_path(page, target)
        assert (REPO / path).is_file(), f"{page.name}: {target}: no such file"
        assert path in committed, f"{page.name}: {target}: not committed"


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: p.name)
def test_every_committed_figure_a_guide_names_is_shown_there(page):
    """A guide that names a committed figure by its path (``sensing/coupling-bias-sweep.png``) shows it."""
    committed = {p for p in _committed() if p.endswith(".png") and not p.startswith("docs/")}
    text = page.read_text()
    named = {m for m in re.findall(r"[\w./-]+\.png", FIGURE.sub("", text)) if m in committed}
    shown = {_repo_path(page, t) for t in _shown(page)}
    assert named <= shown, f"{page.name} names but does not show: {sorted(named - shown)}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_leads_to_a_file(page):
    text = CODE.sub("", _prose(page.read_text()))
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (not fetched: no network in the tests) or an anchor of the page itself
        path = target.split("#", 1)[0]
        full = (page.parent / path).resolve()
        if full.is_relative_to(REPO / "docs" / "gallery"):
            # sphinx-gallery writes docs/gallery/ from docs/examples/ when the pages are built (not committed)
            assert (REPO / "docs" / "examples" / "README.txt").exists(), f"{target}: no docs/examples to build it"
            continue
        assert (page.parent / path).exists(), f"{page.relative_to(REPO)}: link to {target}: no such file"


def test_the_checks_can_fail(tmp_path):
    """The patterns find what they are for (a test that cannot fail is a defect)."""
    page = tmp_path / "p.md"
    page.write_text("```{figure} ../x.png\n:alt: x\n\ncap\n```\n\n![a](b/c.png) [d](e.md#f) `[g](h.md)`\n"
                    "```bash\n[i](j.md)\n```\n")
    assert _shown(page) == ["../x.png", "b/c.png"]
    assert LINK.findall(CODE.sub("", _prose(page.read_text()))) == ["e.md#f"]
