"""Live plots: time traces and the effective impedances (with a Bode tab).

Curves are created once and refreshed with ``setData`` from the window's
redraw timer (never from the acquisition thread). Pen width 1 and no
antialiasing: on this class of machine width 2 costs ~4x per frame.
"""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from gui.buffers import StreamBuffer
from gui.live_estimate import Estimate

pg.setConfigOptions(antialias=False, background="w", foreground="k")

COLOURS = {"position": "#1f77b4", "velocity": "#2ca02c", "command": "#d62728",
           "excitation": "#7f7f7f", "measured": "#1f5fa8", "theory": "#d95f02", "band": (31, 95, 168, 60)}


def _pen(name: str, style=QtCore.Qt.PenStyle.SolidLine):
    return pg.mkPen(COLOURS[name], width=1, style=style)


class TimeTraces(pg.GraphicsLayoutWidget):
    """Position, velocity estimate and forces (commanded, excitation) over the last ``window`` samples."""

    def __init__(self, window: int = 5000, parent=None):
        super().__init__(parent)
        self.window = window
        rows = [("position", "position", "m"), ("velocity", "velocity estimate", "m/s"),
                ("force", "force", "N")]
        self.plots = {}
        for i, (key, title, unit) in enumerate(rows):
            p = self.addPlot(row=i, col=0)
            p.setLabel("left", title, units=unit)
            p.showGrid(x=True, y=True, alpha=0.3)
            p.setClipToView(True)
            p.setDownsampling(auto=True, mode="peak")
            if i:
                p.setXLink(self.plots["position"])
            self.plots[key] = p
        self.plots["force"].setLabel("bottom", "time", units="s")
        self.plots["force"].addLegend(offset=(-10, 5))
        self.curves = {
            "position": self.plots["position"].plot(pen=_pen("position")),
            "velocity": self.plots["velocity"].plot(pen=_pen("velocity")),
            "excitation": self.plots["force"].plot(pen=_pen("excitation"), name="excitation"),
            "command": self.plots["force"].plot(pen=_pen("command"), name="command"),
        }
        self.frames = 0

    def clear_data(self) -> None:
        for c in self.curves.values():
            c.setData([], [])

    def update_from(self, buf: StreamBuffer) -> None:
        t = buf.channel("t", self.window)
        for name, curve in self.curves.items():
            curve.setData(t, buf.channel(name, self.window), skipFiniteCheck=True)
        self.frames += 1


class ImpedancePlots(QtWidgets.QTabWidget):
    """ES / ED / EM against w (log axis) with band, theory and w_s*, w_b* marks; |Z| and phase on a tab."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.effective = pg.GraphicsLayoutWidget()
        self.bode = pg.GraphicsLayoutWidget()
        self.addTab(self.effective, "Effective impedances")
        self.addTab(self.bode, "Bode |Z|, phase")
        self.title = self.effective.addLabel("effective impedances: waiting for data", row=0, col=0)
        self.plots, self.curves, self.bands, self.marks = {}, {}, {}, {}
        rows = [("ES", "stiffness ES", "N/m"), ("ED", "damping ED", "N s/m"), ("EM", "mass EM", "kg")]
        for i, (key, title, unit) in enumerate(rows, start=1):
            p = self.effective.addPlot(row=i, col=0)
            self._setup(p, title, unit)
            if key == "ES":
                p.addLegend(offset=(-10, 5))
            if i > 1:
                p.setXLink(self.plots["ES"])
            lo = p.plot(pen=None)
            hi = p.plot(pen=None)
            self.bands[key] = (lo, hi)
            p.addItem(pg.FillBetweenItem(lo, hi, brush=COLOURS["band"]))
            named = key == "ES"  # one legend (on ES) serves all three rows
            self.curves[key] = p.plot(pen=_pen("measured"),
                                      name="measured (ETFE), 95 % band" if named else None)
            self.curves[key + "_theory"] = p.plot(pen=_pen("theory", QtCore.Qt.PenStyle.DashLine),
                                                  name="theory" if named else None)
            self.plots[key] = p
        self.plots["EM"].setLabel("bottom", "frequency w", units="rad/s")
        for key, plot in (("ws", "ES"), ("wb", "ED")):
            line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#444444", width=1),
                                   label="", labelOpts={"position": 0.85, "color": "#222222"})
            line.setVisible(False)
            self.plots[plot].addItem(line)
            self.marks[key] = line
        self.bode_plots = {
            "mag": self.bode.addPlot(row=0, col=0),
            "phase": self.bode.addPlot(row=1, col=0),
        }
        self._setup(self.bode_plots["mag"], "|Z|", "N s/m", logy=True)
        self._setup(self.bode_plots["phase"], "phase of Z", "deg")
        self.bode_plots["phase"].setXLink(self.bode_plots["mag"])
        self.bode_plots["phase"].setLabel("bottom", "frequency w", units="rad/s")
        for k, p in self.bode_plots.items():
            self.curves["bode_" + k] = p.plot(pen=_pen("measured"))
            self.curves["bode_" + k + "_theory"] = p.plot(pen=_pen("theory", QtCore.Qt.PenStyle.DashLine))
        self.last: Estimate | None = None
        self.updates = 0

    @staticmethod
    def _setup(p, title, unit, logy=False):
        p.setLabel("left", title, units=unit)
        p.setLogMode(x=True, y=logy)
        p.showGrid(x=True, y=True, alpha=0.3)
        p.getAxis("left").enableAutoSIPrefix(False)
        p.getAxis("bottom").enableAutoSIPrefix(False)

    def clear_data(self) -> None:
        for c in self.curves.values():
            c.setData([], [])
        for lo, hi in self.bands.values():
            lo.setData([], [])
            hi.setData([], [])
        for m in self.marks.values():
            m.setVisible(False)
        self.title.setText("effective impedances: waiting for data")
        self.last = None

    def show_estimate(self, est: Estimate) -> None:
        ok = est.w > 0
        w = est.w[ok]
        # ES reads as stiffness where Im Z < 0, EM as mass where Im Z > 0 (paper Figure 2).
        shown = {"ES": np.where(est.Z.imag[ok] < 0, est.ES[ok], np.nan),
                 "ED": est.ED[ok],
                 "EM": np.where(est.Z.imag[ok] > 0, est.EM[ok], np.nan)}
        for key, y in shown.items():
            self.curves[key].setData(w, y, connect="finite")
            lo, hi = est.band(key)
            fin = np.isfinite(y)
            self.bands[key][0].setData(w[fin], lo[ok][fin])
            self.bands[key][1].setData(w[fin], hi[ok][fin])
        th = est.theory
        for key in ("ES", "ED", "EM"):
            if th:
                keep = (th["Z"].imag < 0) if key == "ES" else (th["Z"].imag > 0) if key == "EM" else True
                self.curves[key + "_theory"].setData(th["w"], np.where(keep, th[key], np.nan),
                                                     connect="finite")
            else:
                self.curves[key + "_theory"].setData([], [])
        self.curves["bode_mag"].setData(w, np.abs(est.Z[ok]))
        self.curves["bode_phase"].setData(w, np.degrees(np.unwrap(np.angle(est.Z[ok]))))
        if th:
            self.curves["bode_mag_theory"].setData(th["w"], np.abs(th["Z"]))
            self.curves["bode_phase_theory"].setData(th["w"], np.degrees(np.unwrap(np.angle(th["Z"]))))
        for key, value, theory, sym in (("ws", est.ws_measured, est.ws_theory, "w_s*"),
                                        ("wb", est.wb_measured, est.wb_theory, "w_b*")):
            line = self.marks[key]
            if value:
                line.setValue(np.log10(value))  # view coordinates are log10 on a log axis
                text = f"{sym} = {value:.0f} rad/s"
                if theory:
                    text += f" (theory {theory:.0f})"
                line.label.setFormat(text)
                line.setVisible(True)
            else:
                line.setVisible(False)
        plant = (f"m = {est.plant.m * 1e3:.1f} g, b = {est.plant.b:.3f} N s/m ({est.plant_source})"
                 if est.plant else "plant unknown: no theory overlay")
        self.title.setText(f"effective impedances from {est.n_samples} samples; {plant}")
        self.last = est
        self.updates += 1
