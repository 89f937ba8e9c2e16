"""Every relative link in the README, docs/ and bench/README.md points at a file that exists.

Markdown links and images (``[text](target)``, ``![alt](target)``) and HTML ``src=``/``href=``
attributes are checked; web addresses are not. A ``#fragment`` on a link to a Markdown file (or a
bare ``#fragment``) must name a heading of that file, slugged the way GitHub does. Links inside code
(fenced blocks, inline backticks) are text, not links.
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parents[1]

_FENCE = re.compile(r"^\s*(```|~~~)")
_INLINE_CODE = re.compile(r"`[^`]*`")
_MD_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HTML_ATTR = re.compile(r"\b(?:src|href)\s*=\s*\"([^\"]+)\"")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def doc_files() -> list[Path]:
    """The product's pages: README.md, every Markdown file under docs/, bench/README.md."""
    files = [ROOT / "README.md", ROOT / "bench" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [f for f in files if f.exists()]


def _prose_lines(text: str, strip_code: bool = True) -> list[tuple[int, str]]:
    """(line number, line) for every line outside fenced code blocks, inline code removed if asked."""
    out, in_fence = [], False
    for i, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            in_fence = not in_fence
            continue
        if not in_fence:
            out.append((i, _INLINE_CODE.sub("", line) if strip_code else line))
    return out


def links(text: str) -> list[tuple[int, str]]:
    """(line number, target) of every link in ``text`` outside code."""
    found = []
    for i, line in _prose_lines(text):
        found += [(i, m.group(1)) for m in _MD_LINK.finditer(line)]
        found += [(i, m.group(1)) for m in _HTML_ATTR.finditer(line)]
    return found


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading keeps its text
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(md: Path) -> set[str]:
    """Every heading anchor of a Markdown file (repeated headings get -1, -2, ... as on GitHub)."""
    seen: dict[str, int] = {}
    result = set()
    for _, line in _prose_lines(md.read_text(encoding="utf-8"), strip_code=False):
        m = _HEADING.match(line)
        if not m:
            continue
        slug = github_slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        result.add(slug if n == 0 else f"{slug}-{n}")
    return result


def broken_links(md: Path, root: Path = ROOT) -> list[str]:
    """A line per relative link of ``md`` whose file (or heading) does not exist (paths shown from ``root``)."""
    problems = []
    for lineno, target in links(md.read_text(encoding="utf-8")):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):  # http:, https:, mailto:, ...
            continue
        path_part, _, fragment = target.partition("#")
        dest = (md.parent / unquote(path_part)).resolve() if path_part else md
        where = f"{md.relative_to(root)}:{lineno}: {target}"
        if not dest.exists():
            problems.append(f"{where} -> no such file {dest}")
        elif fragment and dest.suffix == ".md" and unquote(fragment) not in anchors(dest):
            problems.append(f"{where} -> no heading #{fragment} in {dest.name}")
    return problems


def test_the_pages_exist() -> None:
    names = {str(f.relative_to(ROOT)) for f in doc_files()}
    assert {"README.md", "bench/README.md", "docs/results.md", "docs/graph.md"} <= names


@pytest.mark.parametrize("md", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(md: Path) -> None:
    assert broken_links(md) == []


def test_the_checker_finds_a_broken_link_and_a_missing_heading(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Title\n\n## A `code` heading: yes\n", encoding="utf-8")
    page = tmp_path / "page.md"
    page.write_text(
        "# Page\n[ok](other.md) [ok](other.md#a-code-heading-yes) ![img](missing.png)\n"
        '[bad anchor](other.md#nope) <img src="gone.gif"> [web](https://example.org/x)\n'
        "```\n[in code](nowhere.md)\n```\n`[inline](nowhere.md)` [self](#page)\n",
        encoding="utf-8",
    )
    problems = [p.split(" -> ")[1] for p in broken_links(page, root=tmp_path)]
    assert problems == [
        f"no such file {tmp_path / 'missing.png'}",
        "no heading #nope in other.md",
        f"no such file {tmp_path / 'gone.gif'}",
    ]
