"""The docs are one linked whole: every relative markdown link resolves, and every docs page is reachable
from README.md by following links (a page linked from nowhere is a page nobody finds)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# [text](target) and ![alt](target); the target ends at the first space (a title may follow) or ")".
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE_SPAN = re.compile(r"`[^`\n]*`")
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.I)  # http:, https:, mailto:, ...


def links(page: Path) -> list[str]:
    """The relative link targets of a markdown page (no anchors, no external links, none inside code)."""
    text = CODE_SPAN.sub("", FENCE.sub("", page.read_text(encoding="utf-8")))
    out = []
    for target in LINK.findall(text):
        if EXTERNAL.match(target) or target.startswith("#"):
            continue
        out.append(target.split("#", 1)[0])
    return out


def broken_links(pages: list[Path]) -> list[str]:
    """'page: target' for every relative link that names no existing file."""
    return [
        f"{page.relative_to(ROOT) if page.is_relative_to(ROOT) else page}: {t}"
        for page in pages
        for t in links(page)
        if not (page.parent / t).exists()
    ]


def reachable(start: Path) -> set[Path]:
    """Every markdown page reachable from ``start`` by following relative links."""
    seen, todo = set(), [start.resolve()]
    while todo:
        page = todo.pop()
        if page in seen or not page.is_file():
            continue
        seen.add(page)
        todo += [(page.parent / t).resolve() for t in links(page) if t.endswith(".md")]
    return seen


def orphans(readme: Path, docs: Path) -> list[str]:
    found = reachable(readme)
    return sorted(str(p.relative_to(docs)) for p in docs.rglob("*.md") if p.resolve() not in found)


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_every_relative_link_resolves():
    bad = broken_links(_pages())
    assert not bad, "links to files that do not exist:\n" + "\n".join(bad)


def test_every_docs_page_is_reachable_from_the_readme():
    lost = orphans(ROOT / "README.md", ROOT / "docs")
    assert not lost, f"docs pages no link reaches from README.md (link them from a page that is reached): {lost}"


def test_the_checks_find_a_broken_link_and_an_orphan(tmp_path):
    """The two checks above on a small tree with one broken link and one unlinked page."""
    docs = tmp_path / "docs"
    (docs / "sub").mkdir(parents=True)
    (tmp_path / "README.md").write_text("[a](docs/a.md) `[not a link](docs/nowhere.md)`\n")
    (docs / "a.md").write_text("[b](sub/b.md#part) ![img](img/missing.png) [web](https://example.org)\n")
    (docs / "sub" / "b.md").write_text("back to [a](../a.md)\n```\n[in code](c.md)\n```\n")
    (docs / "c.md").write_text("nobody links here\n")
    assert broken_links([tmp_path / "README.md", docs / "a.md", docs / "sub" / "b.md"]) == [
        f"{docs / 'a.md'}: img/missing.png"
    ]
    assert orphans(tmp_path / "README.md", docs) == ["c.md"]
