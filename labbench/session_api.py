"""``labbench.load(path)``: a recorded session or an analysis CSV as one object.

For notebooks and scripts (docs/notebook.md)::

    import labbench
    s = labbench.load("sessions/20261126-113329_chirp-id_a6811cee.lbsession")
    s.meta["fs"], s.data["position"], s.units["position"]
    fit = s.identify()        # the numbers of `labbench analyze id FILE --json`
    fit.m, fit.b, fit.ci95["m"]
    fr = s.etfe()             # the numbers of `labbench analyze etfe FILE --json`
    fr.w, fr.Z, fr.ES, fr.ED, fr.EM
    s.plot(); fr.plot(); s.to_dataframe()

``identify_recording`` and ``etfe_recording`` are the analyses behind both this
API and ``labbench analyze`` (the command prints their ``as_dict()``), so there
is one set of numbers.
"""
from __future__ import annotations

import csv
import io
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labbench.model import device_delay
from labbench import records
from labbench.analysis.dataio import Recording, load_recording
from labbench.analysis.etfe import W_BAND, EtfeResult
from labbench.analysis.identify import IdResult
from labbench.analysis.progress import Progress, Steps
from labbench.model.effective import effective_impedances
from labbench.errors import UserError, missing_extra

# Units of the analysis CSV's columns (the session's channels carry their own).
CSV_UNITS = {**records.CHANNELS, "force": "N"}


# ----------------------------------------------------------------------------- analyses
@dataclass
class Identification:
    """Identified device f = m x'' + b x' [+ Fc sign(x')] [+ f0] with 95 % intervals (SI)."""

    result: IdResult
    force_source: str  # which force the fit used (open loop: as recorded; closed: minus the VE)

    @property
    def model(self) -> str:
        return self.result.model

    @property
    def m(self) -> float:
        """Mass [kg]."""
        return self.result.m

    @property
    def b(self) -> float:
        """Viscous damping [N s/m]."""
        return self.result.b

    @property
    def coulomb(self) -> float | None:
        """Coulomb friction [N] (None when the model has no such term)."""
        return self.result.params.get("coulomb")

    @property
    def offset(self) -> float | None:
        """Force offset [N] (None when the model has no such term)."""
        return self.result.params.get("offset")

    @property
    def ci95(self) -> dict:
        """Parameter name -> (lo, hi) 95 % interval."""
        return dict(self.result.ci95)

    @property
    def flags(self) -> list[str]:
        return list(self.result.flags)

    @property
    def residual(self) -> np.ndarray | None:
        """Force residual [N] of the fit, per used sample."""
        return self.result.residual

    @property
    def readout(self):
        """What a person reads of it (``labbench.readout.wording``: the words of the CLI, report, window)."""
        from labbench.readout import wording

        return wording.of_identification({**self.result.as_dict(), "force_source": self.force_source})

    def as_dict(self) -> dict:
        """What ``labbench analyze id --json`` prints (before JSON encoding)."""
        return {**self.result.as_dict(), "force_source": self.force_source,
                "readout": self.readout.as_dict()}

    def __repr__(self) -> str:
        return (f"Identification(model={self.model!r}, m={self.m:.6g} kg, b={self.b:.6g} N s/m, "
                f"flags={len(self.result.flags)})")


def identify_recording(rec: Recording, model: str = "auto", method: str = "l2",
                       cutoff_hz: float | None = None, solver: str = "fast",
                       force_hold: str | None = None, progress: Progress | None = None,
                       cancel: threading.Event | None = None) -> Identification:
    """Identify the device from a record: open loop as recorded, closed loop (a VE in the
    metadata) on the force the plant felt (``labbench.analysis.compare.plant_recording``).
    ``force_hold``: "zoh" or "sample" (None: the metadata's, else chosen from the data;
    ``labbench.analysis.identify``). ``progress(fraction, phrase)`` hears how far it is;
    once ``cancel`` is set it raises ``labbench.errors.Cancelled`` within about 0.5 s
    (``labbench.analysis.progress``)."""
    from labbench.analysis import compare
    from labbench.analysis.identify import identify

    plant_rec, ve = compare.plant_recording(rec)
    latency = device_delay.from_meta(rec.meta)
    res = identify(plant_rec, model=model, method=method, cutoff_hz=cutoff_hz, solver=solver,
                   hold=force_hold, response=None if ve is None else compare.loop_response(rec, ve, latency),
                   progress=progress, cancel=cancel)
    source = "force" if ve is None else f"force minus the {ve.kind} VE force of the metadata"
    if latency:
        source += f", as held after the device delay of {1e3 * latency:.4g} ms"
    return Identification(res, source)


@dataclass
class FrequencyResponse:
    """Closed-loop impedance Z = F/(jw X) [N s/m] on ``w`` [rad/s], its effective impedances
    and, when the record names a VE, the theory it is held against."""

    result: EtfeResult
    source: str
    fs: float
    comparison: dict | None  # labbench.analysis.compare.compare(...) + plant_source, or None
    fit: object | None = None  # labbench.analysis.loopfit's fit of m, b, td (etfe(fit=True))
    # the stiffness and damping rendered, beside commanded and theory (analysis.rendered)
    rendered: dict | None = None
    # the device's Coulomb friction and the damper it acts as (analysis.friction.Prediction)
    friction: dict | None = None
    # the fit as reported: friction's part of its b taken out or named (analysis.friction.separate)
    fit_summary: dict | None = None
    # w_s*, w_b* measured and predicted as a run's results keep them (labbench.model.predictions.read);
    # None without a VE
    bandwidths: dict | None = None

    @property
    def w(self) -> np.ndarray:
        return self.result.w

    @property
    def Z(self) -> np.ndarray:
        return self.result.Z

    @property
    def Z_err(self) -> np.ndarray:
        """95 % radius |dZ| [N s/m] per frequency."""
        return self.result.Z_err

    @property
    def coherence(self) -> np.ndarray:
        return self.result.coherence

    @property
    def ES(self) -> np.ndarray:
        """Effective stiffness [N/m]."""
        return effective_impedances(self.w, self.Z).ES

    @property
    def ED(self) -> np.ndarray:
        """Effective damping [N s/m]."""
        return effective_impedances(self.w, self.Z).ED

    @property
    def EM(self) -> np.ndarray:
        """Effective mass [kg]."""
        return effective_impedances(self.w, self.Z).EM

    @property
    def ws_star(self) -> float | None:
        """Measured stiffness bandwidth [rad/s]."""
        return self._dict()["ws_star"]

    @property
    def wb_star(self) -> float | None:
        """Measured damping bandwidth [rad/s] (a VE's: None without one)."""
        return self._dict()["wb_star"]

    @property
    def Z_theory(self) -> np.ndarray | None:
        """Theory Z on ``w`` (the model in ``comparison["model"]``), None without a VE."""
        return None if self.comparison is None else self.comparison["Z_theory"]

    @property
    def flags(self) -> list[str]:
        return list(self.result.flags)

    @property
    def readout(self):
        """What a person reads of it (``labbench.readout.wording``: the words of the CLI, report, window)."""
        from labbench.readout import wording

        return wording.of_etfe_analysis(self._dict())

    def as_dict(self, units=None) -> dict:
        """What ``labbench analyze etfe --json`` prints (before JSON encoding)."""
        from labbench.readout import wording

        d = self._dict()
        return {**d, "readout": wording.of_etfe_analysis(d).as_dict(units)}

    def _dict(self) -> dict:
        d = self.result.as_dict()
        if self.fit is not None:
            d["fit"] = self.fit_summary if self.fit_summary is not None else self.fit.as_dict()
        d["rendered"] = self.rendered
        bw = self.bandwidths or {}
        if self.bandwidths is not None:  # read as the rendered K, B are: labbench.model.predictions
            d["ws_star"], d["bandwidths"] = bw["ws_star_measured"], bw
        d["wb_star"] = bw.get("wb_star_measured")
        cmp = self.comparison
        if cmp is not None:
            d["theory"] = {k: v for k, v in cmp.items()
                           if k not in ("Z_theory", "Z_paper", "deviation")}
            d["theory"]["Z_re"] = cmp["Z_theory"].real
            d["theory"]["Z_im"] = cmp["Z_theory"].imag
            d["deviation"] = cmp["deviation"]
        d["friction"] = self.friction
        return d

    def plot(self, path=None, inputs=(), force: bool = False):
        """Paper-style figure (Bode, ES, ED, EM; ``labbench.readout.figures.paper_figure``) of the
        measurement and its theory, up to 0.3 x Nyquist (beyond, the sampled loop's own
        near-Nyquist growth would set the scale of every panel). Returns the Figure; with
        ``path`` (.png, .svg, .pdf) also writes it (never onto ``inputs``; an existing
        file only with ``force``)."""
        from labbench.readout.figures import Curve, paper_figure

        res, cmp = self.result, self.comparison
        keep = res.w <= 0.3 * math.pi * self.fs
        w = res.w[keep]
        curves = [Curve(label=f"measured ({res.estimator})", w=w, Z=res.Z[keep], style="points",
                        Z_err=res.Z_err[keep])]
        marks, title = {}, self.source
        if cmp is not None:
            curves.append(Curve(label=f"theory ({cmp['model']}, m = {cmp['plant']['m']:.3g}, "
                                      f"b = {cmp['plant']['b']:.3g})", w=w, Z=cmp["Z_theory"][keep]))
            marks = {k: v for k, v in (("ws*", cmp["predicted_ws_star"]),
                                       ("wb*", cmp["predicted_wb_star"])) if v}
            ve = cmp["ve"]
            title = f"{self.source}: {ve['kind']} K = {ve['K']:g}, B = {ve['B']:g}, td = {ve['td']:g} s"
        return paper_figure(curves, path, title=title, marks=marks, inputs=inputs, force=force)

    def to_csv(self, path, force: bool = False):
        """Write the response as CSV (w in rad/s and Hz, Z, its 95 % radius, coherence, ES,
        ED, EM, the theory's Z; ``labbench.sessions.export.export_frequency_response``); returns the
        path. An existing file is replaced only with ``force``; never the record itself."""
        from labbench.sessions.export import export_frequency_response

        return export_frequency_response(self, path, [self.source], force)

    def __repr__(self) -> str:
        return (f"FrequencyResponse(estimator={self.result.estimator!r}, {len(self.w)} frequencies "
                f"{self.w[0]:.3g}-{self.w[-1]:.4g} rad/s)")


def etfe_recording(rec: Recording, estimator: str | None = None, window: int = 200,
                   m: float | None = None, b: float | None = None, fit: bool = False,
                   fit_ve: bool = False, progress: Progress | None = None,
                   cancel: threading.Event | None = None,
                   band_rad_s: tuple[float, float] | None = None,
                   coulomb_n: float | None = None) -> FrequencyResponse:
    """ETFE of a record; with a VE in the metadata, the theory curve and the deviation from
    it, on the device ``m``, ``b`` given (here or in the metadata) or identified from the
    closed-loop record itself (``labbench.analysis.compare``, friction included), and the
    friction-aware theory with the device's Coulomb friction ``coulomb_n`` [N] (None: the
    metadata's, ``labbench.model.device_friction``, else estimated from the record;
    ``labbench.analysis.friction``). ``fit``: fit m, b and the
    extra loop delay to Z with the exact sampled model (``labbench.analysis.loopfit``; with
    ``fit_ve`` the rendered K, B too); the theory then uses the fitted plant and delay.
    ``progress(fraction, phrase)`` hears how far it is; once ``cancel`` is set it raises
    ``labbench.errors.Cancelled`` within about 0.5 s (``labbench.analysis.progress``).
    ``band_rad_s``: the band the verdict, the deviation and the rendered K, B speak of
    (``labbench.analysis.etfe.analysis_band``; None: 2-100 rad/s)."""
    from labbench.model import device_friction
    from labbench.analysis import compare, friction
    from labbench.analysis.etfe import etfe
    from labbench.model import predictions
    from labbench.analysis.rendered import rendered_impedance
    from labbench.model.ve import Plant

    steps = Steps(progress, cancel)
    ve = compare.ve_from_meta(rec.meta, rec.fs)
    etfe_end, ident_end = (0.2, 0.5) if (fit or fit_ve) else (0.2, 0.95)
    res = etfe(rec, estimator, window, band_rad_s=band_rad_s, progress=steps.part(0.0, etfe_end),
               cancel=cancel)
    m = m if m is not None else compare.meta_number(rec.meta, "m")
    b = b if b is not None else compare.meta_number(rec.meta, "b")
    if (m is None) != (b is None):
        raise UserError("give both --m and --b (or neither, to identify them from the record)")
    if (fit or fit_ve) and ve is None:
        raise UserError(f"{rec.source}: --fit needs the VE in the metadata (ve=..., K, B, w0, td)")
    cmp, bandwidths, loop_fit, rendered, fr, fit_summary = None, None, None, None, None, None
    known = device_friction.given(coulomb_n) if coulomb_n is not None else device_friction.from_meta(rec.meta)
    if ve is not None:
        source, latency = "given", device_delay.from_meta(rec.meta)
        evidence = None
        if m is None:  # with its friction, which would otherwise pass for viscous damping
            ident = compare.identify_closed_loop(rec, ve, latency=latency, model="auto",
                                                 progress=steps.part(etfe_end, ident_end), cancel=cancel,
                                                 coulomb_n=known.n if known.known else None)
            m, b, source = ident.m, max(ident.b, 0.0), "identified from this record"
            evidence = None if known.known else ident
        if fit or fit_ve:
            from labbench.analysis.loopfit import fit_loop

            loop_fit = fit_loop(res, ve, Plant(float(m), float(b)), fit_ve=fit_ve,
                                progress=steps.part(ident_end, 0.95), cancel=cancel)
            m, b, latency = loop_fit.m, loop_fit.b, loop_fit.td_s
            source = "fitted (with the fitted device latency td)"
            n_tv = round(loop_fit.tv_s / ve.T)
            if loop_fit.tv_s != ve.td and abs(loop_fit.tv_s / ve.T - n_tv) < 0.01:
                ve = ve.with_(td=n_tv * ve.T)  # the overlay's VE delay line: whole samples only
                source += f" and VE-path delay {n_tv} samples"
            if known.known and known.n > 0:  # the fitted b is b + b_eq: the theory takes the viscous b
                b = max(b - friction.fitted_b_eq(Plant(m, b), ve, known.n, rec.force, latency), 0.0)
                source += ", less Coulomb friction's equivalent damping"
        steps.report(0.95, "comparing with the theory")
        plant = Plant(float(m), float(b))
        cmp = compare.compare(res, plant, ve, latency, band_rad_s)
        cmp["plant_source"] = source
        pred, rendered = friction.analyse(res, rendered_impedance(res, ve, plant, latency, band_rad_s),
                                          plant, ve, known, rec, latency, evidence)
        fr = pred.as_dict()
        if pred.plant is not None:
            z_f = compare.theory_curves(pred.plant, ve, res.w, latency)["Z"]
            cmp["friction"] = compare.deviation(res, z_f, band_rad_s or W_BAND)
        if loop_fit is not None:
            fit_summary = friction.separate(loop_fit.as_dict(), pred, ve, rec.force)
        # as a run's results keep them: ED falls towards b + b_eq where friction is compared
        felt = pred.plant if friction.compared_model(rendered) == "friction" else plant
        bandwidths = predictions.read(res.w, res.Z, felt, ve, latency, rendered)
    steps.report(1.0, "done")
    return FrequencyResponse(res, rec.source, rec.fs, cmp, loop_fit, rendered, fr, fit_summary,
                             bandwidths)


# ----------------------------------------------------------------------------- the session
class Session:
    """One recorded run (or analysis CSV) with its channels, units and metadata.

    ``meta``: the analysis metadata (fs, ve, K, B, w0, td, protocol, uid, seed, rig,
    as ``labbench analyze`` reads them) plus, for a session file, status, started
    (ISO 8601), device and software. ``data``: channel -> array (``force`` is the
    exogenous force, the ``excitation`` channel of a session). ``units``: channel
    -> unit (SI). ``records``: the session's start, descriptor and stop records
    (empty for a CSV); ``events`` its events; ``problem`` a damaged tail, if any.
    """

    def __init__(self, path, meta: dict, data: dict, units: dict, records_: dict | None = None,
                 events: list | None = None, problem: str | None = None):
        self.path = Path(path)
        self.meta = meta
        self.data = data
        self.units = units
        self.records = records_ or {}
        self.events = events or []
        self.problem = problem
        self._recording: Recording | None = None

    @property
    def recording(self) -> Recording:
        """The record ``labbench analyze`` reads from this file (t, force, position, meta)."""
        if self._recording is None:
            self._recording = load_recording(self.path)
        return self._recording

    def identify(self, model: str = "auto", method: str = "l2", cutoff_hz: float | None = None,
                 solver: str = "fast", force_hold: str | None = None,
                 progress: Progress | None = None, cancel: threading.Event | None = None) -> Identification:
        """``labbench analyze id`` on this file (same options, same numbers). ``progress``,
        ``cancel``: as ``identify_recording`` (a progress bar, a Cancel button)."""
        return identify_recording(self.recording, model=model, method=method, cutoff_hz=cutoff_hz,
                                  solver=solver, force_hold=force_hold, progress=progress, cancel=cancel)

    def etfe(self, estimator: str | None = None, window: int = 200, m: float | None = None,
             b: float | None = None, fit: bool = False, fit_ve: bool = False,
             progress: Progress | None = None, cancel: threading.Event | None = None,
             band_rad_s: tuple[float, float] | None = None) -> FrequencyResponse:
        """``labbench analyze etfe`` on this file (same options, same numbers); ``fit``:
        ``--fit`` (the loop fit in ``.fit``, its verdict in ``.fit.verdict``). ``progress``,
        ``cancel``, ``band_rad_s``: as ``etfe_recording`` (a progress bar, a Cancel button)."""
        return etfe_recording(self.recording, estimator=estimator, window=window, m=m, b=b,
                              fit=fit, fit_ve=fit_ve, progress=progress, cancel=cancel,
                              band_rad_s=band_rad_s)

    def plot(self, path=None, force: bool = False):
        """Position and forces against time; returns the matplotlib Figure (and writes it to
        ``path`` if given; an existing file is replaced only with ``force``)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from labbench.readout.escape import literal_mpl
        from labbench.safe_write import replacing

        t = self.data["t"]
        fig = Figure(figsize=(9, 5), layout="constrained")
        FigureCanvasAgg(fig)
        ax_x, ax_f = fig.subplots(2, 1, sharex=True)
        ax_x.plot(t, 1e3 * self.data["position"], lw=0.7)
        ax_x.set_ylabel("position (mm)")
        forces = [c for c in ("excitation", "ve_force", "command") if c in self.data] or ["force"]
        for name in forces:
            ax_f.plot(t, self.data[name], lw=0.6, label=name)
        ax_f.set_ylabel("force (N)")
        ax_f.set_xlabel("time (s)")
        ax_f.legend(fontsize=8, loc="upper right")
        for ax in (ax_x, ax_f):
            ax.grid(alpha=0.3)
        fig.suptitle(literal_mpl(f"{self.path.name}: {self.meta.get('protocol', '')}"))
        if path is not None:
            with replacing(path, [self.path], force) as tmp:
                fig.savefig(tmp, dpi=120)
        return fig

    def to_dataframe(self):
        """The channels as a pandas DataFrame (one column per channel, units in ``.attrs``)."""
        try:
            import pandas as pd
        except ModuleNotFoundError:
            raise missing_extra("pandas", "pandas", "Session.to_dataframe()") from None
        df = pd.DataFrame({k: np.asarray(v) for k, v in self.data.items()})
        df.attrs["units"] = dict(self.units)
        df.attrs["meta"] = dict(self.meta)
        return df

    def __repr__(self) -> str:
        n = len(self.data.get("t", ()))
        fs = self.meta.get("fs")
        rate = f", {fs:g} Hz" if isinstance(fs, (int, float)) else ""
        return f"Session({self.path.name!r}, {self.meta.get('protocol', '?')}, {n} samples{rate})"


def load(path) -> Session:
    """A session file or an analysis CSV (docs/analysis.md) as a ``Session``."""
    from labbench.sessions.session_format import looks_like_session

    p = Path(path)
    if not p.is_file():
        raise UserError(f"{p}: no such file")
    if p.suffix.lower() != ".csv" and looks_like_session(p):
        return _from_session(p)
    return _from_csv(p)


def _warn(line: str) -> None:
    """A notebook hears a session read up to a damaged record as a Python warning."""
    import warnings

    warnings.warn(line, stacklevel=4)


def _from_session(p: Path) -> Session:
    from labbench.sessions.session_content import analysis_meta, load_session

    start, desc, ch, events, stop, problem = load_session(p, warn=_warn)
    meta = analysis_meta(start, desc)
    if start.get("time") is not None:
        meta["started"] = records.iso_time(start["time"])
    meta["status"] = str((stop or {}).get("status", "incomplete"))
    for key in ("software",):
        if start.get(key) is not None:
            meta[key] = start[key]
    device = start.get("device")
    if isinstance(device, dict) and device.get("kind"):
        meta["device"] = device["kind"]
    data = {name: np.asarray(v) for name, v in ch.items()}
    data["force"] = data["excitation"]  # the analysis name of the exogenous force
    units = {**dict(desc.get("channels") or records.CHANNELS), "force": "N"}
    return Session(p, meta, data, units, {"start": start, "descriptor": desc, "stop": stop},
                   events, problem)


def _from_csv(p: Path) -> Session:
    rec = load_recording(p)  # validates columns, numbers and uniform sampling
    data = {"t": rec.t, "force": rec.force, "position": rec.position}
    data.update({k: v for k, v in _csv_columns(p).items() if k not in data})
    s = Session(p, dict(rec.meta), data, {k: CSV_UNITS.get(k, "") for k in data})
    s._recording = rec
    return s


def _csv_columns(p: Path) -> dict[str, np.ndarray]:
    """Every all-numeric column of an analysis CSV (the required ones are read already)."""
    lines = p.read_text(encoding="utf-8").splitlines()
    body = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    header = [h.strip().lower() for h in next(csv.reader(body[:1]))]
    try:
        table = np.loadtxt(io.StringIO("\n".join(body[1:])), delimiter=",", ndmin=2)
    except ValueError:
        return {}  # a non-numeric extra column: keep the three analysis columns only
    return {name: table[:, i] for i, name in enumerate(header) if i < table.shape[1]}
