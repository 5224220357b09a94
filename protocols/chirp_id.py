"""Chirp identification (paper sec. 4.1): VE off, a chirp force 0.1-25 Hz, fit f = m x'' + b x'.

The free mass-damper has an integrator, so a constant-amplitude force at
0.1 Hz would carry the handle far out of its window (|X/F| = 1/(w |b + j w m|)
is ~14 m/N there for the paper's Phantom). The force amplitude therefore
follows ``min(amplitude_n, x_max_m * w |b + j w m|)`` with the nominal plant
(``excitation.displacement_envelope``), and the plan is checked before enabling
by simulating the nominal plant exactly (ZOH) against the rig's position and
velocity limits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter, ss2tf

from labbench.errors import UserError
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.protocols import excitation
from labbench.protocol import (
    MAX_DURATION_S,
    MAX_FORCE_N,
    Config,
    ProtocolBase,
    Segment,
    check_plant_fields,
    choice,
    number,
    setting,
)
from labbench.model.linear import zoh_matrices

METHODS = ("l2", "l1")


def _model_choices() -> tuple:
    from labbench.analysis.identify import MODEL_CHOICES

    return MODEL_CHOICES


@dataclass(frozen=True)
class ChirpIdConfig(Config):
    """Chirp identification: VE off, chirp force f0-f1 Hz, l2/l1 fit of m, b (sec. 4.1)."""

    f0_hz: float = setting(0.1, "start frequency of the chirp", "Hz")
    f1_hz: float = setting(25.0, "end frequency of the chirp, below Nyquist", "Hz")
    sweep: str = setting("log", "how the frequency moves from f0_hz to f1_hz",
                         choices=excitation.SWEEPS)
    amplitude_n: float = setting(1.0, "peak force of the chirp (lowered where the handle "
                                 "would move more than x_max_m)", "N")
    x_max_m: float = setting(0.02, "largest steady displacement the chirp may cause, by the "
                             "nominal plant", "m")
    duration_s: float = setting(60.0, f"length of the chirp, at most {MAX_DURATION_S:g} s", "s")
    fade_s: float = setting(1.0, "raised-cosine fade in and out", "s")
    model: str = setting("auto", "model fitted: mb (mass, damping), mbc (+ Coulomb "
                         "friction), mbco (+ force offset), auto (chosen by cross-validation)",
                         choices=_model_choices)
    methods: tuple = setting(METHODS, "fits to run, comma-separated: l2 (least squares), l1 "
                             "(least absolute deviations)", choices=METHODS)
    sample_time_s: float = 0.001
    plant_m_kg: float | None = setting(None, "nominal device mass that shapes the chirp's "
                                       "envelope; none: the rig's", "kg")
    plant_b: float | None = setting(None, "nominal device damping for the envelope; none: "
                                    "the rig's", "N s/m")

    def check(self):
        self._set("f0_hz", number("f0_hz", self.f0_hz, "Hz", lo=0, lo_open=True))
        self._set("f1_hz", number("f1_hz", self.f1_hz, "Hz", lo=0, lo_open=True))
        self._set("sample_time_s", number("sample_time_s", self.sample_time_s, "s", lo=0, lo_open=True))
        nyquist = 0.5 / self.sample_time_s
        if not self.f0_hz < self.f1_hz:
            raise UserError(f"f0_hz ({self.f0_hz:g} Hz) must be below f1_hz ({self.f1_hz:g} Hz)")
        if self.f1_hz >= nyquist:
            raise UserError(f"f1_hz must be below the Nyquist frequency {nyquist:g} Hz, got {self.f1_hz:g}")
        choice("sweep", self.sweep, excitation.SWEEPS)
        self._set("amplitude_n", number("amplitude_n", self.amplitude_n, "N", lo=0, lo_open=True,
                                        hi=MAX_FORCE_N))
        self._set("x_max_m", number("x_max_m", self.x_max_m, "m", lo=0, lo_open=True))
        self._set("duration_s", number("duration_s", self.duration_s, "s", lo=0, lo_open=True,
                                              hi=MAX_DURATION_S))
        self._set("fade_s", number("fade_s", self.fade_s, "s", lo=0, hi=self.duration_s / 2))
        from labbench.analysis.identify import MODEL_CHOICES  # checked now: not after the run

        choice("model", self.model, MODEL_CHOICES)
        if isinstance(self.methods, str):
            methods = (self.methods,)
        elif isinstance(self.methods, (list, tuple)):
            methods = tuple(self.methods)
        else:
            raise UserError(f"methods must be a list of l2, l1, got {self.methods!r}")
        if not methods:
            raise UserError("methods must name at least one of l2, l1")
        for m in methods:
            choice("methods", m, METHODS)
        self._set("methods", methods)
        check_plant_fields(self)
        if self.duration_s * self.f0_hz < 1:
            raise UserError(f"duration_s ({self.duration_s:g} s) must cover at least one period "
                            f"of f0_hz ({1 / self.f0_hz:g} s)")


class ChirpId(ProtocolBase):
    name = "chirp-id"

    Config = ChirpIdConfig
    config: ChirpIdConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return VirtualEnvironment("none", T=self.config.sample_time_s)

    @property
    def n_samples(self) -> int:
        return round(self.config.duration_s / self.config.sample_time_s)

    def excitation(self, plant: Plant) -> np.ndarray:
        c = self.config

        def env(f_hz):
            return excitation.displacement_envelope(f_hz, plant.m, plant.b, c.x_max_m, c.amplitude_n)

        return excitation.chirp(self.n_samples, c.sample_time_s, c.f0_hz, c.f1_hz, env, c.sweep,
                                round(c.fade_s / c.sample_time_s))

    def check_plan(self, plant: Plant, rig=None) -> dict:
        """Simulate the nominal plant (exact ZOH) under the planned force; refuse a plan
        that leaves the rig's position window or exceeds its velocity/force limits."""
        f = self.excitation(plant)
        Ad, Bd = zoh_matrices(plant.m, plant.b, self.config.sample_time_s)
        # x[k+1] = Ad x[k] + Bd f[k], as two transfer functions run by lfilter (C speed).
        x, v = (_run_tf(ss2tf(Ad, Bd[:, None], C, [[0.0]]), f) for C in ([[1.0, 0.0]], [[0.0, 1.0]]))
        out = {"predicted_x_range_m": [float(x.min()), float(x.max())],
               "predicted_v_max_m_s": float(np.abs(v).max()),
               "force_peak_n": float(np.abs(f).max())}
        if rig is not None:
            lo, hi = rig.position_limits_m
            if x.min() < lo or x.max() > hi:
                raise UserError(
                    f"chirp would move the handle over [{x.min():.3g}, {x.max():.3g}] m, outside the "
                    f"rig's window [{lo:g}, {hi:g}] m (m = {plant.m:g} kg, b = {plant.b:g} N s/m): "
                    f"lower x_max_m ({self.config.x_max_m:g} m)")
            if np.abs(v).max() > rig.velocity_limit_m_s:
                raise UserError(
                    f"chirp would reach {np.abs(v).max():.3g} m/s, above the rig's velocity limit "
                    f"{rig.velocity_limit_m_s:g} m/s: lower amplitude_n or x_max_m")
            if np.abs(f).max() > rig.force_limit_n:
                raise UserError(f"amplitude_n {self.config.amplitude_n:g} N exceeds the rig's "
                                f"force limit {rig.force_limit_n:g} N")
        return {"plan": out}

    def segments(self, plant: Plant):
        yield Segment("chirp", self.ve, self.excitation(plant))

    def analyze(self, data: dict, meta: dict) -> dict:
        """l2 and l1 fits of f = m x'' + b x' (labbench.analysis.identify) on the force
        actually applied (the ``command`` channel: the VE is off, so it is the chirp
        after the safety envelope), as the plant felt it after the device's own delay
        (``labbench.model.device_delay``: ``compare.plant_force`` shifts the held command)."""
        from labbench.model import device_delay
        from labbench.analysis.compare import plant_force
        from labbench.analysis.dataio import recording_from_arrays
        from labbench.analysis.identify import identify

        rec = recording_from_arrays(data["t"], data["command"], data["position"],
                                    {**meta, "protocol": self.name})
        latency = device_delay.from_meta(meta)
        if latency:
            rec = recording_from_arrays(rec.t, plant_force(rec, None, latency), rec.position,
                                        rec.meta, rec.source)
        fits = {method: identify(rec, model=self.config.model, method=method).as_dict()
                for method in self.config.methods}
        best = fits.get("l2") or fits[self.config.methods[0]]
        # the device's Coulomb friction for the runs that take this plant (None: not in the model)
        return {"identification": fits, "m": best["m"], "b": best["b"], "coulomb": best.get("coulomb"),
                "coulomb_ci95": (best.get("ci95") or {}).get("coulomb")}

    def report_sections(self, session):
        """Page 1: the identified m, b with intervals and the model chosen; details: every
        fit, and the open-loop impedance of the chirp against the identified model."""
        return _report_sections(self, session)


def _run_tf(tf, u: np.ndarray) -> np.ndarray:
    num, den = tf
    return lfilter(num[0], den, u)


def _report_sections(protocol: ChirpId, session):
    from labbench.report.blocks import Figure, Paragraph, ReportSections, Table, fmt, fmt_ci

    ident = session.results.get("identification") or {}
    if not ident:
        return ReportSections()
    primary = "l2" if "l2" in ident else next(iter(ident))
    sel = ident[primary].get("selection") or {}
    rows = []
    for method, fit in ident.items():
        fci = fit.get("ci95") or {}
        rows.append([method, str(fit.get("model")), fmt_ci(fit.get("m"), *fci.get("m", (None, None))),
                     fmt_ci(fit.get("b"), *fci.get("b", (None, None))),
                     fmt_ci(fit.get("coulomb"), *fci.get("coulomb", (None, None))),
                     fmt(fit.get("rms_residual"), 3), f"{100 * fit.get('explained', 0):.4f} %",
                     str(fit.get("n_used"))])
    details = [Table("Identification f = m x'' + b x' [+ Fc sign(x')] [+ f0], every fit",
                     ["fit", "model", "m (kg), 95 % interval", "b (N s/m), 95 % interval",
                      "Fc (N), 95 % interval", "rms residual (N)", "explained", "samples"], rows,
                     note=f"Model selection: {sel.get('reason') or sel.get('criterion') or 'as configured'}.")]
    figure = _open_loop_figure(protocol, session, ident)
    if figure is not None:
        details.append(Figure("Open-loop impedance during the chirp (points) against the "
                              "identified model (lines, exact sampled, VE off)", figure))
    else:
        details.append(Paragraph("No open-loop impedance figure: the chirp's band is empty."))
    return ReportSections(details=details)


def _open_loop_figure(protocol: ChirpId, session, ident: dict):
    """ETFE of the applied force (``command``) over position in the chirp's band, against
    Z = b + j w m of each fit through the exact sampled model with the VE off."""
    import math

    from labbench.analysis.compare import theory_curves
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe
    from labbench.readout.figures import Curve, paper_figure

    c = protocol.config
    rec = recording_from_arrays(session.ch["t"], session.ch["command"], session.ch["position"],
                                {"fs": 1 / session.T})
    est = etfe(rec)
    w, Z = np.asarray(est.w), np.asarray(est.Z)
    keep = (w >= 2 * math.pi * c.f0_hz) & (w <= 2 * math.pi * c.f1_hz)
    if not keep.any():
        return None
    off = VirtualEnvironment("none", T=session.T)
    curves = [Curve(f"identified ({method}): m = {fit['m']:.4g} kg, b = {fit['b']:.4g} N s/m",
                    w[keep], theory_curves(Plant(float(fit["m"]), float(fit["b"])), off, w[keep])["Z"])
              for method, fit in ident.items() if fit.get("m") and fit.get("b") is not None]
    curves.append(Curve("measured (ETFE of the chirp)", w[keep], Z[keep], "points"))
    return paper_figure(curves, title=f"{session.tag} chirp identification, VE off")

