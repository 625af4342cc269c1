"""The drawing surface of the report's figures: matplotlib Figures without pyplot, and how they are saved.

Figures are drawn on :class:`matplotlib.figure.Figure` objects, never through
pyplot: no global figure registry and no display, so they render with the Agg
canvas from any thread or job. Matplotlib is imported only when a figure is
drawn. Made, drawn and dropped within :func:`collector_paused`, a figure's
objects do not weigh on the garbage collector's later passes.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import io
import logging
import os
import struct
import threading
import zlib
from pathlib import Path

import numpy as np

from surffin.io.files import write_atomically

__all__ = ["DPI", "DRAWING", "figure", "save", "colormap", "subsample", "message", "collector_paused"]

log = logging.getLogger("surffin")

#: Resolution of the written images, dots per inch.
DPI = 120
#: Each thread's last renderer (:func:`_renderer`).
_THREAD = threading.local()
#: Matplotlib settings of drawing: text unhinted. Hinting took a third of drawing a text, and texts take
#: a good part of drawing a figure; at :data:`DPI` unhinted text reads as well.
DRAWING = {"text.hinting": "no_hinting"}


def figure(width: float, height: float, layout: str | None = "constrained"):
    """Create a new matplotlib Figure.

    Parameters
    ----------
    width, height : float
        Size, inches.
    layout : str or None
        Matplotlib's layout engine; default constrained.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout=layout)


def save(fig, path: str | os.PathLike, *, dpi: float = DPI) -> Path:
    """Write a figure with :data:`DRAWING`, atomically, in the image format of the path's suffix.

    PNG is drawn on a renderer of :func:`_renderer` (:func:`_canvas_type`) and encoded by :func:`_png`.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : path-like
        The image to write; its folder is made.
    dpi : float
        Resolution, dots per inch; default :data:`DPI`.

    Returns
    -------
    Path
        ``path``.
    """
    import matplotlib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    kind = path.suffix.lstrip(".").lower() or "png"
    with matplotlib.rc_context(DRAWING):
        if kind == "png":
            canvas = _canvas_type()(fig)
            fig.set_dpi(dpi)
            canvas.draw()
            content = _png(np.asarray(canvas.buffer_rgba()), dpi)
        else:
            buffer = io.BytesIO()
            fig.savefig(buffer, format=kind, dpi=dpi)
            content = buffer.getvalue()
    write_atomically(path, content)
    return path


@functools.cache
def _canvas_type() -> type:
    """Return matplotlib's Agg canvas drawing on :func:`_renderer`'s renderers (matplotlib imported on first use).

    Its ``get_renderer`` serves the figure's drawing and its layout engine (a constrained layout measures
    the texts first): one renderer, its text sizes measured once.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    class Canvas(FigureCanvasAgg):
        def get_renderer(self):
            return _renderer(*self.get_width_height(physical=True), self.figure.dpi)

    return Canvas


def _renderer(width: int, height: int, dpi: float):
    """Return an Agg renderer of images of ``width`` x ``height`` px at ``dpi``: the thread's last one if of that size.

    Kept for the thread's next figure (one at a time: a renderer is one image), as ``FigureCanvasAgg`` keeps
    one for the next draw of its figure. Matplotlib caches the sizes of texts per renderer: a worker's
    figures, most of one size, then measure a text once, not once per figure. The image is the same: the
    canvas clears the renderer before it draws. Only the last is kept (a feature figure's holds 5 MB of
    pixels), dropped before another is made.
    """
    from matplotlib.backends.backend_agg import RendererAgg

    if getattr(_THREAD, "size", None) != (width, height, dpi):
        _THREAD.renderer = None
        _THREAD.renderer, _THREAD.size = RendererAgg(width, height, dpi), (width, height, dpi)
    return _THREAD.renderer


@contextlib.contextmanager
def collector_paused():
    """Pause Python's cyclic garbage collector in the block (figures made, drawn and dropped there).

    A figure is tens of thousands of objects in reference cycles. Collected while it lives, they outlive the
    collections and reach the oldest generation, whose collections go through the whole heap of a worker
    (about 0.1 s each) and come the more often: they cost a feature figure about a tenth of its CPU time.
    With the collector paused, a dropped figure is still in the youngest generation, freed by the next
    collection of that one. On leaving, the collector is enabled again if it was.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _png(rgba: np.ndarray, dpi: float = DPI) -> bytes:
    """Encode an image as PNG, fast: rows unfiltered, zlib level 1.

    Pillow (matplotlib's PNG writer) picks a filter per row, which took most of
    the encoding time and made larger files of figures' flat colours.

    Parameters
    ----------
    rgba : ndarray (rows, columns, 4) of uint8
    dpi : float
        The resolution written in the file.

    Returns
    -------
    bytes
    """
    height, width = rgba.shape[:2]
    rows = np.zeros((height, 1 + 4 * width), np.uint8)  # each row: filter type 0 (none), then its pixels
    rows[:, 1:] = rgba.reshape(height, -1)
    per_metre = round(dpi / 0.0254)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return b"".join(
        (
            b"\x89PNG\r\n\x1a\n",
            chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)),
            chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1)),
            chunk(b"IDAT", zlib.compress(rows, 1)),
            chunk(b"IEND", b""),
        )
    )


def colormap(name: str, bad: str = "0.8"):
    """Copy a matplotlib colormap to draw NaN (missing pixels) in another colour.

    Parameters
    ----------
    name : str
        A matplotlib colormap.
    bad : str
        Matplotlib colour of NaN; default light grey.

    Returns
    -------
    matplotlib.colors.Colormap
    """
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=bad)


def subsample(count: int, limit: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``count`` items, drawn at random (all of them when few enough).

    Parameters
    ----------
    count : int
        Items there are.
    limit : int
        Most items drawn.
    seed : int
        Seed of the draw.

    Returns
    -------
    ndarray of int
    """
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, limit, replace=False))


def message(path: str | os.PathLike, title: str, text: str) -> Path:
    """Write a figure that says why it has no content (e.g. an input made by an older surffin); log it as a warning.

    Parameters
    ----------
    path : path-like
        The image to write.
    title : str
        The figure's title.
    text : str
        Why it has no content.

    Returns
    -------
    Path
        ``path``.
    """
    fig = figure(8, 3)
    ax = fig.add_subplot()
    ax.axis("off")
    ax.set_title(title)
    ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, fontsize=11)
    log.warning("%s: %s", title, text)
    return save(fig, path)
