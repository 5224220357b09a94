"""The Design page: sliders for K, B, w0 and T over the rig's device, and the three corners of
the trade-off redrawn at every move (``labbench.design.tradeoffs``, docs/design.md).

Stability (K_max of the exact sampled loop, the margin, the passive bounds), accuracy (w_s*,
w_b*, rendered B, ED error at 10 Hz; the ED curve of the exact sampled model and of the
paper's eq. 2) and force noise (the command's and the felt force's spectra with the felt band,
their RMS against the noise limit; with the device's Coulomb friction, its part), each number
with the model it comes from in its tooltip.
The work is synchronous, in the window's thread: one setting costs a K_max search (cached per
B, w0, T: moving K reuses it), one noise spectrum and two impedance curves
(``bench/bench_design.py`` times a slider move to the painted page).
"""
from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from labbench.design.tradeoffs import EXCITATION_N, MODELS, Designer, Device, Targets, device_for
from labbench.gui.keep_alive import keep_plots
from labbench.gui.live_plots import COLOURS, DecadeAxis
from labbench.model import linear
from labbench.model.noise import STICK_SHARE_MAX
from labbench.readout.numfmt import fmt
from labbench.readout.units import SI
from labbench.rig import Rig

# slider name -> (label, unit, values, default)
SLIDERS = {
    "K": ("stiffness K", "N/m", np.geomspace(1.0, 5000.0, 241), 50.0),
    "B": ("damping B", "N s/m", np.round(np.linspace(0.0, 5.0, 101), 3), 1.0),
    "w0": ("filter w0", "rad/s", np.geomspace(10.0, 3000.0, 201), 125.0),
    "T": ("period T", "ms", np.array([0.25, 0.5, 1.0, 2.0, 4.0]), 1.0),
}
N_CURVE = 200  # frequencies of the ED curves
N_SPECTRUM = 600  # frequencies of the noise spectra drawn
# the ED curves stop at this share of Nyquist: above, the sampled model's hold advance turns
# mass into large negative ED (docs/theory.md) and would set the scale
W_MAX_NYQUIST = 0.3
SETTINGS_KEY = "design/sliders"


class DesignView(QtWidgets.QWidget):
    """Sliders emit nothing outward: every move redraws the page at once (``redraw``)."""

    redrawn = QtCore.Signal()  # after each redraw (the bench and tests wait on it)

    def __init__(self, device: Device | None = None, settings=None, parent=None):
        super().__init__(parent)
        self.settings = settings
        self.units = SI  # display units (set_units): the frequencies shown; the model stays SI
        self.designer = Designer(device or device_for(Rig(), simulated=False))
        self.point = None
        self.sliders: dict[str, QtWidgets.QSlider] = {}
        self.values: dict[str, QtWidgets.QLabel] = {}
        controls = QtWidgets.QGridLayout()
        for row, (name, (label, unit, values, default)) in enumerate(SLIDERS.items()):
            s = QtWidgets.QSlider(QtCore.Qt.Orientation.Horizontal)
            s.setRange(0, len(values) - 1)
            s.setValue(int(np.argmin(np.abs(values - default))))
            s.setToolTip(f"{label} ({unit})")
            s.valueChanged.connect(self.redraw)
            value = QtWidgets.QLabel()
            value.setMinimumWidth(90)
            controls.addWidget(QtWidgets.QLabel(label), row, 0)
            controls.addWidget(s, row, 1)
            controls.addWidget(value, row, 2)
            self.sliders[name], self.values[name] = s, value
        self.limit = QtWidgets.QDoubleSpinBox()
        self.limit.setRange(0.0, 1000.0)
        self.limit.setDecimals(2)
        self.limit.setSuffix(" mN")
        self.limit.setSpecialValueText("none")
        self.limit.setToolTip("largest acceptable force noise the loop commands, rms in the "
                              "felt band 10-500 Hz (none: 0)")
        self.limit.valueChanged.connect(self._limit_changed)
        controls.addWidget(QtWidgets.QLabel("noise limit"), len(SLIDERS), 0)
        controls.addWidget(self.limit, len(SLIDERS), 1)
        self.device_line = QtWidgets.QLabel()
        self.device_line.setWordWrap(True)
        self.numbers = Numbers()

        self.plots = pg.GraphicsLayoutWidget()
        self.noise_plot = self.plots.addPlot(
            row=0, col=0, axisItems={"bottom": DecadeAxis("bottom"), "left": DecadeAxis("left")})
        self.noise_plot.setLogMode(True, True)
        self.noise_plot.setLabel("bottom", "frequency (Hz)")
        self.noise_plot.setLabel("left", "force noise (mN/√Hz)")
        self.noise_plot.addLegend(offset=(-10, 10))
        self.band = pg.LinearRegionItem(movable=False, brush=(31, 95, 168, 30), pen=pg.mkPen(None))
        self.noise_plot.addItem(self.band)
        self.curves = {
            "command": self.noise_plot.plot(pen=pg.mkPen(COLOURS["command"], width=1),
                                            name="command"),
            "felt": self.noise_plot.plot(pen=pg.mkPen(COLOURS["theory"], width=1),
                                         name="force at the actuator"),
        }
        self.ed_plot = self.plots.addPlot(row=1, col=0, axisItems={"bottom": DecadeAxis("bottom")})
        self.ed_plot.setLogMode(True, False)
        self.ed_plot.setLabel("left", "ED (N s/m)")
        self.ed_plot.addLegend(offset=(-10, 10))
        self.curves["ed_sampled"] = self.ed_plot.plot(
            pen=pg.mkPen(COLOURS["measured"], width=1), name="exact sampled (an ETFE)")
        self.curves["ed_paper"] = self.ed_plot.plot(
            pen=pg.mkPen(COLOURS["theory"], width=1, style=QtCore.Qt.PenStyle.DashLine),
            name="paper eq. 2 (felt)")
        dotted, dashed = QtCore.Qt.PenStyle.DotLine, QtCore.Qt.PenStyle.DashLine
        self.target_line = pg.InfiniteLine(angle=0, pen=pg.mkPen("#555", style=dotted))
        self.wb_line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#555", style=dashed))
        self.ed_plot.addItem(self.target_line)
        self.ed_plot.addItem(self.wb_line)
        for plot in (self.noise_plot, self.ed_plot):  # a label re-laid at every range change
            for side in ("left", "bottom"):  # costs more than the curves: units are fixed
                plot.getAxis(side).enableAutoSIPrefix(False)
        self.noise_plot.enableAutoRange(x=False)  # the frequency range is the loop's
        self.ed_plot.enableAutoRange(x=False)
        keep_plots(self.plots)

        left = QtWidgets.QVBoxLayout()
        left.addLayout(controls)
        left.addWidget(self.device_line)
        left.addWidget(self.numbers, 1)
        panel = QtWidgets.QWidget()
        panel.setLayout(left)
        panel.setMaximumWidth(430)
        layout = QtWidgets.QHBoxLayout(self)
        layout.addWidget(panel)
        layout.addWidget(self.plots, 1)
        self._restore()
        self.set_units(SI)

    def set_units(self, units) -> None:
        """Display units (``labbench.readout.units.DisplayUnits``) of the frequencies: w0, w_s*,
        w_b* and the ED plot's axis (the noise spectra are per Hz, in Hz, whatever is chosen)."""
        self.units = units
        self.numbers.units = units
        freq = "f" if units.frequency == "Hz" else "w"
        self.ed_plot.setLabel("bottom", f"frequency {freq} ({units.frequency})")
        self.sliders["w0"].setToolTip(f"{SLIDERS['w0'][0]} ({units.frequency})")
        self.redraw()

    # ----- inputs ---------------------------------------------------------------------------
    def value(self, name: str) -> float:
        v = float(SLIDERS[name][2][self.sliders[name].value()])
        return v * 1e-3 if name == "T" else v

    def set_device(self, device: Device, T: float | None = None) -> None:
        """Design for ``device`` (the window's rig and its identified plant) from now on, the
        period slider at the rig's ``T`` when it offers it."""
        changed = device != self.designer.device
        if T is not None:
            values = SLIDERS["T"][2] * 1e-3
            at = int(np.argmin(np.abs(values - T)))
            if abs(values[at] - T) <= 1e-9 * T and at != self.sliders["T"].value():
                self.sliders["T"].blockSignals(True)
                self.sliders["T"].setValue(at)
                self.sliders["T"].blockSignals(False)
                changed = True
        if changed:
            if device != self.designer.device:
                self.designer = Designer(device, self.designer.targets)
            self.redraw()

    def _limit_changed(self, mn: float) -> None:
        self.designer = self.designer.retarget(Targets(noise_limit_n=mn * 1e-3 if mn > 0 else None))
        self.redraw()

    def _restore(self) -> None:
        if self.settings is None:
            return
        saved = self.settings.value(SETTINGS_KEY, "", type=str)
        for item in saved.split(";") if saved else ():
            name, _, pos = item.partition("=")
            if name in self.sliders and pos.isdigit():
                self.sliders[name].blockSignals(True)
                self.sliders[name].setValue(int(pos))
                self.sliders[name].blockSignals(False)

    def _remember(self) -> None:
        if self.settings is not None:
            self.settings.setValue(SETTINGS_KEY, ";".join(f"{n}={s.value()}"
                                                          for n, s in self.sliders.items()))

    # ----- the redraw -----------------------------------------------------------------------
    def redraw(self) -> None:
        K, B, w0, T = (self.value(n) for n in ("K", "B", "w0", "T"))
        for name in SLIDERS:
            v = self.value(name)
            if name == "w0":
                self.values[name].setText(f"{fmt(self.units.frequency_of(v), 4)} {self.units.frequency}")
                continue
            self.values[name].setText(f"{fmt(v * 1e3 if name == 'T' else v, 4)} {SLIDERS[name][1]}")
        d = self.designer.device
        self.device_line.setText(
            f"device: m = {fmt(d.plant.m)} kg, b = {fmt(d.plant.b)} N s/m, delay "
            f"{fmt(1e3 * d.latency)} ms, encoder step {fmt(1e6 * d.quantum_m)} um, amplifier "
            f"noise {fmt(1e3 * d.force_noise_n)} mN"
            + (f", Coulomb friction {fmt(d.coulomb_n)} N ({d.sources.get('coulomb', 'given')})"
               if d.coulomb_n else ""))
        p, fn = self.designer.detail(K, B, w0, T)
        self.point = p
        self.numbers.show_point(p, self.designer.targets)
        if fn is not None:
            # the model's grid (up to 2^21 points near a sharp resonance) thinned to
            # N_SPECTRUM log-spaced points: a curve of more costs paint time, shows nothing more
            keep = np.unique(np.searchsorted(fn.f_hz, np.geomspace(
                fn.f_hz[1], fn.f_hz[-1], N_SPECTRUM)))
            f = fn.f_hz[keep]
            self.curves["command"].setData(f, 1e3 * np.sqrt(fn.psd_command[keep]))
            self.curves["felt"].setData(f, 1e3 * np.sqrt(fn.psd_force[keep]))
            lo, hi = fn.band_hz
            self.band.setRegion((math.log10(max(lo, f[0])), math.log10(min(hi, f[-1]))))
            self.noise_plot.setXRange(math.log10(f[0]), math.log10(f[-1]), padding=0)
        else:
            for name in ("command", "felt"):
                self.curves[name].setData([], [])
        ve = self.designer.ve(K, B, w0, T)
        w = np.geomspace(0.1, W_MAX_NYQUIST * math.pi / T, N_CURVE)
        fx = self.units.frequency_of(1.0)  # the axis in the display unit; the model in rad/s
        self.curves["ed_sampled"].setData(fx * w, linear.z_sampled(d.plant, ve, w, d.latency).real)
        self.curves["ed_paper"].setData(fx * w, linear.z_paper(d.plant, ve, w, d.latency).real)
        target = d.plant.b + B
        self.target_line.setValue(target)
        self.ed_plot.setYRange(-0.5 * target, 1.5 * target, padding=0)
        self.ed_plot.setXRange(math.log10(fx * w[0]), math.log10(fx * w[-1]), padding=0)
        self.wb_line.setVisible(p.wb_star is not None)
        if p.wb_star is not None:
            self.wb_line.setValue(math.log10(fx * p.wb_star))
        self._remember()
        self.redrawn.emit()


# the numbers panel: (key, name, model); a key None is a heading
ROWS = (
    (None, "stability", ""),
    ("k_max", "K_max", "exact sampled loop"),
    ("margin", "margin K_max / K", "exact sampled loop"),
    ("k_passive", "passive K", "Colgate & Schenkel"),
    ("k_quantised", "passive K, friction", "Abbott & Okamura 2 fc/Δ"),
    ("k_friction", "stable K, 1 mm swings", "with friction (describing fn.)"),
    (None, "accuracy", ""),
    ("ws_star", "w_s*", "exact sampled ES"),
    ("wb_star", "w_b*", "exact sampled ED"),
    ("rendered_B", "rendered B", "ED(0), exact sampled"),
    ("ed_error_sampled", "ED error at 10 Hz", "exact sampled (an ETFE)"),
    ("ed_error_paper", "ED error at 10 Hz", "paper eq. 2 (felt)"),
    (None, "force noise, 10-500 Hz", ""),
    ("noise_command", "command", "labbench.model.noise"),
    ("noise_felt", "felt (held, + amplifier)", "labbench.model.noise"),
    ("noise_friction", "of which friction", f"Booton + arcsine law, {EXCITATION_N:g} N white"),
)


class Numbers(QtWidgets.QWidget):
    """The numbers of one setting: a grid of plain labels whose values alone change (a rich
    text table laid out again at every move cost more than the plots: 6 ms of 13)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.units = SI  # of w_s* and w_b* (DesignView.set_units)
        grid = QtWidgets.QGridLayout(self)
        grid.setContentsMargins(0, 0, 0, 0)
        grid.setVerticalSpacing(2)
        self.state = QtWidgets.QLabel()
        grid.addWidget(self.state, 0, 0, 1, 3)
        self.cells: dict[str, QtWidgets.QLabel] = {}
        for row, (key, name, model) in enumerate(ROWS, start=1):
            head = QtWidgets.QLabel(name)
            if key is None:
                head.setStyleSheet("font-weight: bold")
                grid.addWidget(head, row, 0, 1, 3)
                continue
            value = QtWidgets.QLabel()
            value.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight)
            value.setStyleSheet("font-weight: bold")
            value.setToolTip(MODELS.get(key, ""))
            small = QtWidgets.QLabel(model)
            small.setStyleSheet("color: #555; font-size: small")
            grid.addWidget(head, row, 0)
            grid.addWidget(value, row, 1)
            grid.addWidget(small, row, 2)
            self.cells[key] = value
        grid.setRowStretch(len(ROWS) + 1, 1)

    def show_point(self, p, targets: Targets) -> None:
        limit = ("none" if targets.noise_limit_n is None else
                 f"{fmt(1e3 * targets.noise_limit_n)} mN")
        if not p.stable:
            state, colour = "UNSTABLE: K above K_max", "#b00020"
        elif not p.within_limit:
            state, colour = f"stable, but over the noise limit ({limit})", "#b00020"
        else:
            state, colour = f"stable; noise limit {limit}", "#1b5e20"
        if p.noise_white is False:
            state += "; the hand is too slow for white quantisation noise"
        if p.stable and p.noise_command is None:
            state += "; friction holds the handle: no noise predicted"
        elif p.stick_share is not None and p.stick_share > STICK_SHARE_MAX:
            state += (f"; friction sticks the handle at {100 * p.stick_share:.2g} % of "
                      "reversals: its noise is a rough guess")
        self.state.setText(state)
        self.state.setStyleSheet(f"color: {colour}; font-weight: bold")
        for key, text in (
                ("k_max", f"{fmt(p.k_max)} N/m"), ("margin", fmt(p.margin, 3)),
                ("k_passive", f"{fmt(p.k_passive)} N/m"),
                ("k_quantised", f"{fmt(p.k_quantised)} N/m"),
                ("k_friction", f"{fmt(p.k_friction)} N/m"),
                ("ws_star", self._frequency(p.ws_star)), ("wb_star", self._frequency(p.wb_star)),
                ("rendered_B", f"{fmt(p.rendered_B)} N s/m"),
                ("ed_error_sampled", _pct(p.ed_error_sampled)),
                ("ed_error_paper", _pct(p.ed_error_paper)),
                ("noise_command", _mn(p.noise_command)), ("noise_felt", _mn(p.noise_felt)),
                ("noise_friction", _mn(p.noise_friction))):
            self.cells[key].setText(text)

    def _frequency(self, w) -> str:
        return "-" if w is None else f"{fmt(self.units.frequency_of(w))} {self.units.frequency}"

    def text(self) -> str:
        """Everything shown, as one text (tests read it)."""
        return "\n".join([self.state.text(), *(c.text() for c in self.cells.values())])


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _mn(v) -> str:
    return "-" if v is None else f"{fmt(1e3 * v, 3)} mN"
