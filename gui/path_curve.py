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
        """Show ``y`` against ``x`` (SI values; ``connect``: "all", or "finite" to break
        the line at NaN)."""
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
        """The (x, y) last given to ``setData`` (before log mapping and reduction)."""
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


def reduce_to_columns(x: np.ndarray, ys: np.ndarray, group: int, first: int):
    """(xs, ys) reduced to the first, lowest, highest and last sample of each group of
    ``group`` samples, in time order (the "M4" reduction of line charts).

    ``ys`` is (channels, n) against ``x`` (n,); returns (channels, m) arrays for both.
    Groups are aligned to the absolute sample index (``first`` is the index of sample 0),
    so that a sample stays in its group as the window scrolls and the picture does not
    flicker. The kept points are samples of the curve, and every dropped one lies inside
    its group's vertical span less than a group's width away: with groups of at most one
    pixel column the line drawn covers the same pixels as the full data, to a pixel.
    """
    if group <= 1 or x.size < 2 * group:
        return np.broadcast_to(x, ys.shape), ys
    head = first % group
    tail = -(head + x.size) % group
    xp = np.pad(x, (head, tail), mode="edge").reshape(-1, group)
    yp = np.pad(ys, ((0, 0), (head, tail)), mode="edge").reshape(ys.shape[0], -1, group)
    pick = np.zeros(yp.shape[:2] + (4,), dtype=np.intp)
    pick[..., 1], pick[..., 2], pick[..., 3] = yp.argmin(axis=2), yp.argmax(axis=2), group - 1
    pick.sort(axis=2)
    shape = (ys.shape[0], -1)
    return (np.take_along_axis(xp[None], pick, axis=2).reshape(shape),
            np.take_along_axis(yp, pick, axis=2).reshape(shape))
