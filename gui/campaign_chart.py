"""The Campaign page's chart, drawn live (pyqtgraph): the points of the campaign's table as
they are written, the measurement beside the prediction, the row under the mouse named.

What it draws is what the campaign's own charts draw first (``labbench.campaign.figures``,
the PNGs its table's charts folder gets): for a Z-width study K_max against B, measured
(dots, 95 % interval as an error bar; a triangle where no step grew, K_max above it)
beside the exact sampled prediction (a line per velocity filter w0); for a rate study the
ED rendering error against the sample time, measured and predicted. A point that is not
ok is a red cross at its prediction. (It was a 430 x 300 bitmap of the matplotlib figure,
its text about 6 px tall, with nothing to point at.)
"""
from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from labbench.gui.keep_alive import keep_plots
from labbench.gui.live_plots import no_si_prefix

COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf")
NOT_OK = "#d62728"


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def study(rows: list[dict]) -> str | None:
    """"zwidth", "rate" or None (nothing this chart draws), as ``labbench.campaign.figures``
    tells them apart (``zwidth_rows``, ``rate_rows``)."""
    if any("zw.k_max" in r for r in rows):
        return "zwidth"
    if len({r.get("rig.sample_time_s") for r in rows if r.get("acc.ed_median") is not None}) > 1:
        return "rate"
    return None


class CampaignChart(QtWidgets.QWidget):
    """``show(rows)`` draws them; ``row_hovered(i)`` / ``row_clicked(i)`` name a row of
    ``rows`` (-1: none under the mouse)."""

    row_hovered = QtCore.Signal(int)
    row_clicked = QtCore.Signal(int)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.plot = pg.PlotWidget()
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        self.plot.addLegend(offset=(10, 5), brush=pg.mkBrush(255, 255, 255, 200))
        for side in ("bottom", "left"):
            no_si_prefix(self.plot.getAxis(side))
        self.caption = QtWidgets.QLabel("the chart fills in as the campaign's rows are written")
        self.caption.setWordWrap(True)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.plot, 1)
        lay.addWidget(self.caption)
        keep_plots(self.plot)
        self.kind: str | None = None
        self.points: list[pg.ScatterPlotItem] = []  # the hoverable ones; each spot's data: row

    def show(self, rows: list[dict]) -> None:  # noqa: A003 - the page's verb for its parts
        self.plot.clear()
        self.points = []
        self.kind = study(rows)
        if self.kind == "zwidth":
            self._zwidth(rows)
        elif self.kind == "rate":
            self._rate(rows)
        self.caption.setText(
            "hover a point to read its row, click it to select the row" if self.points else
            "no Z-width or rate study in this table yet: the chart fills in as rows are written")

    def _scatter(self, x, y, at: list[int], name, colour, symbol="o", filled=True) -> None:
        """Points (x, y) of the rows at positions ``at`` of the rows shown (each spot's data)."""
        keep = np.isfinite(x) & np.isfinite(y)
        if not keep.any():
            return
        item = pg.ScatterPlotItem(
            x=x[keep], y=y[keep], data=[at[i] for i in np.flatnonzero(keep)], symbol=symbol, size=10, pen=pg.mkPen(colour, width=1.5),
            brush=pg.mkBrush(colour if filled else "w"), hoverable=True, tip=None, hoverSize=14,
            hoverPen=pg.mkPen("k", width=2), name=name)
        item.sigHovered.connect(self._hovered)
        item.sigClicked.connect(self._clicked)
        self.plot.addItem(item)
        self.points.append(item)

    def _zwidth(self, rows: list[dict]) -> None:
        self.plot.setLabel("bottom", "virtual damping B [N s/m]")
        self.plot.setLabel("left", "largest stable stiffness K_max [N/m]")
        series: dict = {}
        for i, r in enumerate(rows):
            series.setdefault(r.get("ve.w0_rad_s"), []).append((i, r))
        for n, (w0, group) in enumerate(sorted(series.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))):
            colour = COLOURS[n % len(COLOURS)]
            name = f"w0 = {w0:g} rad/s" if isinstance(w0, (int, float)) else "no filter"
            idx = [i for i, _ in group]
            B = np.array([_num(r.get("ve.B")) for _, r in group])
            order = np.argsort(B)
            pred = np.array([_num(r.get("pred.k_max")) for _, r in group])
            line = np.isfinite(B[order]) & np.isfinite(pred[order])
            if line.any():
                self.plot.plot(B[order][line], pred[order][line], pen=pg.mkPen(colour, width=1.5),
                               name=f"exact sampled prediction ({name})")
            k = np.array([_num(r.get("zw.k_max")) for _, r in group])
            lo = np.array([_num(r.get("zw.ci_lo")) for _, r in group])
            hi = np.array([_num(r.get("zw.ci_hi")) for _, r in group])
            ranged = np.isfinite(k) & np.isfinite(lo) & np.isfinite(hi)
            if ranged.any():
                self.plot.addItem(pg.ErrorBarItem(x=B[ranged], y=k[ranged], top=(hi - k)[ranged],
                                                  bottom=(k - lo)[ranged], beam=0.02,
                                                  pen=pg.mkPen(colour)))
            self._scatter(B, k, idx, f"measured K_max, 95 % interval ({name})", colour)
            above = np.array([_num(r.get("zw.k_max_above")) for _, r in group])
            self._scatter(B, above, idx, f"no step grew: K_max above ({name})", colour, "t1", False)
            bad = np.array([r.get("status") not in ("ok", None) for _, r in group])
            self._scatter(B, np.where(bad & ~np.isfinite(k) & ~np.isfinite(above), pred, np.nan),
                          idx, "point not ok (see its row)", NOT_OK, "x")

    def _rate(self, rows: list[dict]) -> None:
        self.plot.setLabel("bottom", "sample time T [ms]")
        self.plot.setLabel("left", "ED rendering error over 2-100 rad/s, median [%]")
        T = np.array([1e3 * _num(r.get("rig.sample_time_s")) for r in rows])
        order = np.argsort(T)
        pred = np.array([100 * _num(r.get("pred.ed_median")) for r in rows])
        line = np.isfinite(T[order]) & np.isfinite(pred[order])
        if line.any():
            self.plot.plot(T[order][line], pred[order][line], pen=pg.mkPen(COLOURS[0], width=1.5),
                           name="predicted (exact sampled)")
        at = list(range(len(rows)))
        self._scatter(T, np.array([100 * _num(r.get("acc.ed_median")) for r in rows]), at,
                      "measured", COLOURS[0])
        bad = np.array([r.get("status") not in ("ok", None) for r in rows])
        self._scatter(T, np.where(bad, pred, np.nan), at, "point not ok (see its row)", NOT_OK, "x")

    @staticmethod
    def _row_of(points) -> int:
        return int(points[0].data()) if len(points) else -1

    def _hovered(self, _item, points, _ev) -> None:
        self.row_hovered.emit(self._row_of(points))

    def _clicked(self, _item, points, _ev) -> None:
        self.row_clicked.emit(self._row_of(points))
