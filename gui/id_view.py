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


class IdView(QtWidgets.QWidget):
    def __init__(self, parent=None):
        super().__init__(parent)
        self.plot = pg.PlotWidget()
        self.plot.setLabel("left", "force", units="N")
        self.plot.setLabel("bottom", "time", units="s")
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        self.plot.addLegend(offset=(-10, 5), brush=pg.mkBrush(255, 255, 255, 200))
        self.plot.setClipToView(True)
        self.plot.setDownsampling(auto=True, mode="peak")
        # wide light pen under a thin one: both stay visible where the fit is exact
        self.measured = self.plot.plot(pen=pg.mkPen("#9ab8d8", width=4),
                                       name="measured (mean of the two holds)")
        self.model = self.plot.plot(pen=pg.mkPen(COLOURS["theory"], width=1), name="model")
        self.chosen = QtWidgets.QLabel("no identification yet: run chirp-ID, or open a session and press Re-analyse")
        self.chosen.setWordWrap(True)
        self.table = QtWidgets.QTableWidget(0, 0)
        self.flags = QtWidgets.QLabel("")
        self.flags.setWordWrap(True)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        split = QtWidgets.QSplitter()
        split.addWidget(self.plot)
        side = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(side)
        lay.addWidget(self.chosen)
        lay.addWidget(self.table, 1)
        lay.addWidget(self.flags)
        split.addWidget(side)
        split.setSizes([700, 400])
        QtWidgets.QVBoxLayout(self).addWidget(split)
        self.results: dict = {}

    def show_results(self, results: dict[str, dict], t=None, f_measured=None, f_model=None) -> None:
        """``results``: method name -> ``IdResult.as_dict()``; one table column per method.

        Rows: the parameters with their 95 % intervals, fit quality, flags.
        """
        self.results = results
        rows = {}
        for method, res in results.items():
            col = rows.setdefault
            for k in ("m", "b", "coulomb", "offset"):
                if res.get(k) is not None:
                    col(k, {})[method] = res[k]
                    ci = (res.get("ci95") or {}).get(k)
                    if ci:
                        col(f"{k} 95% interval", {})[method] = ci
            for k in ("rms_residual", "explained", "n_used", "cutoff_hz", "model"):
                if k in res:
                    col(k, {})[method] = res[k]
            col("warnings", {})[method] = len(res.get("flags") or [])
        keys = list(rows)
        self.table.setRowCount(len(keys))
        self.table.setColumnCount(len(results))
        self.table.setHorizontalHeaderLabels(list(results))
        self.table.setVerticalHeaderLabels(keys)
        for c, method in enumerate(results):
            for r, k in enumerate(keys):
                self.table.setItem(r, c, QtWidgets.QTableWidgetItem(fmt(rows[k].get(method, ""), 5)))
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
        if t is not None:
            self.measured.setData(t, f_measured)
            self.model.setData(t, f_model if f_model is not None else [])
