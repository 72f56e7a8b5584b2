"""Reports every broken internal link and image of the built docs site.

    python tools/docs/check_site.py [site]

Reads the HTML that ``mkdocs build`` wrote (default ``site/``) and checks each internal
``href`` and ``src``: the file it names must exist and, for a link with a ``#fragment`` into
a page, the page must have an element with that id. Links to other hosts are not followed:
the check needs no network and mkdocs cannot know them either. Exits 1 when anything is
broken, so ``make docs`` fails on what ``mkdocs build --strict`` lets through (a link mkdocs
does not resolve, such as one inside a page's raw HTML or one that a hook rewrote).
"""

from __future__ import annotations

import argparse
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

# (tag, attribute) pairs that name another file of the site.
LINK_ATTRIBUTES = {
    ("a", "href"),
    ("img", "src"),
    ("link", "href"),
    ("script", "src"),
    ("source", "src"),
    ("iframe", "src"),
}


class _Page(HTMLParser):
    """The ids a page defines and the internal links it makes."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[tuple[str, str]] = []  # (tag, url)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if value is None:
                continue
            if name == "id" or (tag == "a" and name == "name"):
                self.ids.add(value)
            elif (tag, name) in LINK_ATTRIBUTES:
                self.links.append((tag, value))


def _parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8", errors="replace"))
    return page


def _target(site: Path, page: Path, url: str) -> tuple[Path, str] | None:
    """The file and fragment an internal url names, or None for one to another host."""
    parts = urlsplit(url)
    if parts.scheme or parts.netloc:
        return None  # http(s):, mailto:, data:, //host/...
    path = unquote(parts.path)
    if not path:
        target = page
    elif path.startswith("/"):
        target = site / path.lstrip("/")
    else:
        target = page.parent / path
    if path.endswith("/") or target.is_dir():
        target = target / "index.html"
    return target.resolve(), unquote(parts.fragment)


def check(site: Path) -> list[str]:
    """One line per broken internal link or image of the site in ``site``."""
    site = site.resolve()
    pages = {path.resolve(): _parse(path) for path in sorted(site.rglob("*.html"))}
    broken: list[str] = []
    for path, page in pages.items():
        where = path.relative_to(site)
        for tag, url in page.links:
            found = _target(site, path, url)
            if found is None:
                continue
            target, fragment = found
            if not target.is_relative_to(site):
                broken.append(f"{where}: <{tag}> {url}: outside the site")
            elif not target.is_file():
                broken.append(f"{where}: <{tag}> {url}: no such file")
            elif fragment and target in pages and fragment not in pages[target].ids:
                broken.append(f"{where}: <{tag}> {url}: no id {fragment!r} on that page")
    return broken


def main() -> int:
    """Checks the site named on the command line; 1 when anything is broken."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("site", nargs="?", default="site", type=Path, help="the built site")
    args = parser.parse_args()
    if not (args.site / "index.html").is_file():
        print(f"check_site: {args.site}/index.html not found: build the site first (make docs)")
        return 2
    broken = check(args.site)
    for line in broken:
        print(line)
    pages = sum(1 for _ in args.site.rglob("*.html"))
    print(f"check_site: {len(broken)} broken internal links or images in {pages} pages")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
