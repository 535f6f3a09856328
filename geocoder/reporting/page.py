"""A self-contained HTML page: headings, paragraphs, tables and figures linked by relative paths.

No scripts, no fonts or styles from the network: the page opens in any browser from the
directory that holds it and its PNG figures.
"""

from __future__ import annotations

import html
import math
from collections.abc import Iterable, Sequence

STYLE = """
body { font-family: sans-serif; max-width: 1300px; margin: 1em auto; padding: 0 1em; color: #222; }
h1 { border-bottom: 2px solid #2c7bb6; }
h2 { margin-top: 1.8em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #bbb; padding: 0.2em 0.6em; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #eef3f8; }
figure { margin: 0.8em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; }
p.missing { background: #fff3cd; border-left: 4px solid #e0a800; padding: 0.4em 0.8em; }
pre { background: #f6f6f6; padding: 0.6em; white-space: pre-wrap; }
nav a { margin-right: 1em; }
"""


def fmt(value, digits: int = 3) -> str:
    """A number for a table: fixed digits, ``-`` for None/NaN, integers as they are.

    Parameters
    ----------
    value : number, str, bool or None
        The cell's value.
    digits : int
        Digits after the point (tiny values in scientific notation).

    Returns
    -------
    str
    """
    if value is None:
        return "-"
    if isinstance(value, (bool, str)):
        return str(value)
    if isinstance(value, int):
        return str(value)
    v = float(value)
    if not math.isfinite(v):
        return "-"
    return f"{v:.{digits}f}" if abs(v) >= 10 ** (-digits) or v == 0 else f"{v:.2e}"


class Page:
    """An HTML document built section by section.

    Parameters
    ----------
    title : str
        The page's title and first heading.
    """

    def __init__(self, title: str) -> None:
        self.title = title
        self.parts: list[str] = []
        self.sections: list[tuple[str, str]] = []
        self.figures: list[str] = []

    def section(self, anchor: str, heading: str) -> None:
        """Start a section (``<h2 id=anchor>``), listed in the page's navigation.

        Parameters
        ----------
        anchor : str
            The section's id.
        heading : str
            Its heading.
        """
        self.sections.append((anchor, heading))
        self.parts.append(f'<h2 id="{html.escape(anchor)}">{html.escape(heading)}</h2>')

    def paragraph(self, text: str, *, missing: bool = False) -> None:
        """A paragraph of plain text (``missing``: highlighted as something the report could not show).

        Parameters
        ----------
        text : str
            Plain text (escaped).
        missing : bool
            Highlight it as a missing input or result.
        """
        cls = ' class="missing"' if missing else ""
        self.parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def preformatted(self, lines: Iterable[str]) -> None:
        """Lines of text shown as they are.

        Parameters
        ----------
        lines : iterable of str
            The lines.
        """
        self.parts.append("<pre>" + html.escape("\n".join(lines)) + "</pre>")

    def table(self, header: Sequence[str], rows: Iterable[Sequence], *, table_id: str | None = None) -> None:
        """A table; numbers right-aligned.

        Parameters
        ----------
        header : sequence of str
            Column headings.
        rows : iterable of sequences
            Cells (strings are shown as they are, numbers through :func:`fmt`).
        table_id : str, optional
            The table's id attribute.
        """
        ident = f' id="{html.escape(table_id)}"' if table_id else ""
        out = [f"<table{ident}>", "<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>"]
        for row in rows:
            cells = []
            for v in row:
                if isinstance(v, str):
                    cells.append(f"<td>{html.escape(v)}</td>")
                else:
                    cells.append(f'<td class="num">{html.escape(fmt(v))}</td>')
            out.append("<tr>" + "".join(cells) + "</tr>")
        out.append("</table>")
        self.parts.append("\n".join(out))

    def figure(self, filename: str, caption: str) -> None:
        """A figure: a PNG beside the page, by its relative file name.

        Parameters
        ----------
        filename : str
            The PNG's name in the report directory.
        caption : str
            Its caption (plain text).
        """
        self.figures.append(filename)
        self.parts.append(f'<figure><img src="{html.escape(filename)}" alt="{html.escape(caption)}">'
                          f"<figcaption>{html.escape(caption)}</figcaption></figure>")

    def render(self) -> str:
        """The whole document.

        Returns
        -------
        str
            HTML5 text.
        """
        nav = " ".join(f'<a href="#{html.escape(a)}">{html.escape(h)}</a>' for a, h in self.sections)
        return "\n".join([
            "<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
            f"<title>{html.escape(self.title)}</title>", f"<style>{STYLE}</style>", "</head>", "<body>",
            f"<h1>{html.escape(self.title)}</h1>", f"<nav>{nav}</nav>", *self.parts, "</body>", "</html>", "",
        ])
