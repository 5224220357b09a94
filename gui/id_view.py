"""Identification view: measured vs model force, the l2 / l1 table with intervals, the model chosen."""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from labbench.gui.keep_alive import keep_plots
from labbench.gui.live_plots import COLOURS, DecadeAxis, no_si_prefix
from labbench.gui.verdict_view import VerdictLabel, judged
from labbench.readout.numfmt import fmt


def model_force(t, force, position, fit: dict, hold: str = "zoh"):
    """(t, measured, model) force on the samples an identification used.

    The model force is f = m x'' + b x' [+ Fc L sign(x')] [+ f0] (paper sec. 4.1)
    with the derivatives of ``labbench.analysis.derivatives`` at the fit's own
    cut-off. As ``labbench.analysis.identify`` does: a force with power the
    derivatives do not see (a broadband one) is low-passed the same way, the
    sign term too (L), and a zero-order-held force is compared as the mean of
    the two holds around each sample (the central second difference spans both);
    so the difference shown is the fit's own residual.
    """
    from labbench.analysis.derivatives import CUTOFF_FACTOR, differentiate, force_band, lowpass

    t = np.asarray(t, float)
    f = np.asarray(force, float)
    fs = (len(t) - 1) / (t[-1] - t[0])
    cutoff = float(fit["cutoff_hz"])
    if force_band(f, fs) > cutoff / CUTOFF_FACTOR:
        f = lowpass(f, fs, cutoff)
    if hold == "zoh":
        f = np.concatenate([f[:1], 0.5 * (f[1:] + f[:-1])])
    d = differentiate(np.asarray(position, float), fs, cutoff)
    model = (fit["m"] or 0.0) * d.a + (fit["b"] or 0.0) * d.v
    if fit.get("coulomb") is not None:
        model = model + fit["coulomb"] * lowpass(np.sign(d.v_all), fs, cutoff)[d.keep]
    if fit.get("offset") is not None:
        model = model + fit["offset"]
    return t[d.keep], f[d.keep], model


# table rows: result key -> (label, unit)
# (m, b, Fc and f0 as labbench.readout.wording writes them: value, unit, 95 % interval)
ROWS = (("m", "mass m", ""), ("b", "damping b", ""),
        ("coulomb", "Coulomb friction Fc", ""), ("offset", "force offset f0", ""),
        ("rms_residual", "rms force residual", "N"), ("explained", "force variance explained", "%"),
        ("n_used", "samples used", ""), ("cutoff_hz", "derivative cut-off", "Hz"),
        ("model", "model", ""), ("warnings", "warnings", ""), ("verdict", "verdict", ""))
READOUT_ROWS = {"mass m": "m", "damping b": "b", "Coulomb friction Fc": "coulomb",
                "force offset f0": "offset"}
# the open-loop impedance is shown up to this fraction of Nyquist (where the ZOH plant
# model and the ETFE both hold and the chirp still excites)
W_MAX_NYQUIST = 0.3


def open_loop_impedance(t, force, position, fits: dict):
    """(w, measured Z, {method: model Z}) of a record with the VE off: the ETFE of the
    applied force over position at its coherent frequencies (coherence >= 0.8), and
    Z = b + j w m of each fit through the exact sampled model (``compare.theory_curves``)."""
    from labbench.analysis.compare import theory_curves
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe
    from labbench.model.ve import Plant, VirtualEnvironment

    t = np.asarray(t, float)
    fs = (len(t) - 1) / (t[-1] - t[0])
    est = etfe(recording_from_arrays(t, force, position, {"fs": fs}))
    keep = ~np.asarray(est.low_coherence) & (est.w <= W_MAX_NYQUIST * np.pi * fs)
    w = np.asarray(est.w)[keep]
    off = VirtualEnvironment("none", T=1.0 / fs)
    models = {method: theory_curves(Plant(float(f["m"]), float(f["b"])), off, w)["Z"]
              for method, f in fits.items() if f.get("m") and f.get("b") is not None}
    return w, np.asarray(est.Z)[keep], models


# the closed-loop fit's rows: key -> (label, unit, scale from SI, the readout's part)
FIT_ROWS = (("m", "mass m", "kg", 1.0, "m"), ("b", "damping b", "N s/m", 1.0, "b"),
            ("td_s", "device latency td", "ms", 1e3, "td"), ("tv_s", "VE-path delay tv", "ms", 1e3, "tv"),
            ("K", "rendered K", "N/m", 1.0, None), ("B", "rendered B", "N s/m", 1.0, None))


def loop_fit_rows(fit: dict, units=None) -> list[tuple[str, str]]:
    """(label, value with its 95 % interval) of a loop fit (``LoopFit.as_dict()``): m, b and
    the delays as ``labbench.readout.wording`` writes them (the CLI's, the report's numbers), then
    the model, the band (in the display unit of frequency) and the fit's quality."""
    from labbench.readout import wording
    from labbench.readout.numfmt import fmt_ci
    from labbench.readout.units import SI

    units = units or SI
    read = wording.of_results("etfe", {"etfe": {}, "loop_fit": fit})
    parts = dict(next((v for label, v in read.rows if label == "closed-loop fit"), ()))
    ci = fit.get("ci95") or {}
    rows = []
    for key, label, unit, scale, part in FIT_ROWS:
        if fit.get(key) is None:
            continue
        if part in parts:
            rows.append((label, parts[part].text(units)))
        elif ci.get(key):
            rows.append((label, fmt_ci(scale * fit[key], scale * ci[key][0], scale * ci[key][1], unit)))
        else:  # given, not fitted (the run's own VE delay)
            rows.append((label, f"{fmt(scale * fit[key])} {unit}, held (not fitted)"))
    sel = fit.get("selection") or {}
    why = sel.get("reason") or sel.get("criterion") or ""
    if why == "given":  # the protocol's own analysis: it rendered the VE, so tv is known
        why = "given (the VE's delay is known)"
    rows.append(("delay model", f"{fit.get('delay_model')}" + (f": {why}" if why else "")))
    if fit.get("loop_delay_s") is not None:
        rows.append(("loop delay tv + td", f"{fmt(1e3 * fit['loop_delay_s'], 5)} ms"))
    band = fit.get("band_rad_s") or []
    if len(band) == 2:
        f = units.frequency_of
        rows.append(("band", f"{fmt(f(band[0]))} to {fmt(f(band[1]))} {units.frequency}, "
                             f"{fit.get('n_freq')} coherent frequencies"))
    rows.append(("chi2/dof", f"{fmt(fit.get('chi2_dof'), 3)} (1 when the model fits to the noise)"))
    if fit.get("residual_rms") is not None:
        rows.append(("residual rms", f"{fmt(100 * fit['residual_rms'], 3)} % of |Z|"))
    return rows


def _table(table: QtWidgets.QTableWidget, header: list[str], rows: list[tuple[str, ...]]) -> None:
    """Fill ``table``: row labels from the first cell of each row, the rest as columns."""
    table.clear()
    table.setRowCount(len(rows))
    table.setColumnCount(len(header))
    table.setHorizontalHeaderLabels(header)
    table.setVerticalHeaderLabels([r[0] for r in rows])
    for i, row in enumerate(rows):
        for j, text in enumerate(row[1:]):
            item = QtWidgets.QTableWidgetItem(text)
            item.setToolTip(text)  # all of it, should the column be narrower than the text
            table.setItem(i, j, item)
    table.setVisible(True)
    _fit_rows(table)


def _fit_rows(table: QtWidgets.QTableWidget) -> None:
    """The columns share the table's width (a value with its interval wraps in its cell: at
    1280 x 800 the l1 column was off to the right), every row at once (the side scrolls)."""
    table.resizeRowsToContents()
    table.setFixedHeight(table.horizontalHeader().sizeHint().height() + 2 * table.frameWidth()
                         + sum(table.rowHeight(r) for r in range(table.rowCount())))


def _sharing_columns(table: QtWidgets.QTableWidget) -> None:
    table.setWordWrap(True)
    table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.Stretch)
    table.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    table.horizontalHeader().sectionResized.connect(lambda *_: _fit_rows(table))


def cells(table: QtWidgets.QTableWidget) -> dict[str, list[str]]:
    """row label -> the texts of its cells (what a person reads; for tests)."""
    out = {}
    for r in range(table.rowCount()):
        head = table.verticalHeaderItem(r)
        out[head.text() if head else str(r)] = [table.item(r, c).text() if table.item(r, c) else ""
                                               for c in range(table.columnCount())]
    return out


class IdView(QtWidgets.QWidget):
    """What an identification is judged by: the open-loop impedance of the record against
    the identified model, the force residual of the fit, and the fits with units and
    verdicts; the plant the theory overlay uses, with where it came from; and the
    closed-loop fit of an ETFE session."""

    def __init__(self, parent=None):
        super().__init__(parent)
        from labbench.readout.units import SI

        plots = pg.GraphicsLayoutWidget()
        self.impedance = plots.addPlot(row=0, col=0, axisItems={"bottom": DecadeAxis("bottom")})
        self.impedance.setLogMode(x=True, y=True)
        self.impedance.setLabel("left", "|Z| = |F / (jω X)|", units="N s/m")
        self.impedance.showGrid(x=True, y=True, alpha=0.3)
        self.impedance.addLegend(offset=(10, 5), brush=pg.mkBrush(255, 255, 255, 200))
        self.z_measured = self.impedance.plot(pen=None, symbol="o", symbolSize=5,
                                              symbolBrush=COLOURS["measured"], symbolPen=None,
                                              name="measured (coherent ETFE)")
        self.z_model = self.impedance.plot(pen=pg.mkPen(COLOURS["theory"], width=2),
                                           name="identified model")
        self.residual_plot = plots.addPlot(row=1, col=0)
        self.residual_plot.setLabel("left", "force residual", units="N")
        self.residual_plot.setLabel("bottom", "time", units="s")
        self.residual_plot.showGrid(x=True, y=True, alpha=0.3)
        self.residual_plot.setClipToView(True)
        self.residual_plot.setDownsampling(auto=True, mode="peak")
        self.residual = self.residual_plot.plot(pen=pg.mkPen(COLOURS["measured"], width=1))
        plots.ci.layout.setRowStretchFactor(0, 3)
        plots.ci.layout.setRowStretchFactor(1, 2)
        keep_plots(plots)

        def label(text=""):
            lab = QtWidgets.QLabel(text)
            lab.setWordWrap(True)
            lab.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
            return lab

        self.overlay = label("theory overlay plant: -")
        self.overlay.setStyleSheet("QLabel { background: #eef3fa; padding: 4px; }")
        self.source = label("no identification yet: run chirp-ID, or open a session and press Re-analyse")
        self.chosen = label()
        self.table = QtWidgets.QTableWidget(0, 0)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.verdicts = VerdictLabel()
        self.flags = label()
        self.fit_source = label("closed-loop fit: none yet (an ETFE run, a replayed ETFE session, "
                                "or Re-analyse of one)")
        self.fit_table = QtWidgets.QTableWidget(0, 0)
        self.fit_table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.fit_verdict = VerdictLabel()
        for table in (self.table, self.fit_table):
            table.verticalHeader().setDefaultSectionSize(22)
            table.setVerticalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
            _sharing_columns(table)
            table.setVisible(False)  # until there is something to show
        self.splitter = QtWidgets.QSplitter()
        self.splitter.addWidget(plots)
        side = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(side)
        lay.addWidget(self.overlay)
        heading = label("<b>Identification (open loop, paper sec. 4.1)</b>")
        lay.addWidget(heading)
        for w in (self.source, self.chosen):
            lay.addWidget(w)
        lay.addWidget(self.table)
        lay.addWidget(self.verdicts)
        lay.addWidget(self.flags)
        lay.addWidget(label("<b>Closed-loop fit of an ETFE session (exact sampled model)</b>"))
        lay.addWidget(self.fit_source)
        lay.addWidget(self.fit_table)
        lay.addWidget(self.fit_verdict)
        lay.addStretch(1)
        scroll = QtWidgets.QScrollArea()  # the tables at their full height; the side scrolls
        scroll.setWidgetResizable(True)
        scroll.setWidget(side)
        self.splitter.addWidget(scroll)
        self.splitter.setSizes([480, 720])  # the fits side by side, each value with its interval
        QtWidgets.QVBoxLayout(self).addWidget(self.splitter)
        self.results: dict = {}
        self.loop_fit: dict = {}
        self._data: dict | None = None
        self.set_units(SI)

    def set_units(self, units) -> None:
        """Display unit of frequency on the impedance plot and in the fit's band."""
        self.units = units
        freq = "f" if units.frequency == "Hz" else "ω"
        self.impedance.setLabel("bottom", f"frequency {freq}", units=units.frequency)
        no_si_prefix(self.impedance.getAxis("bottom"))
        for label in (self.verdicts, self.fit_verdict):
            label.set_units(units)
        if self.results and self._data is not None:
            self._show_data(self.results, self._data)
        if self.loop_fit:
            self.show_loop_fit(self.loop_fit, self.fit_source.text())

    def show_overlay(self, text: str) -> None:
        """The plant the theory overlay uses and where it came from (rich text)."""
        self.overlay.setText(f"theory overlay plant {text}")

    def show_results(self, results: dict[str, dict], data: dict | None = None, source: str = "",
                     used: str | None = None) -> None:
        """``results``: method name -> ``IdResult.as_dict()``, one table column each;
        ``data``: the record they were fitted on (t, command force, position); ``source``:
        where they come from (a session, this run); ``used``: the method whose m, b the
        theory overlay takes, if any."""
        from labbench.readout import wording

        self.results = results
        cells_ = {}
        for method, res in results.items():
            read = wording.of_identification(res, method)
            for label, value in read.rows:
                if label in READOUT_ROWS and hasattr(value, "text"):
                    cells_.setdefault(READOUT_ROWS[label], {})[method] = value.text(self.units)
            for k in ("rms_residual", "n_used", "cutoff_hz", "model"):
                if k in res:
                    cells_.setdefault(k, {})[method] = fmt(res[k], 4)
            if "explained" in res:
                cells_.setdefault("explained", {})[method] = f"{100 * res['explained']:.4f}"
            cells_.setdefault("warnings", {})[method] = str(len(res.get("flags") or []))
            if isinstance(res.get("verdict"), dict):
                cells_.setdefault("verdict", {})[method] = str(res["verdict"].get("level"))
        rows = [(f"{label} ({unit})" if unit else label,
                 *(cells_[key].get(m, "") for m in results))
                for key, label, unit in ROWS if key in cells_]
        _table(self.table, [f"{m} fit" + (" (next runs)" if m == used else "") for m in results], rows)
        self.verdicts.show_judged([j for m, res in results.items()
                                   for j in judged(f"{m} fit", res.get("verdict"))])
        self.flags.setText("<br>".join(f"<b>{m}</b>: {f}" for m, res in results.items()
                                       for f in res.get("flags") or []))
        first = next(iter(results.values()))
        sel = first.get("selection") or {}
        why = sel.get("reason") or sel.get("criterion", "")
        terms = "f = m x'' + b x'"
        if first.get("coulomb") is not None:
            terms += " + Fc sign(x')"
        if first.get("offset") is not None:
            terms += " + f0"
        self.source.setText(source or "identification of this run")
        self.chosen.setText(f"model chosen: {first.get('model')} ({terms})"
                            + (f"; selection: {why}" if why else ""))
        self._data = data
        if data is not None:
            self._show_data(results, data)

    def show_loop_fit(self, fit: dict, source: str) -> None:
        """The closed-loop fit of an ETFE record (``LoopFit.as_dict()``, or {"error": why})."""
        self.loop_fit = fit
        self.fit_source.setText(source)
        if "error" in fit:
            _table(self.fit_table, ["value (95 % interval)"], [("no fit", str(fit["error"]))])
            self.fit_verdict.show_judged([])
            return
        _table(self.fit_table, ["value (95 % interval)"], loop_fit_rows(fit, self.units))
        self.fit_verdict.show_judged(judged("closed-loop fit", fit.get("verdict")))

    def _show_data(self, results: dict, data: dict) -> None:
        fit = results.get("l2") or next(iter(results.values()))
        t, measured, model = model_force(data["t"], data["command"], data["position"], fit)
        self.residual.setData(t, measured - model)
        w, Z, models = open_loop_impedance(data["t"], data["command"], data["position"], results)
        fx = self.units.frequency_of(1.0)
        self.z_measured.setData(w * fx, np.abs(Z))
        primary = "l2" if "l2" in models else next(iter(models), None)
        self.z_model.setData(w * fx, np.abs(models[primary]) if primary else [])
