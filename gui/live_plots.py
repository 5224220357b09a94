"""Live plots: time traces and the effective impedances (with a Bode tab).

Curves are created once and refreshed with ``setData`` from the window's
redraw timer (never from the acquisition thread). Pen width 1 and no
antialiasing: on this class of machine width 2 costs ~4x per frame.
"""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from labbench.readout import bandwidth_text
from labbench.gui.buffers import StreamBuffer
from labbench.gui.keep_alive import keep_plots
from labbench.gui.live_estimate import Estimate
from labbench.gui.path_curve import PathCurve, column_spans
from labbench.readout.numfmt import fmt
from labbench.readout.units import SI

pg.setConfigOptions(antialias=False, background="w", foreground="k")

W_SHOWN_OF_NYQUIST = 1 / 3
# Stacked plots below this height each had their axis titles printed over each other (the
# log dragged taller): the splitters stop there instead.
MIN_PLOT_HEIGHT = 90  # three of them, the verdicts and the log fit 1280 x 800
# The y ranges follow the estimate only where it is trustworthy: its 95 % radius within
# this fraction of |Z|. Early in a run the wide-band points (6 s into white noise: ES of
# +-400 000 N/m) would otherwise set the range and flatten the curve into a line.
TRUSTED_REL_ERR = 0.25
RIGHT_OF_LINE, LEFT_OF_LINE = (0, 0.5), (1, 0.5)  # a vertical mark's label anchor: its side
LABEL_GROUND = pg.mkBrush(255, 255, 255, 220)
WAITING = "effective impedances: waiting for data"  # under a mark's label where no curve is

COLOURS = {"position": "#1f77b4", "velocity": "#2ca02c", "command": "#d62728",
           "excitation": "#7f7f7f", "measured": "#1f5fa8", "theory": "#d95f02", "band": (31, 95, 168, 60)}


def _pen(name: str, style=QtCore.Qt.PenStyle.SolidLine):
    return pg.mkPen(COLOURS[name], width=1, style=style)


def _fit(set_range, current, lo: float, hi: float, fresh: bool = False) -> None:
    """Show [lo, hi] (padded by 5 %) unless the ``current`` range still holds it and half
    of that range is used: a range that moves every frame makes pyqtgraph re-render the
    axis (and, with autoRange, re-scan every item's bounds) on each paint. ``fresh``: the
    first data after a clear, set whatever the range was (another record's)."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return
    if hi - lo <= 0:  # flat data: a span around the value
        half = abs(lo) * 0.1 or 1.0
        lo, hi = lo - half, hi + half
    a, b = current
    if not fresh and a <= lo and hi <= b and hi - lo >= 0.5 * (b - a):
        return
    set_range(lo, hi, padding=0.05)


def _cheap_repaint(layout: pg.GraphicsLayoutWidget) -> None:
    """Keep axes, text and legend samples as pixmaps: text is the dearest part of a paint
    and, with ranges that rarely move, they are redrawn only when they change. (A cached
    item's children are not in its pixmap: the text of labels, axis titles and legends
    is a child QGraphicsTextItem, cached by itself.) The view fills its background
    itself, so Qt need not paint the widgets beneath it first."""
    cache = QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache
    for item in layout.scene().items():
        if isinstance(item, (pg.AxisItem, QtWidgets.QGraphicsTextItem, pg.ItemSample)):
            item.setCacheMode(cache)
    layout.viewport().setAttribute(QtCore.Qt.WidgetAttribute.WA_OpaquePaintEvent)


def _plot_options_off(p: pg.PlotItem) -> None:
    """No "Plot options" menu (its data transforms act on pyqtgraph's own curve items,
    not on ``PathCurve``s or the bands); the view's menu (ranges) stays."""
    p.setMenuEnabled(False, enableViewBoxMenu=True)


def _finite_span(*arrays) -> tuple[float, float]:
    """(min, max) over the finite values of ``arrays`` (NaN, NaN when there are none)."""
    v = np.concatenate([np.ravel(a) for a in arrays])
    v = v[np.isfinite(v)]
    return (float(v.min()), float(v.max())) if v.size else (np.nan, np.nan)


class TimeTraces(pg.GraphicsLayoutWidget):
    """Position, velocity estimate and forces (commanded, excitation) over the last ``window`` samples.

    Time runs relative to the newest sample on a fixed x range, the y ranges
    move only when the data leave them or use less than half of them, and there
    is no grid: then the axes are not re-rendered every frame (measured: a
    scrolling absolute time axis with grid doubled the frame time). The curves are
    ``PathCurve``s of what the line covers in each device pixel column
    (``column_spans``: the same pixels, each drawn once), redone when the plots are
    resized. Nothing is drawn while the traces are hidden (another tab): they catch
    up when shown.
    """

    def __init__(self, window: int = 5000, parent=None):
        super().__init__(parent)
        self.window = window
        self._buffer: StreamBuffer | None = None  # the one drawn (or to draw when shown)
        rows = [("position", "position", "m"), ("velocity", "velocity estimate", "m/s"),
                ("force", "force", "N")]
        self.plots = {}
        for i, (key, title, unit) in enumerate(rows):
            p = self.addPlot(row=i, col=0)
            p.setLabel("left", title, units=unit)
            no_si_prefix(p.getAxis("left"))  # the display unit chosen (set_units)
            p.enableAutoRange(x=False, y=False)
            _plot_options_off(p)
            if i:
                p.setXLink(self.plots["position"])
            p.getViewBox().sigResized.connect(self._redraw)
            self.plots[key] = p
        self.plots["force"].setLabel("bottom", "time before the newest sample", units="s")
        self.setMinimumHeight(len(rows) * MIN_PLOT_HEIGHT)
        self._span = None
        self._fresh = True  # no data drawn since the last clear: the next set the ranges
        # the force traces' legend on a row of its own under their plot, in one line: inside
        # the plot its box covered the traces' newest end
        self.legend = pg.LegendItem(colCount=2, labelTextSize="9pt")
        self.addItem(self.legend, row=len(rows), col=0)
        self.legend.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred,
                                  QtWidgets.QSizePolicy.Policy.Fixed)
        self.curves = {}
        for name, key in (("position", "position"), ("velocity", "velocity"),
                          ("excitation", "force"), ("command", "force")):
            self.curves[name] = PathCurve(_pen(name))
            self.plots[key].addItem(self.curves[name])
        for name in ("excitation", "command"):
            self.legend.addItem(self.curves[name], name)
        _cheap_repaint(self)
        keep_plots(self)
        self.frames = 0
        self.set_units(SI)

    def set_units(self, units) -> None:
        """Length unit of the position and velocity axes (``labbench.readout.units.DisplayUnits``):
        the axes scale their ticks, the data stay SI."""
        self.units = units
        for key, title, per in (("position", "position", ""), ("velocity", "velocity estimate", "/s")):
            axis = self.plots[key].getAxis("left")
            axis.setScale(units.length_of(1.0))
            self.plots[key].setLabel("left", title, units=units.length + per)

    def clear_data(self) -> None:
        self._buffer = None
        self._fresh = True
        self._empty()

    def _empty(self) -> None:
        for c in self.curves.values():
            c.setData([], [])

    def showEvent(self, ev) -> None:  # noqa: N802 - Qt override
        super().showEvent(ev)
        self._redraw()

    def update_from(self, buf: StreamBuffer) -> None:
        self._buffer = buf
        if self.isVisible():
            self._draw(buf)
            self.frames += 1

    def _redraw(self, *_) -> None:
        if self._buffer is not None and self.isVisible():
            self._draw(self._buffer)

    def _draw(self, buf: StreamBuffer) -> None:
        t = buf.channel("t", self.window)
        span = self.window * (buf.sample_time_s or 1e-3)
        if span != self._span:
            self.plots["position"].setXRange(-span, 0, padding=0)
            self._span = span
        if not t.size:
            return self._empty()
        x = t - t[-1]
        for key, names in (("position", ["position"]), ("velocity", ["velocity"]),
                           ("force", ["excitation", "command"])):
            vb = self.plots[key].getViewBox()
            ys = np.stack([buf.channel(n, self.window) for n in names])
            columns = self._device_columns(vb, span)
            if columns is not None and x.size > 1 and (x[1] - x[0]) * columns[1] < 0.5:
                xs, ys = column_spans(x, ys, -span, columns[0], columns[1])
                connect = "pairs"
            else:  # fewer than 2 samples a pixel column: the line itself
                xs, connect = x, "all"
            for n, y in zip(names, ys):
                self.curves[n].setData(xs, y, connect=connect)
            _fit(vb.setYRange, vb.viewRange()[1], ys.min(), ys.max(), self._fresh)
        self._fresh = False

    def _device_columns(self, vb: pg.ViewBox, span: float):
        """(device pixel coordinate of x = -span, pixels per second) of ``vb``, or None
        before it is laid out."""
        a, b = vb.mapViewToDevice(QtCore.QPointF(-span, 0)), vb.mapViewToDevice(QtCore.QPointF(0, 0))
        if a is None or b is None or b.x() - a.x() < 1:
            return None
        dpr = self.devicePixelRatioF()
        return a.x() * dpr, (b.x() - a.x()) * dpr / span


def no_si_prefix(axis) -> None:
    """Numbers on ``axis`` as they are, in its label's unit. pyqtgraph's
    ``enableAutoSIPrefix(False)`` applies once the prefix of the range it has at that moment
    (a frequency axis read "kHz" with ticks 0.001-0.1 after a switch to Hz): cleared here."""
    axis.enableAutoSIPrefix(False)
    axis.autoSIPrefixScale, axis.labelUnitPrefix = 1.0, ""
    axis._updateLabel()  # noqa: SLF001 - pyqtgraph's own re-label, no public form


class DecadeAxis(pg.AxisItem):
    """Log axis labelled at decades only (pyqtgraph labels minor ticks too when a
    plot spans less than about two decades, and they overlap), written alike: 0.1, 1, 10,
    100 (pyqtgraph wrote 0.1, 1, 10\u00b9, 10\u00b2 on one axis); beyond 1e-3..1e5 its own."""

    def logTickStrings(self, values, scale, spacing):
        strings = super().logTickStrings(values, scale, spacing)
        return [("" if abs(v - round(v)) >= 1e-6 else
                 f"{10.0 ** round(v) * scale:g}" if -3 <= round(v) <= 5 else s)
                for v, s in zip(values, strings)]


def _log_plot(layout, row, logy=False):
    axes = {"bottom": DecadeAxis("bottom")}
    if logy:
        axes["left"] = DecadeAxis("left")
    return layout.addPlot(row=row, col=0, axisItems=axes)


class ImpedancePlots(QtWidgets.QTabWidget):
    """ES / ED / EM against w (log axis) with band, theory and w_s*, w_b* marks; |Z| and phase on a tab.

    Cheap to redraw: no pyqtgraph grid (on log axes it cost ~3 ms per axis and
    frame) but a few decade lines and a zero line; each band is one filled path;
    theory curves are re-set only when the theory changed; the ranges are set
    from each new estimate (no autoRange scan of every item at paint time); the
    hidden tab is drawn when it is shown.
    """

    def __init__(self, parent=None):
        super().__init__(parent)
        self.effective = pg.GraphicsLayoutWidget()
        self.bode = pg.GraphicsLayoutWidget()
        self.addTab(self.effective, "Effective impedances")
        self.addTab(self.bode, "Bode |Z|, phase")
        # the title and the legend above the plots: a legend inside the stiffness plot lay
        # over the w_s* mark's label at 1280 x 800
        head = self.effective.addLayout(row=0, col=0)
        self.title = head.addLabel(WAITING, row=0, col=0, size="9pt")
        self.plots, self.curves, self.bands, self.marks = {}, {}, {}, {}
        # two lines: one rotated line was longer than a plot is tall at 1280 x 800 (they overlapped)
        rows = [("ES", "stiffness<br>ES", "N/m"), ("ED", "damping<br>ED", "N s/m"), ("EM", "mass<br>EM", "kg")]
        for i, (key, title, unit) in enumerate(rows, start=1):
            p = _log_plot(self.effective, i)
            self._setup(p, title, unit, zero_line=True)
            p.disableAutoRange()  # set from each estimate (_fit_ranges)
            if i > 1:
                p.setXLink(self.plots["ES"])
            band = QtWidgets.QGraphicsPathItem()
            band.setBrush(pg.mkBrush(COLOURS["band"]))
            band.setPen(pg.mkPen(None))
            p.addItem(band)
            self.bands[key] = band
            # measured wide, theory thin and dashed on top: both show where they agree
            self.curves[key] = _add_curve(p, pg.mkPen(COLOURS["measured"], width=3), (True, False))
            self.curves[key + "_theory"] = _add_curve(p, _pen("theory", QtCore.Qt.PenStyle.DashLine),
                                                      (True, False))
            self.plots[key] = p
        # one legend serves all rows; "theory" only while a theory curve is drawn
        self.legend = pg.LegendItem(colCount=2, labelTextSize="9pt", verSpacing=-6)
        head.addItem(self.legend, row=1, col=0)
        self.legend.addItem(self.curves["ES"], "measured (ETFE), 95 % band")
        # the labels where the curves are not (_label_side): right of w_s* (ES is not drawn
        # there), high right of w_b* (ED falls below half its level there; at 0.3 the
        # label's last line fell below a 1280 x 800 plot)
        for key, plot, at in (("ws", "ES", 0.5), ("wb", "ED", 0.6)):
            # the label on a white ground: a curve behind it does not cross its numbers
            line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#444444", width=1),
                                   label="", labelOpts={"position": at, "color": "#222222",
                                                        "fill": LABEL_GROUND,
                                                        "anchors": [RIGHT_OF_LINE] * 2})
            line.setVisible(False)
            self.plots[plot].addItem(line, ignoreBounds=True)
            self.marks[key] = line
        self.effective.setMinimumHeight(len(rows) * MIN_PLOT_HEIGHT + 40)  # and the title
        grid = self.effective.ci.layout  # the room beyond the head's own goes to the plots
        for row in range(len(rows) + 1):
            grid.setRowStretchFactor(row, 1 if row else 0)
        self.bode_plots = {"mag": _log_plot(self.bode, 0, logy=True), "phase": _log_plot(self.bode, 1)}
        self._setup(self.bode_plots["mag"], "|Z|", "N s/m", logy=True)
        self.bode_legend = self.bode_plots["mag"].addLegend(offset=(-10, -10),  # bottom right: empty
                                                           brush=pg.mkBrush(255, 255, 255, 200))
        self._setup(self.bode_plots["phase"], "phase of Z", "rad")
        self.bode_plots["phase"].setXLink(self.bode_plots["mag"])
        for k, p in self.bode_plots.items():
            log = (True, k == "mag")
            self.curves["bode_" + k] = _add_curve(p, pg.mkPen(COLOURS["measured"], width=3), log)
            self.curves["bode_" + k + "_theory"] = _add_curve(
                p, _pen("theory", QtCore.Qt.PenStyle.DashLine), log)
        self.bode_legend.addItem(self.curves["bode_mag"], "measured (ETFE)")
        self._legend_theory = False  # whether the legends list the theory now
        _cheap_repaint(self.effective)
        _cheap_repaint(self.bode)
        keep_plots(self.effective, self.bode)
        self.last: Estimate | None = None
        self._fresh = True  # no estimate since the last clear: the next one sets the ranges
        self._theory_shown = None
        self._bode_shown = None
        self.updates = 0
        self.set_units(SI)
        self.currentChanged.connect(lambda *_: self._draw_bode())

    @staticmethod
    def _setup(p, title, unit, logy=False, zero_line=False):
        p.setLabel("left", title, units=unit)
        p.setLogMode(x=True, y=logy)  # the axes; the curves map their own data (PathCurve.log)
        _plot_options_off(p)
        _add_rules(p, zero_line)
        no_si_prefix(p.getAxis("left"))
        no_si_prefix(p.getAxis("bottom"))

    def clear_data(self, title: str = WAITING) -> None:
        """Nothing drawn; ``title`` says why (the legend only while waiting for data)."""
        for c in self.curves.values():
            c.setData([], [])
        for band in self.bands.values():
            band.setPath(QtGui.QPainterPath())
        for m in self.marks.values():
            m.setVisible(False)
        self._show_theory_in_legend(False)
        self.legend.setVisible(title == WAITING)
        self.title.setText(title)
        self.last = self._theory_shown = self._bode_shown = None
        self._fresh = True

    def show_estimate(self, est: Estimate) -> None:
        # Up to a third of Nyquist (the paper's figures end near 1000 rad/s at 1 kHz):
        # beyond it the sampled loop's ED and EM swing by orders of magnitude and
        # would set the scale of the whole plot.
        ok = (est.w > 0) & (est.w <= W_SHOWN_OF_NYQUIST * est.w_nyquist)
        fx = self.units.frequency_of(1.0)  # the x axis in the display unit of frequency
        w = est.w[ok] * fx
        lw = np.log10(w)  # view x coordinates on a log axis
        excited = _excited(est)[ok]  # not reached by the excitation: not drawn
        # ES reads as stiffness where Im Z < 0, EM as mass where Im Z > 0 (paper Figure 2).
        shown = {"ES": np.where(excited & (est.Z.imag[ok] < 0), est.ES[ok], np.nan),
                 "ED": np.where(excited, est.ED[ok], np.nan),
                 "EM": np.where(excited & (est.Z.imag[ok] > 0), est.EM[ok], np.nan)}
        self.legend.setVisible(True)
        bands = {}
        for key, y in shown.items():
            self.curves[key].setData(w, y, connect="finite")
            lo, hi = est.band(key)
            bands[key] = (lo[ok], hi[ok])
            self.bands[key].setPath(_band_path(lw, lo[ok], hi[ok], np.isfinite(y)))
        th = est.theory
        if (th or {}).get("key") != self._theory_shown:
            for key in ("ES", "ED", "EM"):
                if th:
                    keep = {"ES": th["Z"].imag < 0, "EM": th["Z"].imag > 0}.get(key, True)
                    keep = keep & (th["w"] <= W_SHOWN_OF_NYQUIST * est.w_nyquist)
                    self.curves[key + "_theory"].setData(th["w"] * fx, np.where(keep, th[key], np.nan),
                                                         connect="finite")
                else:
                    self.curves[key + "_theory"].setData([], [])
            self._theory_shown = (th or {}).get("key")
        self._show_theory_in_legend(bool(th))
        trusted = (np.abs(est.Z_err) <= TRUSTED_REL_ERR * np.abs(est.Z))[ok]
        # ED ranged below w_b*, where the VE's damping holds: a damping of 1.1 N s/m must not
        # share its axis with the roll-off to -50 near Nyquist (issue 30; the report's figure
        # does the same, labbench.model.effective.focus_limits); the roll-off leaves the axes
        wb = est.wb_measured if est.renders_ve and est.wb_measured else None
        focus = {"ED": np.log10(wb * fx)} if wb and _excited_at(est, wb) else {}
        self._fit_ranges(lw, shown, bands, trusted, focus)
        for key, value in (("ws", est.ws_measured), ("wb", est.wb_measured)):
            line = self.marks[key]
            # a VE's bandwidths: none without one, none where the excitation has not been
            if value and est.renders_ve and _excited_at(est, value):
                line.setVisible(True)  # first: a hidden label ignores new text
                if line.value() != np.log10(value * fx):  # moving it re-lays out its label
                    line.setValue(np.log10(value * fx))  # view coordinates are log10 on a log axis
                # measured, then the one prediction (labbench.model.predictions: exact sampled
                # model with the device delay, the paper's closed form labelled beside it)
                # two lines: the prediction under the measurement (one line ran off the plot)
                # three: the prediction's two parts under the measurement (two ran off the plot)
                text = bandwidth_text.label(key, value, est.predicted, self.units).replace(
                    " (", "\n(", 1).replace("; ", ";\n", 1)
                if text != line.label.format:  # new text: a re-layout of the label on the next paint
                    line.label.setFormat(text)
                _label_side(line, self.plots["ES" if key == "ws" else "ED"].getViewBox())
            else:
                line.setVisible(False)
        # its source on a line of its own: a session's name ran past the plots at 1280 x 800
        plant = (f"theory: m = {fmt(est.plant.m)} kg, b = {fmt(est.plant.b)} N s/m,<br>{est.plant_source}"
                 if est.plant else "plant unknown: no theory overlay")
        masked = int(np.count_nonzero(~excited))
        unexcited = (f";<br>{masked} of {excited.size} frequencies not excited (yet): not drawn"
                     if masked else "")
        # short lines: a long one set the plot column's minimum width past the window's
        title = f"effective impedances from {est.n_samples} samples{unexcited}<br>{plant}"
        if title != self.title.text:  # a new text re-lays out the whole plot column
            self.title.setText(title)
        self.last = est
        self.updates += 1
        self._draw_bode()

    def set_units(self, units) -> None:
        """Display units (``labbench.readout.units.DisplayUnits``) of the frequency axes, the marks'
        labels and the phase; redrawn at once."""
        self.units = units
        freq = "f" if units.frequency == "Hz" else "w"
        for p in (self.plots["EM"], self.bode_plots["phase"]):
            p.setLabel("bottom", f"frequency {freq}", units=units.frequency)
        self.bode_plots["phase"].setLabel("left", "phase of Z", units=units.angle)
        self._theory_shown = self._bode_shown = None  # every curve again, in the new unit
        if self.last is not None:
            self.show_estimate(self.last)

    def _fit_ranges(self, lw, shown, bands, trusted, focus: dict) -> None:
        """x over the measured and theory frequencies; y over the trusted measured points
        and their band, the theory where something is measured (a chirp's plant theory runs
        on past what it excited) and the zero line (as autoRange would give over those, but
        computed once per estimate); the untrusted points are drawn, not ranged. ``focus``:
        a curve's highest frequency to range over (log10, view coordinates)."""
        lw_theory = []
        if self._theory_shown is not None:  # where a theory curve is drawn
            for key in shown:
                wt, yt = self.curves[key + "_theory"].getOriginalDataset()
                lw_theory.append(np.log10(wt[(wt > 0) & np.isfinite(yt)]))
        es = self.plots["ES"].getViewBox()
        fresh, self._fresh = self._fresh, False
        _fit(es.setXRange, es.viewRange()[0], *_finite_span(lw, *lw_theory), fresh)
        drawn = lw[np.isfinite(np.column_stack(list(shown.values()))).any(axis=1)]
        for key, y in shown.items():
            wt, yt = self.curves[key + "_theory"].getOriginalDataset()
            top = min(focus.get(key, np.inf), drawn.max()) if drawn.size else np.inf
            if yt is not None and drawn.size:  # the theory where something is measured
                lwt = np.log10(np.clip(wt, 1e-12, None))
                yt = yt[(lwt >= drawn.min()) & (lwt <= top)]
            keep = np.isfinite(y) & trusted & (lw <= top)
            vb = self.plots[key].getViewBox()
            _fit(vb.setYRange, vb.viewRange()[1],
                 *_finite_span(y[keep], bands[key][0][keep], bands[key][1][keep],
                               [] if yt is None else yt, [0.0]), fresh)

    def _show_theory_in_legend(self, shown: bool) -> None:
        """The legends name the theory only while a theory curve is drawn."""
        if shown == self._legend_theory:
            return
        for legend, curve in ((self.legend, "ES_theory"), (self.bode_legend, "bode_mag_theory")):
            if shown:
                legend.addItem(self.curves[curve], "theory (exact sampled model)")
            else:
                legend.removeItem(self.curves[curve])
        self._legend_theory = shown

    def _draw_bode(self) -> None:
        est = self.last
        if est is None or self.currentWidget() is not self.bode or est is self._bode_shown:
            return
        ok = (est.w > 0) & (est.w <= W_SHOWN_OF_NYQUIST * est.w_nyquist)
        fx, u = self.units.frequency_of(1.0), self.units
        Z = np.where(_excited(est), est.Z, np.nan)[ok]
        phase = np.unwrap(np.angle(Z[np.isfinite(Z)]))  # unwrapped along what is drawn
        self.curves["bode_mag"].setData(est.w[ok] * fx, np.abs(Z), connect="finite")
        self.curves["bode_phase"].setData(est.w[ok][np.isfinite(Z)] * fx, u.angle_of(phase),
                                          connect="finite")
        th = est.theory
        if th:
            shown = th["w"] <= W_SHOWN_OF_NYQUIST * est.w_nyquist
            wt, Zt = th["w"][shown] * fx, th["Z"][shown]
            self.curves["bode_mag_theory"].setData(wt, np.abs(Zt), connect="finite")
            self.curves["bode_phase_theory"].setData(wt, u.angle_of(np.unwrap(np.angle(Zt))),
                                                     connect="finite")
        else:
            self.curves["bode_mag_theory"].setData([], [])
            self.curves["bode_phase_theory"].setData([], [])
        self._bode_shown = est


def _label_side(line: pg.InfiniteLine, vb: pg.ViewBox) -> None:
    """A mark's label right of its line, on a white ground, where ES is not drawn (past
    w_s*) and ED falls (past w_b*); where the right has no room for it, left of the line
    with no ground: the measured curve shows through. pyqtgraph chose the side by the
    view's vertical centre: the white ground lay over the measured ES or ED in the band
    K and B are read from (they looked faint there)."""
    try:
        room = (vb.viewRange()[0][1] - line.value()) / vb.viewPixelSize()[0]  # pixels
    except (ZeroDivisionError, ValueError, TypeError):  # a view not laid out yet
        room = np.inf
    right = room >= line.label.boundingRect().width()
    anchor = RIGHT_OF_LINE if right else LEFT_OF_LINE
    if line.label.anchors[0] != anchor:
        line.label.anchors = [anchor] * 2
        line.label.fill = LABEL_GROUND if right else pg.mkBrush(None)
        line.label.updatePosition()
        line.label.update()


def _excited(est: Estimate) -> np.ndarray:
    """Which frequencies of ``est`` the excitation reached (all when it does not say)."""
    return est.excited if est.excited is not None else np.ones(est.w.shape, bool)


def _excited_at(est: Estimate, w: float) -> bool:
    """Whether the excitation reached the frequency band nearest ``w``."""
    return bool(_excited(est)[np.argmin(np.abs(np.log(est.w.clip(1e-12) / w)))])


def _add_rules(p: pg.PlotItem, zero_line: bool) -> None:
    """Light lines at the decades of the log x axis (no pyqtgraph grid: on log axes it
    cost ~3 ms per axis and frame) and, with ``zero_line``, a line at y = 0. Two path
    items that Qt draws by itself, re-made when the view's range moves; as pyqtgraph
    InfiniteLines they were seven Python paints and bounds queries per plot and frame."""
    vb = p.getViewBox()
    # every item goes into the scene at once: a Python-owned QGraphicsItem freed after
    # the QApplication (at the interpreter's exit) crashes it
    decades = QtWidgets.QGraphicsPathItem()
    decades.setPen(pg.mkPen("#dddddd", width=0))  # width 0: the same 1-pixel line as width 1
    p.addItem(decades, ignoreBounds=True)
    zero = None
    if zero_line:
        zero = QtWidgets.QGraphicsPathItem()
        zero.setPen(pg.mkPen("#999999", width=0))
        p.addItem(zero, ignoreBounds=True)

    def remake(*_):  # each line reaches a view's height (width) beyond the view: clipped
        (x0, x1), (y0, y1) = vb.viewRange()
        lines = QtGui.QPainterPath()
        for decade in range(-1, 5):
            lines.moveTo(decade, 2 * y0 - y1)
            lines.lineTo(decade, 2 * y1 - y0)
        decades.setPath(lines)
        if zero is not None:
            line = QtGui.QPainterPath()
            line.moveTo(2 * x0 - x1, 0.0)
            line.lineTo(2 * x1 - x0, 0.0)
            zero.setPath(line)

    vb.sigRangeChanged.connect(remake)
    remake()


def _add_curve(p: pg.PlotItem, pen, log) -> PathCurve:
    curve = PathCurve(pen, log)
    p.addItem(curve)
    return curve


def _band_path(x, lo, hi, keep) -> QtGui.QPainterPath:
    """One filled polygon per run of finite points (lo forward, hi backward); NaN
    separators start a new subpath, and a filled subpath closes itself."""
    idx = np.flatnonzero(keep)
    runs = [r for r in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if r.size >= 2]
    if not runs:
        return QtGui.QPainterPath()
    xs, ys = [], []
    for r in runs:
        xs += [x[r], x[r][::-1], [np.nan]]
        ys += [lo[r], hi[r][::-1], [np.nan]]
    return pg.arrayToQPath(np.concatenate(xs), np.concatenate(ys), connect="finite")
