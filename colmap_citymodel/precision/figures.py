"""Matplotlib figures rendered off-screen to PNG bytes, and the self-contained HTML page."""

from __future__ import annotations

import base64
import html
import io


def new_figure(width: float, height: float):
    from matplotlib.figure import Figure

    # A fixed layout: constrained/tight layout measure every text and cost seconds per figure.
    figure = Figure(figsize=(width, height), dpi=90)
    figure.subplots_adjust(left=0.06, right=0.97, bottom=0.1, top=0.9, wspace=0.3, hspace=0.6)
    return figure


def png_bytes(figure) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def html_page(title: str, plots: dict[str, bytes], summary: str) -> str:
    """A self-contained HTML page: the PNGs inline (base64), then `summary` preformatted."""
    parts = ["<!DOCTYPE html>", "<html><head><meta charset='utf-8'>",
             f"<title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1300px;margin:auto;padding:1em}"
             "pre{background:#f6f6f6;padding:1em;overflow-x:auto}img{max-width:100%}</style>",
             "</head><body>", f"<h1>{html.escape(title)}</h1>"]
    for name, png in plots.items():
        encoded = base64.b64encode(png).decode("ascii")
        parts += [f"<h2>{html.escape(name)}</h2>",
                  f"<img alt='{html.escape(name)}' src='data:image/png;base64,{encoded}'>"]
    parts += ["<h2>Summary</h2>", f"<pre>{html.escape(summary)}</pre>", "</body></html>"]
    return "\n".join(parts)
