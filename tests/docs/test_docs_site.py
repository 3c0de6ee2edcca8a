"""The documentation site as a reader sees it: build it with ``mkdocs build --strict`` into a
temporary folder, then check the rendered HTML for what ``--strict`` does not catch: links and
#anchors that lead nowhere, Markdown that did not render (list items merged into a paragraph,
tables, ``**``, admonitions, code fences), missing images, mermaid diagrams, empty API pages,
and README.md links that would break on GitHub."""

from __future__ import annotations

import html
import os
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"

_SKIP_TEXT = {"code", "pre", "script", "style"}


class _Page(HTMLParser):
    """Ids, links, images and the text of the article (the page body, without the theme),
    outside code; and the text of each paragraph and table cell."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[str] = []
        self.images: list[str] = []
        self.blocks: list[str] = []
        self.mermaid = 0
        self.api_objects = 0
        self._article = 0
        self._skip = 0
        self._block: list[str] | None = None
        self._block_tag = ""

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if "id" in a:
            self.ids.add(a["id"])
        if tag == "article":
            self._article += 1
        if not self._article:
            return
        if tag == "a" and "href" in a:
            self.links.append(a["href"])
        if tag == "img":
            self.images.append(a.get("src", ""))
        if tag == "pre" and "mermaid" in a.get("class", "").split():
            self.mermaid += 1
        if "doc-object" in a.get("class", "").split():
            self.api_objects += 1
        if tag in _SKIP_TEXT:
            self._skip += 1
        if tag in ("p", "td", "th", "li") and self._block is None:
            self._block, self._block_tag = [], tag

    def handle_endtag(self, tag: str) -> None:
        if tag == "article":
            self._article -= 1
        if tag in _SKIP_TEXT and self._article:
            self._skip -= 1
        if self._block is not None and tag == self._block_tag:
            self.blocks.append("".join(self._block))
            self._block = None

    def handle_data(self, data: str) -> None:
        if self._block is not None and not self._skip:
            self._block.append(data)


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def site(site_dir: Path) -> dict[str, _Page]:
    out = site_dir
    pages = {}
    for path in out.rglob("*.html"):
        page = _Page()
        page.feed(path.read_text(encoding="utf-8"))
        page.close()
        pages[path.relative_to(out).as_posix()] = page
    pages.pop("404.html", None)
    return pages


def _target(page: str, href: str, pages: dict[str, _Page]) -> tuple[str | None, str]:
    """The page a relative href of ``page`` leads to (None: nowhere), and its fragment."""
    u = urlsplit(href)
    if not u.path:
        return page, unquote(u.fragment)
    path = os.path.normpath(os.path.join(os.path.dirname(page), unquote(u.path)))
    for candidate in (path, f"{path}/index.html"):
        if candidate in pages:
            return candidate, unquote(u.fragment)
    return None, unquote(u.fragment)


def test_every_internal_link_and_anchor_resolves(site: dict[str, _Page], site_dir: Path) -> None:
    broken = []
    for name, page in site.items():
        for href in page.links:
            u = urlsplit(href)
            if u.scheme or href.startswith("//"):
                continue
            target, fragment = _target(name, href, site)
            if target is None:
                # Not a page: then a file of the site (an image, a download).
                file = site_dir / os.path.dirname(name) / unquote(u.path)
                if not file.is_file():
                    broken.append(f"{name}: {href} (no such page or file)")
                continue
            if fragment and fragment not in site[target].ids:
                broken.append(f"{name}: {href} (no heading #{fragment} in {target})")
    assert not broken, "\n".join(broken)


# Markdown that reached the HTML as text: a list item or numbered step that merged into the
# paragraph above it (no blank line), a table that did not render, bold, an admonition, a
# code fence, a Markdown link, a heading, a backslash escape Python-Markdown does not know.
_RAW = re.compile(
    r"\n\s*(?:[-*+]|\d+[.)])\s+\S"
    r"|\|\s*:?-{3,}"
    r"|^\s*(?:!!!|\?\?\?)"
    r"|\*\*"
    r"|```"
    r"|\]\([^)\s]+\)"
    r"|^\s*#{1,6}\s"
    r"|\\[<>]",
    re.M,
)


def _raw_markdown(site: dict[str, _Page], pages: set[str] | None = None) -> list[str]:
    found = []
    for name, page in site.items():
        if pages is not None and name not in pages:
            continue
        for block in page.blocks:
            for m in _RAW.finditer(block):
                found.append(f"{name}: ...{block[max(0, m.start() - 60) : m.end() + 40]!r}...")
    return found


def test_no_raw_markdown_in_the_written_pages(site: dict[str, _Page]) -> None:
    written = {n for n in site if not n.startswith("reference/")}
    assert not _raw_markdown(site, written), "\n".join(_raw_markdown(site, written))


def test_no_raw_markdown_in_the_generated_reference(site: dict[str, _Page]) -> None:
    generated = {n for n in site if n.startswith("reference/")}
    assert not _raw_markdown(site, generated), "\n".join(_raw_markdown(site, generated))


def test_api_pages_show_no_sphinx_roles(site: dict[str, _Page]) -> None:
    role = re.compile(r":(?:func|class|meth|data|attr|mod|exc|obj):")
    found = [
        f"{name}: {b[:80]!r}"
        for name, page in site.items()
        if name.startswith("reference/api/")
        for b in page.blocks
        if role.search(b)
    ]
    assert not found, "\n".join(found)


def test_every_image_exists(site: dict[str, _Page]) -> None:
    missing = []
    for name, page in site.items():
        for src in page.images:
            if urlsplit(src).scheme:
                continue
            rel = os.path.normpath(os.path.join(os.path.dirname(name), unquote(src)))
            # Images are copied from docs/ as they are, at the same path.
            if not (DOCS / rel).is_file():
                missing.append(f"{name}: {src}")
    assert not missing, "\n".join(missing)


def _markdown_files() -> list[Path]:
    return [*sorted(DOCS.rglob("*.md")), ROOT / "README.md", ROOT / "CONTRIBUTING.md"]


def test_every_code_fence_names_its_language_and_is_closed() -> None:
    bad = []
    fence = re.compile(r"^(\s*)(`{3,}|~{3,})(.*)$")
    for path in _markdown_files():
        open_fence = None
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            m = fence.match(line)
            if not m:
                continue
            if open_fence is None:
                open_fence = (m.group(2), i)
                if not m.group(3).strip():
                    bad.append(f"{path.relative_to(ROOT)}:{i}: code fence without a language")
            elif m.group(2).startswith(open_fence[0]) and not m.group(3).strip():
                open_fence = None
        if open_fence is not None:
            bad.append(f"{path.relative_to(ROOT)}:{open_fence[1]}: code fence never closed")
    assert not bad, "\n".join(bad)


def test_every_mermaid_fence_renders_as_a_diagram(site: dict[str, _Page]) -> None:
    wrong = []
    for path in DOCS.rglob("*.md"):
        fences = len(re.findall(r"^\s*```mermaid\s*$", path.read_text(encoding="utf-8"), re.M))
        rel = path.relative_to(DOCS).with_suffix("").as_posix()
        name = "index.html" if rel == "index" else f"{rel}/index.html"
        if fences and site[name].mermaid != fences:
            wrong.append(f"{name}: {fences} mermaid fences, {site[name].mermaid} diagrams")
    assert not wrong, "\n".join(wrong)


def test_api_reference_pages_document_objects(site: dict[str, _Page]) -> None:
    api = [n for n in site if n.startswith("reference/api/")]
    assert api
    empty = [n for n in api if site[n].api_objects == 0]
    assert not empty, f"API pages with no documented object: {empty}"


def test_readme_links_resolve_in_the_repository() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    tracked = set(
        subprocess.run(
            ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.splitlines()
    )
    broken = []
    for href in re.findall(r"\]\(([^)\s]+)\)", text):
        u = urlsplit(href)
        if u.scheme or not u.path:
            continue
        path = os.path.normpath(unquote(u.path))
        if path.startswith("..") or not (
            path in tracked or any(t.startswith(f"{path}/") for t in tracked)
        ):
            broken.append(f"{href} (not a file of the repository)")
            continue
        if u.fragment and path.endswith(".md"):
            heads = re.findall(r"^#{1,6}\s+(.+?)\s*$", (ROOT / path).read_text("utf-8"), re.M)
            slugs = {
                re.sub(r"[^\w\- ]", "", html.unescape(h).lower()).replace(" ", "-") for h in heads
            }
            if u.fragment not in slugs:
                broken.append(f"{href} (no heading #{u.fragment} on GitHub)")
    assert not broken, "\n".join(broken)
