"""Publish a report folder: Markdown, a self-contained HTML page and its figures, swapped in whole.

Every report of fivecal (calibration, drift, dispensing test) is written through
:func:`publish_report`: built in a sibling temporary folder, then swapped in by rename
(:func:`tasks.core.atomic_io.swap_in_folder`), so a reader sees the old report or the whole new one.
"""

from __future__ import annotations

import base64
import html
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from tasks.core.atomic_io import swap_in_folder

REPORT_FILE = "report.md"
HTML_FILE = "index.html"
FIGURES_DIR = "figures"

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 1200px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; border-bottom: 2px solid #444; padding-bottom: .3em; }
h2 { font-size: 1.3em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 1em 0; font-size: .85em; display: block; overflow-x: auto; }
th, td { border: 1px solid #ccc; padding: .25em .6em; }
th { background: #f0f0f0; }
tr:nth-child(even) td { background: #fafafa; }
img { max-width: 100%; height: auto; display: block; margin: 1em 0 .2em; }
pre { background: #f6f6f6; padding: 1em; overflow-x: auto; font-size: .85em; }
code { font-family: ui-monospace, Menlo, Consolas, monospace; }
"""


def markdown_to_html(markdown: str, images: dict[str, bytes], title: str) -> str:
    """A self-contained HTML page: the Markdown rendered by markdown-it-py (CommonMark + tables,
    raw HTML escaped), each image whose src is a key of ``images`` (e.g. "figures/fig11.png")
    replaced by a data:image/png;base64 URI, CSS inline."""
    from markdown_it import MarkdownIt

    md = MarkdownIt("commonmark", {"html": False}).enable("table")
    tokens = md.parse(markdown)
    for token in tokens:
        for child in token.children or ():
            src = child.attrGet("src") if child.type == "image" else None
            if src in images:
                child.attrSet("src", "data:image/png;base64," + base64.b64encode(images[src]).decode("ascii"))
    body = md.renderer.render(tokens, md.options, {})
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f"<title>{html.escape(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n{body}</body>\n</html>\n")


def check_report_target(out_dir: Path) -> None:
    """Refuse to replace a file, or a non-empty folder that is not a previous report."""
    if out_dir.is_symlink() or (out_dir.exists() and not out_dir.is_dir()):
        raise FileExistsError(f"{out_dir} exists and is not a report folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / REPORT_FILE).is_file():
        raise FileExistsError(f"{out_dir} is a non-empty folder without {REPORT_FILE}: refusing to replace it")


def write_markdown_and_html(folder: Path, markdown: str, title: str) -> dict[str, Path]:
    """Write ``folder/report.md`` and ``folder/index.html`` with every ``figures/*.png`` of ``folder``
    embedded. Returns {"markdown", "html", "figures"} paths."""
    folder = Path(folder)
    (folder / REPORT_FILE).write_text(markdown, encoding="utf-8")
    figures = folder / FIGURES_DIR
    images = {f"{FIGURES_DIR}/{p.name}": p.read_bytes() for p in sorted(figures.glob("*.png"))}
    (folder / HTML_FILE).write_text(markdown_to_html(markdown, images, title), encoding="utf-8")
    return {"markdown": folder / REPORT_FILE, "html": folder / HTML_FILE, "figures": figures}


def publish_report(out_dir: Path, title: str, build_markdown: Callable[[Path], str],
                   write_data: Callable[[Path], object] | None = None) -> dict[str, Path]:
    """Build a report in a sibling staging folder and swap it in at ``out_dir``.

    ``build_markdown(figures_dir)`` returns the Markdown and saves its PNGs into ``figures_dir`` on
    the way; ``write_data(staging)`` adds further files (the calibration report's ``data/``).
    A previous report at ``out_dir`` is replaced whole; anything else there is refused
    (:func:`check_report_target`). Returns {"markdown", "html", "figures"} paths under ``out_dir``.
    """
    out_dir = Path(out_dir).absolute()
    check_report_target(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}.tmp-"))
    try:
        if write_data is not None:
            write_data(staging)
        (staging / FIGURES_DIR).mkdir()
        write_markdown_and_html(staging, build_markdown(staging / FIGURES_DIR), title)
        staging.chmod(0o755)  # mkdtemp creates 0700
        swap_in_folder(staging, out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # the old report after a swap, or a failed build
    return {"markdown": out_dir / REPORT_FILE, "html": out_dir / HTML_FILE, "figures": out_dir / FIGURES_DIR}
