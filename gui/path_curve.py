"""Curves for the live plots that Qt draws by itself, and their reduction to the screen.

A pyqtgraph PlotDataItem calls back into Python for every paint and every bounds
query of each curve, and re-processes its data (mapping, clipping, downsampling,
bounds) on each setData: profiled, that was about half of a live-view frame.
``PathCurve`` is a QGraphicsPathItem in view coordinates: its path is built once per
new data set (``pyqtgraph.arrayToQPath``), and its paint and bounds are Qt's own.
"""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets


class PathCurve(QtWidgets.QGraphicsPathItem):
    """One curve, drawn with ``pen``; ``log`` = (x, y) are plotted as log10 (log axes).

    A pen of width 1 is drawn as width 0: the same one-pixel cosmetic line, pixel for
    pixel, but Qt then bounds the item by the path itself instead of a stroked outline
    of it. A wider solid pen draws each segment by itself, as pyqtgraph draws wide
    curves (square caps overlapping at the joints), so the picture does not change.
    ``opts`` is what a pyqtgraph legend sample reads (the pen); clicking the sample
    hides the curve, as for pyqtgraph's own items.
    """

    def __init__(self, pen: QtGui.QPen, log: tuple[bool, bool] = (False, False)):
        super().__init__()
        self.opts = {"pen": pen}
        self._segments = pen.widthF() > 1 and pen.style() == QtCore.Qt.PenStyle.SolidLine
        drawn = QtGui.QPen(pen)
        if drawn.widthF() <= 1:
            drawn.setWidthF(0)
        self.setPen(drawn)
        self.log = log
        self._data = (np.empty(0), np.empty(0))

    def setData(self, x, y, connect: str = "all") -> None:  # noqa: N802 - pyqtgraph's name
        """Show ``y`` against ``x`` (SI values). ``connect``: "all", "finite" (the line
        breaks at NaN) or "pairs" (separate segments: points 0-1, 2-3, ...)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        self._data = (x, y)
        with np.errstate(divide="ignore", invalid="ignore"):  # log of <= 0: a gap (NaN)
            vx = np.log10(x) if self.log[0] else x
            vy = np.log10(y) if self.log[1] else y
        if self._segments:
            self.setPath(_segment_path(vx, vy))
        elif vx.size:
            self.setPath(pg.arrayToQPath(vx, vy, connect=connect))
        else:
            self.setPath(QtGui.QPainterPath())

    def getOriginalDataset(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: N802 - pyqtgraph's name
        """The (x, y) last given to ``setData`` (before the log mapping)."""
        return self._data

    def dataBounds(self, ax: int, frac: float = 1.0, orthoRange=None):  # noqa: N802 - pyqtgraph's name
        """(min, max) of the plotted values along axis ``ax`` (view coordinates), for a
        ViewBox's automatic range (Qt's own bounds of a wide pen's path are the stroked
        outline in data units, far too wide); ``frac`` and ``orthoRange`` are not used."""
        rect = self.path().controlPointRect()
        if rect.isNull():
            return None, None
        return (rect.left(), rect.right()) if ax == 0 else (rect.top(), rect.bottom())

    def pixelPadding(self) -> float:  # noqa: N802 - pyqtgraph's name
        """Pixels the automatic range leaves around the data: half the line's width."""
        return 0.5 * self.opts["pen"].widthF()


def _segment_path(x, y) -> QtGui.QPainterPath:
    """Each segment between two consecutive finite points as a subpath of its own."""
    both = np.isfinite(x) & np.isfinite(y)
    i = np.flatnonzero(both[:-1] & both[1:])
    if not i.size:
        return QtGui.QPainterPath()
    px, py = np.empty(2 * i.size), np.empty(2 * i.size)
    px[0::2], px[1::2], py[0::2], py[1::2] = x[i], x[i + 1], y[i], y[i + 1]
    return pg.arrayToQPath(px, py, connect="pairs")


def column_spans(x: np.ndarray, ys: np.ndarray, x0: float, d0: float, px_per_unit: float):
    """What a line through (x, ys) covers in each device pixel column, as one vertical
    span per column: (xs, spans), xs (2m,) and spans (channels, 2m), low then high.

    ``ys`` is (channels, n) against increasing ``x`` (n,); x = x0 is at device pixel
    coordinate d0 and ``px_per_unit`` pixels make one unit of x. A continuous line
    covers a contiguous run of pixels in each column: from the lowest to the highest of
    its samples there and of the line where it crosses the column's edges (interpolated
    between the samples either side). So the spans, drawn at the columns' centres as
    separate segments, cover the pixels the full line covers (to a pixel), and each
    pixel is drawn once: a dense line (noise) costs a third of its polyline. A jump over
    empty columns (a gap in x) is drawn as the line across it.
    """
    col = np.floor(d0 + (x - x0) * px_per_unit).astype(np.intp)
    starts = np.concatenate(([0], np.flatnonzero(np.diff(col)) + 1))
    lo = np.minimum.reduceat(ys, starts, axis=1)
    hi = np.maximum.reduceat(ys, starts, axis=1)
    i = starts[1:]  # the first sample of each column but the first
    edge = x0 + (col[i] - d0) / px_per_unit  # where the line enters that column
    at_edge = ys[:, i - 1] + (edge - x[i - 1]) / (x[i] - x[i - 1]) * (ys[:, i] - ys[:, i - 1])
    for part in (slice(1, None), slice(None, -1)):  # the edge bounds both columns
        lo[:, part] = np.minimum(lo[:, part], at_edge)
        hi[:, part] = np.maximum(hi[:, part], at_edge)
    centre = x0 + (col[starts] + 0.5 - d0) / px_per_unit
    xs, spans = np.repeat(centre, 2), np.empty((ys.shape[0], 2 * starts.size))
    spans[:, 0::2], spans[:, 1::2] = lo, hi
    gap = np.flatnonzero(np.diff(col[starts]) > 1)  # columns without samples between
    if gap.size:
        across = np.empty((ys.shape[0], 2 * gap.size))
        across[:, 0::2], across[:, 1::2] = ys[:, starts[gap + 1] - 1], ys[:, starts[gap + 1]]
        xs = np.concatenate((xs, np.ravel(np.column_stack((x[starts[gap + 1] - 1], x[starts[gap + 1]])))))
        spans = np.concatenate((spans, across), axis=1)
    return xs, spans
