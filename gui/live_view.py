"""The Live page: the stream shown (a run's or a replay's), its time traces, its effective
impedances with the theory overlay, and the verdicts of its result.

The page owns the stream it shows (``StreamBuffer``) and its live estimate
(``LiveEstimator``): the window feeds it records and calls ``redraw`` from its redraw timer
and ``estimate`` from its estimate timer. While data stream in, the estimate is the
incremental ``live-welch`` (constant cost, ``labbench.analysis.etfe_live``); once the
stream has ended, the run's own estimator on all of it, as its analysis computes it.
"""
from __future__ import annotations

from PySide6 import QtCore, QtWidgets

from labbench.analysis.compare import ve_from_meta
from labbench.gui.buffers import StreamBuffer
from labbench.readout.wording import plant_source
from labbench.gui.live_estimate import LIVE, MIN_SAMPLES, LiveEstimator
from labbench.gui.live_plots import ImpedancePlots, TimeTraces
from labbench.gui.verdict_view import VerdictLabel
from labbench.model.predictions import recorded_plant
from labbench.records import protocol_name

# the theory overlay's plant: the session's (as its analysis and report), or identified live
PLANT_CHOICES = ("the run's plant (as the report)", "identified (l2) on this run")
RUN_PLANT, IDENTIFIED = range(2)
# protocols whose VE changes as they run (a stability probe steps K or the delay): their
# record has no one effective impedance, and one ETFE of it (its marks "measured" against
# the first step's theory) said numbers of no VE
VE_CHANGES = {"stability": "a stability probe steps its VE as it runs:<br>no effective "
                           "impedance of one VE to estimate<br>(its boundary shows above once it ends)"}
VERDICT_SHARE = 1  # parts of the page's height against the plots' PLOTS_SHARE: the verdicts' room
PLOTS_SHARE = 3


class LiveView(QtWidgets.QWidget):
    """``estimate_shown`` carries each estimate drawn (the Identification page names its
    plant); ``warning`` a failed estimate's message, once per distinct failure."""

    estimate_shown = QtCore.Signal(object)
    warning = QtCore.Signal(str)

    def __init__(self, rig, parent=None):
        super().__init__(parent)
        self.rig = rig  # its nominal plant is the theory's when a run names none
        self.buffer = StreamBuffer()
        self.estimator = LiveEstimator()
        self._drawn_version = self._estimated_version = -1
        self._error_shown: str | None = None
        self.theory_plant = QtWidgets.QComboBox()
        self.theory_plant.addItems(PLANT_CHOICES)
        self.theory_plant.setToolTip("plant m, b used for the theory overlay: the run's own (what "
                                     "its analysis and report use), or l2 identified on its data")
        # the verdicts of the result shown, in room of their own that depends on the page's
        # size only (the plots never move when a result shows): a quarter of it, at least 5
        # lines; a 5-line box hid a note inside the verdict's band at 1280 x 800
        self.verdicts = VerdictLabel(placeholder="the verdicts of a run, a replay or a "
                                     "re-analysis show here once it ends")
        self.verdict_room = room = QtWidgets.QScrollArea()
        room.setWidgetResizable(True)
        room.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        room.setWidget(self.verdicts)
        room.setMinimumHeight(5 * self.verdicts.fontMetrics().lineSpacing() + 8)
        room.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred, QtWidgets.QSizePolicy.Policy.Ignored)
        self.traces = TimeTraces()
        self.impedance = ImpedancePlots()
        self.splitter = QtWidgets.QSplitter()
        self.splitter.addWidget(self.traces)
        self.splitter.addWidget(self.impedance)
        self.splitter.setSizes([500, 700])

        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(QtWidgets.QLabel("theory overlay plant:"))
        row.addWidget(self.theory_plant)
        row.addStretch(1)
        lay.addLayout(row)
        lay.addWidget(room, VERDICT_SHARE)
        lay.addWidget(self.splitter, PLOTS_SHARE)
        self.theory_plant.currentIndexChanged.connect(lambda *_: self.invalidate_estimate())

    # ----- the stream -------------------------------------------------------------------------
    def reset(self) -> None:
        """A new stream (a run or replay starts, or another record is shown): nothing of
        the old one stays on the page."""
        self.buffer = StreamBuffer()
        self.estimator.reset()
        self.traces.clear_data()
        self.impedance.clear_data()
        self.verdicts.show_judged([])
        self._drawn_version = self._estimated_version = -1
        self._error_shown = None

    def feed(self, record: dict) -> None:
        self.buffer(record)

    def show_record(self, start: dict, descriptor: dict, channels: dict, stop: dict | None) -> None:
        """A recorded session whole (a re-analysis shows its traces, its estimate comes
        with it: the page does not estimate it again by itself)."""
        import numpy as np
        from labbench.records import CHANNELS

        self.reset()
        n = len(channels.get("t", ()))
        self.buffer.on_start(start)
        self.buffer.on_descriptor(descriptor)
        self.buffer.on_page({"data": {c: channels.get(c, np.zeros(n)) for c in CHANNELS}})
        if stop is not None:
            self.buffer.on_stop(stop)
        self._estimated_version = self.buffer.version

    def redraw(self) -> None:
        """New samples into the traces, a finished estimate into the plots (redraw timer)."""
        if self.buffer.version != self._drawn_version:
            self.traces.update_from(self.buffer)
            self._drawn_version = self.buffer.version
        est = self.estimator.poll()
        if est is not None:
            self.show_estimate(est)
        err = self.estimator.last_error
        if err and err != self._error_shown:
            self._error_shown = err
            self.warning.emit(err)

    def show_estimate(self, est) -> None:
        self.impedance.show_estimate(est)
        self.estimate_shown.emit(est)

    def invalidate_estimate(self) -> None:
        """Estimate again now (the stream ended, or the overlay's plant was changed)."""
        self._estimated_version = -1
        self.estimate()

    def estimate(self) -> None:
        """Hand the newest samples to the estimator unless it is busy (estimate timer)."""
        buf = self.buffer
        if buf.n < MIN_SAMPLES or buf.start is None or buf.version == self._estimated_version:
            return
        why_not = VE_CHANGES.get(protocol_name(buf.start))
        if why_not:
            if self.impedance.title.text != why_not:
                self.impedance.clear_data(why_not)
            self._estimated_version = buf.version
            return
        ve, plant, meta, source = self._estimate_inputs(buf)
        data = buf.snapshot(("t", "excitation", "position", "command"))
        if self.estimator.submit(data, meta, ve, plant, plant_source=source, **self._etfe_options(buf),
                                 recorded=self._recorded_bandwidths(buf)):
            self._estimated_version = buf.version

    @staticmethod
    def _etfe_options(buf) -> dict:
        """While data stream in: the fast LIVE estimator; once the stream has ended: the
        run's own estimator (its default when none is set), as the analysis uses."""
        proto = buf.start.get("protocol") if isinstance(buf.start.get("protocol"), dict) else {}
        opts = {}
        if isinstance(proto.get("window"), int):
            opts["window"] = proto["window"]
        if buf.stop is None:
            opts["estimator"] = LIVE
        elif proto.get("estimator"):
            opts["estimator"] = proto["estimator"]
        return opts

    def _recorded_bandwidths(self, buf) -> dict | None:
        """The ended stream's w_s*, w_b* as its analysis recorded them (the report's and the
        CLI's numbers: the marks say the same), while the overlay is the run's plant."""
        results = (buf.stop or {}).get("results")
        if not (self.uses_run_plant() and isinstance(results, dict)):
            return None
        return results.get("bandwidths") if isinstance(results.get("bandwidths"), dict) else None

    def uses_run_plant(self) -> bool:
        return self.theory_plant.currentIndex() == RUN_PLANT

    def _estimate_inputs(self, buf):
        """(VE, plant or None to identify it, analysis metadata, where the plant came from)."""
        from labbench.sessions.session_content import analysis_meta

        meta = analysis_meta(buf.start, buf.descriptor or {})
        ve = ve_from_meta(meta)
        plant, source = None, "identified (l2)"
        if self.uses_run_plant():
            plant = recorded_plant(buf.start, (buf.stop or {}).get("results"))
            source = plant_source(buf.start) if plant else "the window's rig nominal model"
            plant = plant or self.rig.nominal_plant
        return ve, plant, meta, source

    def set_units(self, units) -> None:
        self.traces.set_units(units)
        self.impedance.set_units(units)
        self.verdicts.set_units(units)

    def shutdown(self) -> None:
        self.estimator.shutdown()
