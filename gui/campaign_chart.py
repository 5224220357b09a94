"""The Campaign page's chart, drawn live (pyqtgraph): every panel and point of the charts
the campaign's table makes, as its rows are written, the row under the mouse named.

What it draws is the data of ``labbench.campaign.figures`` (``Chart``: panels of
``Series``), the same the PNGs in the table's charts folder and the report are drawn from:
for a Z-width, K_max against B per velocity filter w0, measured with its 95 % interval
(filled: not passive; hollow: within the passive bound; a triangle: no step grew), the
exact sampled and the paper's boundaries, the passive ones (sampled-data, Colgate &
Schenkel, quantisation), and with the friction known the friction-aware boundary (curve)
and each point's (diamonds); for a rate study its four panels against the sample time (ED
and ES errors, the bandwidths, K_max), measured beside predicted. (It drew only the first
panel's measured points and exact line: the PNG had the rest.)
"""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from matplotlib.colors import to_hex
from PySide6 import QtCore, QtWidgets

from labbench.gui.keep_alive import keep_plots
from labbench.gui.live_plots import no_si_prefix

PLOT_PX = 200  # the least height of a plot; its legend below it, what does not fit scrolls
HINT = "hover a point to read its row, click it to select the row"
DASHES = {"-": QtCore.Qt.PenStyle.SolidLine, "--": QtCore.Qt.PenStyle.DashLine,
          ":": QtCore.Qt.PenStyle.DotLine, "-.": QtCore.Qt.PenStyle.DashDotLine}
SYMBOLS = {"o": "o", "s": "s", "^": "t1", "D": "d", "x": "x"}  # matplotlib's -> pyqtgraph's


def _pen(s, width=None):
    pen = pg.mkPen(to_hex(s.colour), width=s.width if width is None else width)
    if isinstance(s.style, tuple):  # (offset, (on, off, ...)) in line widths, as matplotlib's
        pen.setDashPattern([float(v) for v in s.style[1]])
    else:
        pen.setStyle(DASHES[s.style])
    return pen


class CampaignChart(QtWidgets.QWidget):
    """``show(charts, rows)`` draws them (``rows``: the table's, which each point names);
    ``row_hovered(i)`` / ``row_clicked(i)`` name a row (-1: none under the mouse)."""

    row_hovered = QtCore.Signal(int)
    row_clicked = QtCore.Signal(int)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.canvas = pg.GraphicsLayoutWidget()
        self.canvas.setBackground("w")
        self.title = QtWidgets.QLabel()
        self.title.setWordWrap(True)
        self.caption = QtWidgets.QLabel("the chart fills in as the campaign's rows are written")
        self.caption.setWordWrap(True)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.room = QtWidgets.QScrollArea()  # a rate study's 2 x 2 panels scroll on a short page
        self.room.setWidgetResizable(True)
        self.room.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        self.room.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.room.setWidget(self.canvas)
        lay.addWidget(self.title)
        lay.addWidget(self.room, 1)
        lay.addWidget(self.caption)
        self.kind: str | None = None
        self.plots: list[pg.PlotItem] = []  # one per panel, in the charts' order
        self.panels: list = []  # the panel each plot draws
        self.drawn: list[list[tuple]] = []  # per plot: (series, item) of each series drawn
        self.points: list[pg.ScatterPlotItem] = []  # the hoverable ones; each spot's data: row

    def show(self, charts: list, rows: list[dict]) -> None:  # noqa: A003 - the page's verb
        self.canvas.clear()
        self.plots, self.panels, self.drawn, self.points = [], [], [], []
        self.kind = charts[0].name if charts else None
        top, legends = 0, {}
        for chart in charts:
            for n, panel in enumerate(chart.panels):
                row = top + n // chart.columns
                legend = self._panel(panel, row, n % chart.columns)
                legends[row] = max(legends.get(row, 0.0), legend.preferredHeight())
            top += -(-len(chart.panels) // chart.columns)
        # each row's plot at least PLOT_PX tall above its whole legend: the room scrolls
        self.canvas.setMinimumHeight(int(sum(PLOT_PX + 8 + h for h in legends.values())))
        keep_plots(*self.plots)
        self.title.setText("<br>".join(f"<b>{c.title}</b>" + (f"<br><small>{c.foot}</small>"
                                                               if c.foot else "") for c in charts))
        self.caption.setText(HINT if self.points else
                             "no Z-width or rate study in this table yet: the chart fills in as "
                             "rows are written")

    def _panel(self, panel, row: int, col: int) -> None:
        plot = self.canvas.addPlot(row=2 * row, col=col)
        plot.setTitle(panel.title, size="8pt")
        plot.setLabel("bottom", panel.xlabel)
        plot.setLabel("left", panel.ylabel)
        plot.showGrid(x=True, y=True, alpha=0.3)
        for side in ("bottom", "left"):
            no_si_prefix(plot.getAxis(side))
        plot.setLogMode(x=panel.xlog, y=panel.ylog)
        if panel.xticks:
            plot.getAxis("bottom").setTicks([[(self._at(t, panel.xlog), f"{t:g}")
                                              for t in panel.xticks]])
        # the legend under the plot, in two columns: inside it covered half the curves
        legend = pg.LegendItem(labelTextSize="7pt", colCount=2, verSpacing=-6)
        self.canvas.addItem(legend, row=2 * row + 1, col=col)
        self.plots.append(plot)
        self.panels.append(panel)
        self.drawn.append([])
        for s in panel.series:
            item = self._series(plot, legend, panel, s)
            self.drawn[-1].append((s, item))
        if panel.y_from_zero:
            plot.enableAutoRange(y=False)
            plot.autoRange()
            _, (lo, hi) = plot.viewRange()
            plot.setYRange(0, hi, padding=0)
        return legend

    @staticmethod
    def _at(v, log: bool):
        """A value where a scatter item puts it: pyqtgraph's log axes take log10 of the data
        only in items that have a log mode (lines), not in scatter or error-bar items."""
        v = np.asarray(v, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log10(v) if log else v

    def _series(self, plot, legend, panel, s):
        colour = to_hex(s.colour)
        if s.kind == "level":
            item = pg.InfiniteLine(pos=float(s.y[0]), angle=0, pen=_pen(s))
            plot.addItem(item)
            legend.addItem(pg.PlotDataItem(pen=_pen(s)), s.label)
            return item
        if s.kind == "line":
            keep = np.isfinite(s.x) & np.isfinite(s.y)
            item = pg.PlotDataItem(s.x[keep], s.y[keep], pen=_pen(s))
            plot.addItem(item)
            legend.addItem(item, s.label)
            return item
        x, y = self._at(s.x, panel.xlog), self._at(s.y, panel.ylog)
        keep = np.isfinite(x) & np.isfinite(y)
        if s.lo is not None and s.hi is not None:
            bars = keep & ((np.isfinite(s.lo) & np.isfinite(s.hi)) if s.faint_bars
                           else (np.isfinite(s.lo) | np.isfinite(s.hi)))
            if bars.any():
                plot.addItem(pg.ErrorBarItem(
                    x=x[bars], y=y[bars], top=np.where(np.isfinite(s.hi), s.hi - s.y, 0)[bars],
                    bottom=np.where(np.isfinite(s.lo), s.y - s.lo, 0)[bars], beam=0.02,
                    pen=pg.mkPen(colour, width=0.6 if s.faint_bars else 1)))
        face = {None: colour, "white": "w", "none": None}[s.face]
        item = pg.ScatterPlotItem(
            x=x[keep], y=y[keep], data=[s.rows[i] for i in np.flatnonzero(keep)] if s.rows else None,
            symbol=SYMBOLS[s.marker], size=1.6 * s.size, pen=pg.mkPen(colour, width=1.5),
            brush=pg.mkBrush(face) if face else pg.mkBrush(0, 0, 0, 0),
            hoverable=bool(s.rows), tip=None, hoverSize=1.6 * s.size + 4,
            hoverPen=pg.mkPen("k", width=2))
        plot.addItem(item)
        if s.label:
            legend.addItem(item, s.label)
        if s.rows:
            item.sigHovered.connect(self._hovered)
            item.sigClicked.connect(self._clicked)
            self.points.append(item)
        return item

    def shown(self, plot: int) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
        """(label, kind, x, y) of each series plot ``plot`` holds, read back from its items
        (in data units: a log axis's log10 undone)."""
        out = []
        panel = self.panels[plot]
        for s, item in self.drawn[plot]:
            if isinstance(item, pg.InfiniteLine):
                x, y = np.array([]), np.array([item.value()])
            elif isinstance(item, pg.ScatterPlotItem):
                x, y = item.getData()
                x = 10 ** x if panel.xlog else x
                y = 10 ** y if panel.ylog else y
            else:
                x, y = item.xData, item.yData  # a line's data as given (its log mode aside)
            out.append((s.label, s.kind, np.asarray(x, float), np.asarray(y, float)))
        return out

    @staticmethod
    def _row_of(points) -> int:
        return int(points[0].data()) if len(points) else -1

    def _hovered(self, _item, points, _ev) -> None:
        self.row_hovered.emit(self._row_of(points))

    def _clicked(self, _item, points, _ev) -> None:
        self.row_clicked.emit(self._row_of(points))

