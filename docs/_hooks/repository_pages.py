"""Pages read from where they are committed in the repository, not copied into `docs/`.

- the home page is `README.md` (its links into `docs/` are made relative to the site),
  and `ARCHITECTURE.md`, which it links, sits beside it;
- every notebook `notebooks/*.ipynb` (rendered by mkdocs-jupyter with its committed
  outputs) under `notebooks/`, listed in the nav section "Notebooks";
- the benchmark reference results `benchmarks/results/*.md` with their `*.png` plots under
  `benchmarks/results/`, listed in the nav section "Benchmarks" after its overview page.

Each file keeps its path relative to the repository root, so the relative links between
them (README -> ARCHITECTURE.md, a results page -> its plots) work on the site as in the
repository.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File


log = logging.getLogger("mkdocs.hooks.repository_pages")

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = "notebooks"
RESULTS = "benchmarks/results"
SUMMARIES = re.compile(r"summary(-quick)?\.md")


def _notebooks() -> list[Path]:
    return sorted((ROOT / NOTEBOOKS).glob("*.ipynb"))


def _result_pages() -> list[Path]:
    """One page per benchmark suite: its full reference run, or its quick run if there is
    no full one. The summaries repeat the suites' sections and are left out."""
    pages = {}
    for path in sorted((ROOT / RESULTS).glob("*.md")):
        if SUMMARIES.fullmatch(path.name):
            continue
        suite = path.stem.removesuffix("-quick")
        if suite not in pages or not path.stem.endswith("-quick"):
            pages[suite] = path
    return list(pages.values())


def _title(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip()
            return f"{title} (quick run)" if path.stem.endswith("-quick") else title
    return path.stem


def _uri(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def on_config(config):
    """Fill the nav sections "Notebooks" and "Benchmarks" from what is committed."""
    notebooks = [_uri(p) for p in _notebooks()]
    results = [{_title(p): _uri(p)} for p in _result_pages()]
    if not notebooks:
        log.warning("No notebooks found in %s/.", NOTEBOOKS)
    if not results:
        log.warning("No benchmark results found in %s/.", RESULTS)
    for entry in config.nav or []:
        if isinstance(entry, dict) and "Notebooks" in entry:
            entry["Notebooks"] = list(entry["Notebooks"] or []) + notebooks
        if isinstance(entry, dict) and "Benchmarks" in entry:
            entry["Benchmarks"] = list(entry["Benchmarks"] or []) + results
    return config


@event_priority(100)  # before mkdocs-jupyter's on_files, which turns notebooks into pages
def on_files(files, config):
    files.append(File.generated(config, "index.md", abs_src_path=str(ROOT / "README.md")))
    paths = [ROOT / "ARCHITECTURE.md", *_notebooks(), *_result_pages()]
    paths += sorted((ROOT / RESULTS).glob("*.png"))
    for path in paths:
        # At its own path under the repository root (mkdocs-jupyter reads a notebook from there).
        files.append(File(_uri(path), str(ROOT), config.site_dir, config.use_directory_urls))
    return files


# pymdownx.arithmatex reads `$$...$$` as display math only as a block of its own; inside a
# paragraph (as the docstrings write it, and as GitHub renders it) it reads `$` + inline
# math + `$`. Such inline formulas become display math again.
_INLINE_DISPLAY = re.compile(r'\$<span class="arithmatex">\\\(([^<]*?)\\\)</span>\$')


def on_page_content(html, page, config, files):
    return _INLINE_DISPLAY.sub(r'<span class="arithmatex">\\[\1\\]</span>', html)


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri == "index.md":
        # The README links the documentation's pages by their path in the repository.
        markdown = re.sub(r"\]\(docs/", "](", markdown)
    return markdown
