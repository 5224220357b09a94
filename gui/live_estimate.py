"""Live effective impedances: estimate Z from the data so far, off the GUI thread.

While a run streams in, the estimate is the incremental Welch H1 of
``labbench.analysis.etfe_live`` (``LIVE``): each update adds only the samples
new since the last one, so it costs the same at any record length. Once the
stream has ended it is the run's own ETFE of ``labbench.analysis.etfe`` (paper
sec. 4.2) on the whole record, as the analysis computes it. Either is decomposed
by ``labbench.model.effective`` (paper Figure 2), with the theory of
``labbench.model.linear`` for the configured VE and the plant (given, or identified
by l2 on the newest data, paper sec. 4.1).
No Qt here: ``LiveEstimator`` runs ``estimate`` on one worker thread and the
window polls for the newest finished result.
"""
from __future__ import annotations

import concurrent.futures as cf
import functools
import logging
from dataclasses import dataclass, field

import numpy as np

from labbench.analysis.etfe_live import NAME as LIVE, LiveEtfe
from labbench.model import predictions
from labbench.model.effective import effective_impedances
from labbench.model.predictions import Bandwidths
from labbench.model.ve import Plant, VirtualEnvironment

log = logging.getLogger(__name__)

MIN_SAMPLES = 2048  # the live estimate's shortest segment; fewer bins are not worth showing
LIVE_BUDGET = 2**15  # samples transformed per live update: one 33 s segment transform at most
# Live identification uses the newest ID_SAMPLES only and is redone when the data have
# doubled: l2 with intervals costs ~0.5 s on 120 000 samples, the plant does not change.
ID_SAMPLES = 20_000
# A frequency band whose excitation power is under this fraction of the strongest
# frequency's has not been excited (a chirp that has not reached it yet, a band-limited
# noise above its band): what the estimate shows there is the leakage of lower
# frequencies through the window, not the device; it is masked. The Hann window's
# leakage is under it from about two bins off an excited one.
EXCITED_FRACTION = 1e-3


@dataclass
class Estimate:
    """One live estimate, ready to draw. Bands are +-1 Z_err mapped through each formula."""

    n_samples: int
    w: np.ndarray
    Z: np.ndarray
    Z_err: np.ndarray
    ES: np.ndarray
    ED: np.ndarray
    EM: np.ndarray
    ws_measured: float | None
    wb_measured: float | None
    plant: Plant | None
    plant_source: str  # "given", "identified (l2)" or "none"
    theory: dict = field(default_factory=dict)  # w, Z, ES, ED, EM; empty when unavailable
    predicted: Bandwidths | None = None  # labbench.model.predictions: the one theory of the numbers shown
    w_nyquist: float = np.inf  # pi / T [rad/s]
    identified_now: bool = False  # this estimate ran the identification
    estimator: str = ""  # the ETFE estimator used
    excited: np.ndarray | None = None  # bool per w: the excitation reached it (None: all)
    renders_ve: bool = False  # the run rendered a VE (w_s*, w_b* are its bandwidths)

    def band(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of ES, ED or EM from the 95 % radius Z_err (Re and Im each move by at most it)."""
        scale = {"ES": self.w, "ED": np.ones_like(self.w), "EM": 1.0 / self.w}[name]
        mid = getattr(self, name)
        half = np.abs(self.Z_err) * scale
        with np.errstate(invalid="ignore"):  # an infinite estimate has no band: NaN, a gap drawn
            return mid - half, mid + half


def estimate(data: dict[str, np.ndarray], meta: dict, ve: VirtualEnvironment | None,
             plant: Plant | None, window: int = 200, estimator: str | None = None,
             plant_source: str = "given", live: LiveEtfe | None = None, progress=None,
             cancel=None, recorded: dict | None = None) -> Estimate | None:
    """ETFE of force (excitation) to position so far; None while too short to estimate.

    ``estimator`` LIVE: the samples of ``data`` beyond ``live.n`` are added to the
    incremental ``live`` and its estimate is used; else the batch ETFE of the whole
    record. Without ``plant``, m and b are identified by l2 on the newest ID_SAMPLES.
    ``progress``, ``cancel``: the batch ETFE's (``labbench.analysis.progress``).
    ``recorded``: the analysis' ``bandwidths`` of this record (its results, the report's
    numbers): the w_s*, w_b* shown, measured and predicted; else read here as the analysis
    reads them (``labbench.model.predictions.read``).
    """
    from labbench.model.device_delay import from_meta
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe

    n = len(data["t"])
    if n < MIN_SAMPLES:
        return None
    if estimator == LIVE:
        live = live if live is not None else LiveEtfe(float(meta["fs"]))
        live.add(data["excitation"][live.n:], data["position"][live.n:], budget=LIVE_BUDGET)
        res = live.estimate()
        if res is None:
            return None
        fs = live.fs
        # each frequency's own bin (its band is wide at the bottom of a short segment and
        # averages in the excited bins below it), against the strongest bin of all
        level = live.level()
        k = np.clip(np.rint(np.asarray(res.w) * level.n / (2 * np.pi * fs)).astype(int), 0,
                    level.sff.size - 1)
        power, peak = level.sff[k], float(np.max(level.sff[1:]))
    else:
        rec = recording_from_arrays(data["t"], data["excitation"], data["position"], meta)
        res = etfe(rec, estimator=estimator, window=window, progress=progress, cancel=cancel)
        fs = rec.fs
        power, peak = res.force_power, None
    w = np.asarray(res.w, float)
    Z = np.asarray(res.Z, complex)
    Z_err = np.asarray(res.Z_err, float) if res.Z_err is not None else np.zeros_like(w)
    eff = effective_impedances(w, Z)

    source = plant_source if plant is not None else "none"
    identified_now = False
    if plant is None:
        # The plant is driven by the net commanded force, not by the excitation alone.
        last = slice(max(0, n - ID_SAMPLES), n)
        plant = _identify_l2(recording_from_arrays(data["t"][last], data["command"][last],
                                                   data["position"][last], meta))
        source = "identified (l2)" if plant is not None else "none"
        identified_now = plant is not None

    out = Estimate(
        n_samples=n, w=w, Z=Z, Z_err=Z_err, ES=eff.ES, ED=eff.ED, EM=eff.EM,
        ws_measured=None, wb_measured=None,
        plant=plant, plant_source=source, w_nyquist=np.pi * fs,
        identified_now=identified_now, estimator=res.estimator,
        excited=excited_bands(power, peak),
        renders_ve=ve is not None and ve.kind != "none",
    )
    if plant is not None:
        latency = from_meta(meta)
        # a run without a VE (chirp-ID) is the plant's own Z: its theory is the plant's
        out.theory = _theory(plant, ve if ve is not None else VirtualEnvironment("none", T=1.0 / fs),
                             w, latency)
        if out.renders_ve:  # the numbers of the run's results, read as its analysis reads them
            if recorded is None:
                from labbench.analysis.rendered import measured, reading_band

                low = measured(res, reading_band(res, ve, plant, latency))
                recorded = predictions.read(w, Z, plant, ve, latency, low and low.as_dict())
            out.ws_measured, out.wb_measured, out.predicted = predictions.of_results(
                recorded, ve, latency)
    return out


def excited_bands(force_power, peak: float | None = None) -> np.ndarray | None:
    """Which frequencies the excitation reached: force power at least EXCITED_FRACTION of
    ``peak`` (default the strongest frequency's). None when the estimator does not say its
    force power (every frequency is taken as excited)."""
    if force_power is None:
        return None
    p = np.nan_to_num(np.asarray(force_power, float), nan=0.0)
    top = peak if peak is not None else (p.max() if p.size else 0.0)
    return p >= EXCITED_FRACTION * top if top > 0 else np.zeros(p.shape, bool)


def _identify_l2(rec) -> Plant | None:
    """m, b by least squares on the same data; None when identification refuses it."""
    from labbench.analysis.identify import identify

    try:
        res = identify(rec, model="mb", method="l2").as_dict()
        return Plant(float(res["m"]), max(float(res["b"]), 0.0))
    except Exception as exc:  # noqa: BLE001 - the overlay is optional, the estimate is not
        log.info("live identification unavailable: %s", exc)
        return None


def _theory(plant: Plant, ve: VirtualEnvironment, w: np.ndarray, latency: float = 0.0) -> dict:
    return _theory_on(plant, ve, float(max(w[w > 0].min(), 1e-2)), float(w.max()), latency)


@functools.lru_cache(maxsize=8)
def _theory_on(plant: Plant, ve: VirtualEnvironment, w_lo: float, w_hi: float, latency: float) -> dict:
    """Theory on 400 log-spaced points (with the rig's measured extra delay ``latency``);
    cached, so an unchanged theory is the same object (the plots then skip re-drawing it)."""
    from labbench.analysis.compare import theory_curves

    wt = np.geomspace(w_lo, w_hi, 400)
    key = (plant, ve, w_lo, w_hi, latency)  # equal keys: the plots keep the theory already drawn
    Zt = np.asarray(theory_curves(plant, ve, wt, latency)["Z"], complex)
    eff = effective_impedances(wt, Zt)
    return {"w": wt, "Z": Zt, "ES": eff.ES, "ED": eff.ED, "EM": eff.EM, "key": key}


class LiveEstimator:
    """At most one estimate in flight on one worker thread; ``poll`` gives the newest.

    A thread, not a process: a spawned worker process was tried and measured no
    fewer loop overruns on this 2-core machine (the estimate then competes for a
    core instead of the GIL) while it made start-up slower and every script that
    opens a window need a ``__main__`` guard.
    """

    def __init__(self):
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="labbench-etfe")
        self._future: cf.Future | None = None
        self.last_error: str | None = None
        self._identified: tuple[Plant, int] | None = None  # (plant, samples it was fitted on)
        self._live: LiveEtfe | None = None  # the incremental sums of this stream

    def reset(self) -> None:
        """A new stream: forget the identified plant and any estimate of the old one."""
        self._identified = None
        self._future = None
        self._live = None

    @property
    def busy(self) -> bool:
        return self._future is not None and not self._future.done()

    def submit(self, data, meta, ve, plant, window: int = 200, estimator: str | None = None,
               plant_source: str = "given", recorded: dict | None = None) -> bool:
        """Start an estimate unless one is running; True if started. ``plant_source``: where
        a given ``plant`` came from, in words (shown with it); ``recorded``: as ``estimate``'s."""
        if self.busy:
            return False
        source = plant_source
        n = len(data["t"])
        if plant is None and self._identified and n < 2 * self._identified[1]:
            plant, source = self._identified[0], "identified (l2)"
        live = None
        if estimator == LIVE:
            if self._live is None or n < self._live.n or self._live.fs != float(meta["fs"]):
                self._live = LiveEtfe(float(meta["fs"]))  # a new stream
            live = self._live
        self._future = self._pool.submit(estimate, data, meta, ve, plant, window, estimator,
                                         source, live, recorded=recorded)
        return True

    def poll(self) -> Estimate | None:
        """The finished estimate (once), else None; errors land in ``last_error``."""
        f = self._future
        if f is None or not f.done():
            return None
        self._future = None
        try:
            est = f.result()
        except Exception as exc:  # noqa: BLE001 - shown in the window, never raised into Qt
            message = f"live estimate failed: {type(exc).__name__}: {exc}"
            if message != self.last_error:  # one traceback per distinct failure
                log.exception("live estimate failed")
            self.last_error = message
            return None
        if est is not None and est.identified_now:
            self._identified = (est.plant, est.n_samples)
        return est

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
