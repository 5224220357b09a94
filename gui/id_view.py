"""Identification view: measured vs model force, the l2 / l1 table with intervals, the model chosen."""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtWidgets

from labbench.gui.live_plots import COLOURS
from labbench.numfmt import fmt




def model_force(t, force, position, fit: dict, hold: str = "zoh"):
    """(t, measured, model) force on the samples an identification used.

    The model force is f = m x'' + b x' [+ Fc sign(x')] [+ f0] (paper sec. 4.1)
    with the derivatives of ``labbench.analysis.derivatives`` at the fit's own
    cut-off. As in ``labbench.analysis.identify``, a zero-order-held force is
    compared as the mean of the two holds around each sample (the central
    second difference spans both). The force is not low-passed here, so for a
    broadband force the difference shown can exceed the fit's own residual.
    """
    from labbench.analysis.derivatives import differentiate

    t = np.asarray(t, float)
    f = np.asarray(force, float)
    if hold == "zoh":
        f = np.concatenate([f[:1], 0.5 * (f[1:] + f[:-1])])
    fs = (len(t) - 1) / (t[-1] - t[0])
    d = differentiate(np.asarray(position, float), fs, float(fit["cutoff_hz"]))
    model = (fit["m"] or 0.0) * d.a + (fit["b"] or 0.0) * d.v
    if fit.get("coulomb") is not None:
        model = model + fit["coulomb"] * np.sign(d.v)
    if fit.get("offset") is not None:
        model = model + fit["offset"]
    return t[d.keep], f[d.keep], model


# table rows: result key -> (label, unit)
ROWS = (("m", "mass m", "kg"), ("m_ci", "m, 95 % interval", "kg"),
        ("b", "damping b", "N s/m"), ("b_ci", "b, 95 % interval", "N s/m"),
        ("coulomb", "Coulomb friction Fc", "N"), ("coulomb_ci", "Fc, 95 % interval", "N"),
        ("offset", "force offset f0", "N"), ("offset_ci", "f0, 95 % interval", "N"),
        ("rms_residual", "rms force residual", "N"), ("explained", "force variance explained", "%"),
        ("n_used", "samples used", ""), ("cutoff_hz", "derivative cut-off", "Hz"),
        ("model", "model", ""), ("warnings", "warnings", ""))
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
    from labbench.ve import Plant, VirtualEnvironment

    t = np.asarray(t, float)
    fs = (len(t) - 1) / (t[-1] - t[0])
    est = etfe(recording_from_arrays(t, force, position, {"fs": fs}))
    keep = ~np.asarray(est.low_coherence) & (est.w <= W_MAX_NYQUIST * np.pi * fs)
    w = np.asarray(est.w)[keep]
    off = VirtualEnvironment("none", T=1.0 / fs)
    models = {method: theory_curves(Plant(float(f["m"]), float(f["b"])), off, w)["Z"]
              for method, f in fits.items() if f.get("m") and f.get("b") is not None}
    return w, np.asarray(est.Z)[keep], models


class IdView(QtWidgets.QWidget):
    """What an identification is judged by: the open-loop impedance of the record against
    the identified model, the force residual of the fit, and the fits with units."""

    def __init__(self, parent=None):
        super().__init__(parent)
        plots = pg.GraphicsLayoutWidget()
        self.impedance = plots.addPlot(row=0, col=0)
        self.impedance.setLogMode(x=True, y=True)
        self.impedance.setLabel("left", "|Z| = |F / (jω X)|", units="N s/m")
        self.impedance.setLabel("bottom", "frequency", units="rad/s")
        self.impedance.showGrid(x=True, y=True, alpha=0.3)
        self.impedance.addLegend(offset=(10, 5), brush=pg.mkBrush(255, 255, 255, 200))
        self.z_measured = self.impedance.plot(pen=None, symbol="o", symbolSize=5,
                                              symbolBrush=COLOURS["measured"], symbolPen=None,
                                              name="measured (ETFE, coherent points)")
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
        self.chosen = QtWidgets.QLabel("no identification yet: run chirp-ID, or open a session and press Re-analyse")
        self.chosen.setWordWrap(True)
        self.table = QtWidgets.QTableWidget(0, 0)
        self.flags = QtWidgets.QLabel("")
        self.flags.setWordWrap(True)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.splitter = QtWidgets.QSplitter()
        self.splitter.addWidget(plots)
        side = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(side)
        lay.addWidget(self.chosen)
        lay.addWidget(self.table, 1)
        lay.addWidget(self.flags)
        self.splitter.addWidget(side)
        self.splitter.setSizes([700, 420])
        QtWidgets.QVBoxLayout(self).addWidget(self.splitter)
        self.results: dict = {}

    def show_results(self, results: dict[str, dict], data: dict | None = None) -> None:
        """``results``: method name -> ``IdResult.as_dict()``, one table column each;
        ``data``: the record they were fitted on (t, command force, position)."""
        self.results = results
        cells = {}
        for method, res in results.items():
            for k in ("m", "b", "coulomb", "offset"):
                if res.get(k) is not None:
                    cells.setdefault(k, {})[method] = fmt(res[k], 5)
                    ci = (res.get("ci95") or {}).get(k)
                    if ci:
                        cells.setdefault(f"{k}_ci", {})[method] = f"{fmt(ci[0], 5)} to {fmt(ci[1], 5)}"
            for k in ("rms_residual", "n_used", "cutoff_hz", "model"):
                if k in res:
                    cells.setdefault(k, {})[method] = fmt(res[k], 4)
            if "explained" in res:
                cells.setdefault("explained", {})[method] = f"{100 * res['explained']:.4f}"
            cells.setdefault("warnings", {})[method] = str(len(res.get("flags") or []))
        rows = [(key, f"{label} ({unit})" if unit else label) for key, label, unit in ROWS
                if key in cells]
        self.table.setRowCount(len(rows))
        self.table.setColumnCount(len(results))
        self.table.setHorizontalHeaderLabels([f"{m} fit" for m in results])
        self.table.setVerticalHeaderLabels([label for _, label in rows])
        for c, method in enumerate(results):
            for r, (key, _) in enumerate(rows):
                self.table.setItem(r, c, QtWidgets.QTableWidgetItem(cells[key].get(method, "")))
        self.table.resizeColumnsToContents()
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
        self.chosen.setText(f"model chosen: {first.get('model')} ({terms})"
                            + (f"; selection: {why}" if why else ""))
        if data is not None:
            self._show_data(results, data)

    def _show_data(self, results: dict, data: dict) -> None:
        fit = results.get("l2") or next(iter(results.values()))
        t, measured, model = model_force(data["t"], data["command"], data["position"], fit)
        self.residual.setData(t, measured - model)
        w, Z, models = open_loop_impedance(data["t"], data["command"], data["position"], results)
        self.z_measured.setData(w, np.abs(Z))
        primary = "l2" if "l2" in models else next(iter(models), None)
        self.z_model.setData(w, np.abs(models[primary]) if primary else [])
