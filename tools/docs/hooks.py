"""mkdocs hook: pages that include repository files, and links that leave docs/.

A line ``--8<-- "path/from/the/repository/root.md"`` in a page is replaced by that file, with
``level=N`` after the path moving its headings so that its first one is level N. The file was
written to be read where it lies (on GitHub, in a clone), so its relative links are relative
to its own folder; here each one is rebased to what it names in the repository:

- a file under docs/: that page or file of the site, relative to the including page;
- an image: the image itself, copied into the site under ``repo/`` at its repository path;
- anything else (sources, configs, result tables): the file on the repository's web page,
  ``repo_url``/blob/``REF``/path, since the site publishes only docs/.

Links of docs/ pages that leave docs/ are rebased the same way. A link to a file that does
not exist is a warning, which ``mkdocs build --strict`` turns into a failure. This replaces
pymdownx.snippets, which includes the text but leaves its links pointing nowhere.

The API reference renders docstrings written for Sphinx: their roles (``:meth:`step```) and
literal-block markers (``Example::``) would show as typed. The hook turns a role into its
name in code, a link where the name is a documented ``esa_client`` object, and ``::`` into
``:``.
"""

from __future__ import annotations

import logging
import posixpath
import re
from pathlib import Path
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files
from mkdocs.structure.pages import Page

log = logging.getLogger("mkdocs.hooks.esa_docs")

# The branch the repository links of the site point at.
REF = "main"
# The site's folder for images that live outside docs/ (at their repository paths below it).
PUBLISHED = "repo"
IMAGE_SUFFIXES = {".png", ".svg", ".jpg", ".jpeg", ".gif", ".webp"}

INCLUDE = re.compile(r'^--8<-- "(?P<path>[^"]+)"(?:[ \t]+level=(?P<level>[1-6]))?[ \t]*$', re.M)
FENCE = re.compile(r"^[ \t]*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})(?=[ \t])")
# A code span (kept as it is) or an inline link or image's target: ](target "title").
SPAN_OR_LINK = re.compile(r"(?P<code>(`+).*?\2)|(?P<open>\]\()(?P<url><[^>]*>|[^)\s]+)")
REFERENCE = re.compile(r"^(?P<lead>[ \t]{0,3}\[[^\]]+\]:[ \t]*)(?P<url>\S+)")
EXTERNAL = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.-]*:|//|#|/)")
# A Sphinx role as mkdocstrings renders it: :meth:<code>~pkg.Class.method</code>.
ROLE = re.compile(
    r":(?P<role>meth|func|class|mod|attr|exc|data|obj):<code>(?P<short>~?)(?P<target>[^<]+)</code>"
)
LITERAL_MARKER = re.compile(r"(?<=[^:\s])::</p>")


def _root(config: MkDocsConfig) -> Path:
    return Path(config.config_file_path).resolve().parent


def _docs(config: MkDocsConfig) -> str:
    """docs_dir relative to the repository root, in posix form ("docs")."""
    return Path(config.docs_dir).resolve().relative_to(_root(config)).as_posix()


class _Rebaser:
    """Rebases the relative links of text that lies at ``source`` (repository-relative)."""

    def __init__(self, config: MkDocsConfig, page_uri: str, source: str) -> None:
        self.config = config
        self.page_dir = posixpath.dirname(page_uri)
        self.source_dir = posixpath.dirname(source)
        self.source = source
        # A docs/ page's links into docs/ stay as written: mkdocs resolves and checks them.
        self.own_page = source == f"{_docs(config)}/{page_uri}"
        self.images: set[str] = set()  # repository paths to publish

    def url(self, url: str) -> str:
        bracketed = url.startswith("<") and url.endswith(">")
        bare = url[1:-1] if bracketed else url
        if not bare or EXTERNAL.match(bare):
            return url
        path, hash_, fragment = bare.partition("#")
        target = posixpath.normpath(posixpath.join(self.source_dir, path))
        docs = _docs(self.config)
        if target.startswith(docs + "/"):
            if self.own_page:
                return url
            new = posixpath.relpath(target[len(docs) + 1 :], self.page_dir or ".")
        else:
            on_disk = _root(self.config) / target
            if target.startswith("..") or not on_disk.exists():
                log.warning("%s links to %r, which is not in the repository", self.source, path)
                return url
            if on_disk.suffix.lower() in IMAGE_SUFFIXES:
                self.images.add(target)
                new = posixpath.relpath(f"{PUBLISHED}/{target}", self.page_dir or ".")
            else:
                kind = "tree" if on_disk.is_dir() else "blob"
                new = f"{self.config.repo_url.rstrip('/')}/{kind}/{REF}/{target}"
        new += hash_ + fragment
        return f"<{new}>" if bracketed else new

    def text(self, markdown: str, shift: int = 0) -> str:
        """The markdown with its links rebased and its headings moved down by ``shift``."""
        out: list[str] = []
        fence: str | None = None
        for line in markdown.splitlines(keepends=True):
            opening = FENCE.match(line)
            if fence is not None:
                if opening and opening.group(1) == fence:
                    fence = None
                out.append(line)
                continue
            if opening:
                fence = opening.group(1)
                out.append(line)
                continue
            if shift:
                line = HEADING.sub(lambda m: "#" * min(6, len(m.group(1)) + shift), line)
            reference = REFERENCE.match(line)
            if reference:
                rest = line[reference.end() :]
                line = reference.group("lead") + self.url(reference.group("url")) + rest
            else:
                line = SPAN_OR_LINK.sub(self._link, line)
            out.append(line)
        return "".join(out)

    def _link(self, match: re.Match[str]) -> str:
        if match.group("code"):
            return match.group(0)
        return match.group("open") + self.url(match.group("url"))


def _top_level(markdown: str) -> int | None:
    fence: str | None = None
    levels: list[int] = []
    for line in markdown.splitlines():
        opening = FENCE.match(line)
        if fence is not None:
            fence = None if opening and opening.group(1) == fence else fence
        elif opening:
            fence = opening.group(1)
        elif heading := HEADING.match(line):
            levels.append(len(heading.group(1)))
    return min(levels, default=None)


def expand(markdown: str, page_uri: str, config: MkDocsConfig) -> tuple[str, set[str]]:
    """A page's markdown with its includes expanded and its links rebased.

    Returns:
        The markdown, and the repository paths of the images outside docs/ that it shows.
    """
    images: set[str] = set()
    page = _Rebaser(config, page_uri, f"{_docs(config)}/{page_uri}")

    def include(match: re.Match[str]) -> str:
        source = match.group("path")
        path = _root(config) / source
        if not path.is_file():
            log.warning("%s includes %r, which is not in the repository", page_uri, source)
            return match.group(0)
        text = path.read_text(encoding="utf-8")
        top = _top_level(text)
        shift = int(match.group("level")) - top if match.group("level") and top else 0
        included = _Rebaser(config, page_uri, source)
        expanded = included.text(text, max(shift, 0))
        images.update(included.images)
        return expanded

    # The page's own links first: its includes arrive already rebased.
    text = INCLUDE.sub(include, page.text(markdown))
    return text, images | page.images


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Publishes the images outside docs/ that pages show, at ``repo/<repository path>``."""
    images: set[str] = set()
    for file in list(files):
        if file.is_documentation_page():
            images |= expand(file.content_string, file.src_uri, config)[1]
    for image in sorted(images):
        abs_src_path = str(_root(config) / image)
        files.append(File.generated(config, f"{PUBLISHED}/{image}", abs_src_path=abs_src_path))
    return files


def on_page_markdown(markdown: str, page: Page, config: MkDocsConfig, **_: Any) -> str:
    """Expands the page's includes and rebases its links before mkdocs resolves them."""
    return expand(markdown, page.file.src_uri, config)[0]


def on_page_content(html: str, page: Page, **_: Any) -> str:
    """Renders the Sphinx roles and ``::`` markers of the API reference's docstrings."""
    if 'class="doc doc-' not in html:
        return html
    return LITERAL_MARKER.sub(":</p>", ROLE.sub(_role, html))


def _role(match: re.Match[str]) -> str:
    target = match.group("target")
    title = target.rsplit(".", 1)[-1] if match.group("short") else target
    if match.group("role") in ("meth", "func"):
        title += "()"
    code = f"<code>{title}</code>"
    if target.startswith("esa_client."):
        # mkdocs-autorefs links it if the object is on the site, else leaves the code.
        return f'<autoref identifier="{target}" optional>{code}</autoref>'
    return code


def on_serve(server: Any, config: MkDocsConfig, **_: Any) -> Any:
    """``mkdocs serve`` rebuilds when an included file changes too."""
    included: set[str] = set()
    for page in Path(config.docs_dir).rglob("*.md"):
        included.update(m.group("path") for m in INCLUDE.finditer(page.read_text("utf-8")))
    for path in sorted(included):
        server.watch(str(_root(config) / path))
    return server
