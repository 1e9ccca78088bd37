"""`report.html`: a command's `report.md` as one self-contained HTML file, to open in a browser
or send to a colleague. The figures are embedded as base64 data URIs, the style sheet is inline,
and nothing is loaded from the network, so the file reads the same offline.

Markdown is parsed by markdown-it-py (CommonMark plus tables), the parser `rich` already uses.
"""

import base64
import html
import mimetypes
import pathlib

from .io import atomic_write_text

_CSS = """
:root { color-scheme: light; }
body { font: 15px/1.55 -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
       color: #1f2328; background: #fff; max-width: 1100px; margin: 0 auto; padding: 24px 32px 64px; }
h1 { font-size: 1.9em; border-bottom: 1px solid #d0d7de; padding-bottom: .3em; }
h2 { font-size: 1.4em; border-bottom: 1px solid #d0d7de; padding-bottom: .25em; margin-top: 1.8em; }
h3 { font-size: 1.15em; margin-top: 1.4em; }
code { font: 0.9em/1.4 ui-monospace, SFMono-Regular, Menlo, Consolas, monospace;
       background: #f6f8fa; padding: .1em .35em; border-radius: 4px; }
pre { background: #f6f8fa; padding: 12px 16px; overflow-x: auto; border-radius: 6px; }
pre code { background: none; padding: 0; }
table { border-collapse: collapse; margin: 1em 0; display: block; overflow-x: auto; max-width: 100%; }
th, td { border: 1px solid #d0d7de; padding: 5px 11px; text-align: left; vertical-align: top; }
th { background: #f0f3f6; font-weight: 600; }
tr:nth-child(even) td { background: #f9fafb; }
img { max-width: 100%; height: auto; display: block; margin: 1em 0; border: 1px solid #eaeef2; }
blockquote { margin: 0; padding: 0 1em; color: #59636e; border-left: .25em solid #d0d7de; }
footer { margin-top: 3em; color: #59636e; font-size: .85em; border-top: 1px solid #d0d7de; padding-top: .8em; }
"""


def _data_uri(path: pathlib.Path) -> str:
    mime = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def markdown_to_html(text: str, base: pathlib.Path | str = ".", *, title: str | None = None) -> str:
    """A complete HTML document for the Markdown `text`. Images with a relative path that exists
    under `base` are embedded as data URIs; a missing one keeps its path and shows its alt text.

    **Arguments:** `text` Markdown (CommonMark + tables; raw HTML is escaped), `base` the folder
    relative image paths are read from, `title` the document title (default: the first `# `
    heading).

    **Returns:** the HTML text.
    """
    from markdown_it import MarkdownIt

    base = pathlib.Path(base)
    md = MarkdownIt("commonmark", {"html": False}).enable("table")
    tokens = md.parse(text)
    for tok in tokens:
        for child in tok.children or []:
            if child.type != "image":
                continue
            src = str(child.attrGet("src") or "")
            if not src or "://" in src or src.startswith("data:"):
                continue
            path = (base / src).resolve()
            if path.is_file():
                child.attrSet("src", _data_uri(path))
    body = md.renderer.render(tokens, md.options, {})
    if title is None:
        heading = next((ln[2:].strip() for ln in text.splitlines() if ln.startswith("# ")), "hdjax report")
        title = heading.replace("`", "")
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n{body}</main>\n"
        "<footer>Written by hdjax. Self-contained: the figures are embedded in this file.</footer>\n"
        "</body>\n</html>\n"
    )


def write_report_html(report_md: pathlib.Path | str, out: pathlib.Path | str | None = None) -> pathlib.Path:
    """Convert `report_md` (a command's report.md) into `out` (default: report.html beside it),
    written atomically, figures embedded. **Returns:** the path written."""
    report_md = pathlib.Path(report_md)
    out = report_md.with_suffix(".html") if out is None else pathlib.Path(out)
    text = report_md.read_text(encoding="utf-8")
    return atomic_write_text(out, markdown_to_html(text, report_md.parent))
