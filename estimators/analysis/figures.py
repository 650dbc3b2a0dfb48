"""Figures drawn off-screen for files: ``matplotlib.figure.Figure`` objects, never pyplot, so that the library
neither switches the process's backend nor touches a notebook's current figure."""
from __future__ import annotations

import io

from matplotlib.figure import Figure


def new_figure(nrows: int = 1, ncols: int = 1, figsize: tuple[float, float] = (6.4, 4.8), **subplot_kw):
    """``(fig, axes)`` like ``pyplot.subplots``, on a figure that no pyplot state knows of."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **subplot_kw)


def png_bytes(fig: Figure, dpi: int = 100, tight: bool = True) -> bytes:
    """The figure as PNG bytes; ``tight`` crops it to its content (one more layout pass: a third of the
    time of a simple figure, so figures drawn many times with a fixed layout pass False)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    return buf.getvalue()
