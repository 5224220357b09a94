"""White-noise ETFE (paper sec. 4.2): closed loop with the chosen VE, white exogenous force,
2 minutes at 1 kHz by default -> ETFE, effective impedances, theory overlay.

The overlay is the exact sampled model ``labbench.model.linear.z_sampled`` (and the
paper's continuous eq. 2 for comparison; both from
``labbench.analysis.compare.theory_curves``, with the rig's measured extra loop
delay when the rig file has one) with the plant m, b given in the config (the
demo passes the chirp-ID's identified values) or the rig's nominal.
"""
from __future__ import annotations

import secrets
from dataclasses import dataclass

import numpy as np

from labbench.model import device_delay
from labbench.errors import UserError
from labbench.model.ve import VE_KINDS, Plant, VirtualEnvironment
from labbench.protocols import excitation
from labbench.protocol import (
    MAX_DURATION_S,
    MAX_FORCE_N,
    Config,
    ProtocolBase,
    Segment,
    check_plant_fields,
    check_ve_fields,
    choice,
    integer,
    make_ve,
    number,
    setting,
)

MAX_LEVELS = 2  # excitation levels beyond std_n (issue 41: two or three levels in one session)


def _float(x):
    """A level as given: a number, or the CLI's word for one."""
    try:
        return float(x) if isinstance(x, str) else x
    except ValueError:
        return x


# Summary figures stop at this fraction of Nyquist: above, the sampled loop's ED and EM
# swing towards Nyquist and would set the scale of panels meant for the rendered band.
SUMMARY_W_MAX_NYQUIST = 0.1


def _estimators() -> tuple:
    from labbench.analysis.etfe import ESTIMATORS

    return ESTIMATORS


@dataclass(frozen=True)
class EtfeConfig(Config):
    """White-noise ETFE of the closed loop with a chosen VE (sec. 4.2), theory overlay."""

    ve: str = "spring-damper"
    K: float = 50.0
    B: float = 1.0
    w0_rad_s: float | None = 125.0
    td_s: float = 0.0
    std_n: float = setting(0.5, "standard deviation of the white-noise excitation force", "N")
    band_lo_hz: float = setting(0.0, "lower edge of the excitation's band (0, with band_hi_hz "
                                "none: unfiltered white noise)", "Hz")
    band_hi_hz: float | None = setting(None, "upper edge of the excitation's band; none: up "
                                       "to the Nyquist frequency", "Hz")
    duration_s: float = setting(120.0, f"length of the record, 1 to {MAX_DURATION_S:g} s "
                                "(longer: narrower frequency bins); each level's", "s")
    levels_n: tuple = setting((), "more excitation levels after std_n, comma-separated "
                              "standard deviations (at most 2), each a record of duration_s: the "
                              "rendered K and B at each show whether the response depends on "
                              "amplitude (friction's equivalent damping falls as the excitation "
                              "grows)", "N")
    seed: int | None = setting(None, "seed of the noise; none: drawn at random and recorded "
                               "in the session")
    window: int = setting(200, "Hamming window of the paper estimator, in frequency bins "
                          "(its smoothing)")
    estimator: str | None = setting(None, "the ETFE estimator (labbench.analysis.etfe); none: "
                                    "its default", choices=_estimators)
    sample_time_s: float = 0.001
    plant_m_kg: float | None = None
    plant_b: float | None = None
    plant_coulomb_n: float | None = None
    plant_coulomb_ci95: tuple | None = None
    allow_unstable: bool = False  # the runner allows it on simulators only

    def check(self):
        choice("ve", self.ve, VE_KINDS)
        check_ve_fields(self)
        self._set("sample_time_s", number("sample_time_s", self.sample_time_s, "s", lo=0, lo_open=True))
        nyquist = 0.5 / self.sample_time_s
        self._set("std_n", number("std_n", self.std_n, "N", lo=0, lo_open=True, hi=MAX_FORCE_N))
        self._set("band_lo_hz", number("band_lo_hz", self.band_lo_hz, "Hz", lo=0, hi=nyquist))
        self._set("band_hi_hz", number("band_hi_hz", self.band_hi_hz, "Hz", lo=0, lo_open=True,
                                       hi=nyquist, none_ok=True))
        if self.band_hi_hz is not None and not self.band_lo_hz < self.band_hi_hz:
            raise UserError(f"band_lo_hz ({self.band_lo_hz:g}) must be below band_hi_hz "
                            f"({self.band_hi_hz:g}) Hz")
        self._set("duration_s", number("duration_s", self.duration_s, "s", lo=1.0,
                                              hi=MAX_DURATION_S))
        levels = self.levels_n if isinstance(self.levels_n, (list, tuple)) else (self.levels_n,)
        if len(levels) > MAX_LEVELS:
            raise UserError(f"levels_n takes at most {MAX_LEVELS} more levels, got {len(levels)}")
        self._set("levels_n", tuple(number("levels_n", _float(x), "N", lo=0, lo_open=True, hi=MAX_FORCE_N)
                                    for x in levels))
        if (1 + len(self.levels_n)) * self.duration_s > MAX_DURATION_S:
            raise UserError(f"{1 + len(self.levels_n)} levels of {self.duration_s:g} s exceed the "
                            f"longest run, {MAX_DURATION_S:g} s")
        if self.seed is None:
            self._set("seed", secrets.randbits(32))
        self._set("seed", integer("seed", self.seed, lo=0))
        self._set("window", integer("window", self.window, lo=1))
        if self.estimator is not None:  # checked now: not after the whole run
            from labbench.analysis.etfe import ESTIMATORS

            choice("estimator", self.estimator, ESTIMATORS)
        check_plant_fields(self)
        if not isinstance(self.allow_unstable, bool):
            raise UserError(f"allow_unstable must be true or false, got {self.allow_unstable!r}")
        self.make_ve()

    def make_ve(self) -> VirtualEnvironment:
        return make_ve(self.ve, self.K, self.B, self.w0_rad_s, self.sample_time_s, self.td_s)


class WhiteNoiseEtfe(ProtocolBase):
    name = "etfe"

    Config = EtfeConfig
    config: EtfeConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return self.config.make_ve()

    @property
    def n_level(self) -> int:
        """Samples of one excitation level's record."""
        return round(self.config.duration_s / self.config.sample_time_s)

    @property
    def n_samples(self) -> int:
        return self.n_level * (1 + len(self.config.levels_n))

    @property
    def levels(self) -> tuple[float, ...]:
        """The excitation's standard deviations [N], std_n first."""
        return (self.config.std_n, *self.config.levels_n)

    def excitation(self, level: int = 0) -> np.ndarray:
        """The white noise of excitation level ``level`` (0: std_n), each with its own seed."""
        c = self.config
        band = None if (c.band_lo_hz == 0 and c.band_hi_hz is None) else (
            c.band_lo_hz, c.band_hi_hz if c.band_hi_hz is not None else 0.5 / c.sample_time_s)
        return excitation.white_noise(self.n_level, c.sample_time_s, self.levels[level], band,
                                      c.seed + level)

    def analysis_band(self) -> tuple[float, float]:
        """The band [rad/s] the verdict and the accuracy figures speak of: the accuracy
        targets' band (``labbench.analysis.etfe.W_BAND``, docs/protocols.md) within the
        excited one; the excited band itself when the two do not meet."""
        from labbench.analysis.etfe import W_BAND

        c = self.config
        lo = 2 * np.pi * c.band_lo_hz
        hi = np.pi / c.sample_time_s if c.band_hi_hz is None else 2 * np.pi * c.band_hi_hz
        both = (max(W_BAND[0], lo), min(W_BAND[1], hi))
        return both if both[0] < both[1] else (float(lo), float(hi))

    def segments(self, plant: Plant):
        yield Segment("white-noise", self.ve, self.excitation())
        for k in range(1, len(self.levels)):
            yield Segment(f"white-noise {self.levels[k]:g} N", self.ve, self.excitation(k))

    def check_plan(self, plant: Plant, rig=None) -> dict:
        """With the device's Coulomb friction known (``device_friction``, set by the run's
        checks; else the config's): what it will act as at this excitation, and the white
        noise that keeps it below ``labbench.analysis.friction.SHARE`` of B + b."""
        from labbench.model import device_friction
        from labbench.analysis import friction

        fr = getattr(self, "device_friction", None) or device_friction.resolve(self)
        if not fr.known or fr.n == 0:
            return {}
        return {"friction": friction.plan(plant, self.ve, fr, self.excitation(),
                                          getattr(self, "device_delay_s", 0.0),
                                          None if rig is None else rig.force_limit_n)}

    def analyze(self, data: dict, meta: dict) -> dict:
        """ETFE of the exogenous force over the velocity (labbench.analysis.etfe), its effective
        impedances (labbench.model.effective), the deviation from the exact sampled theory and from
        the friction-aware one (labbench.analysis.friction, with the run's friction:
        labbench.model.device_friction), the closed-loop fit of m, b and the rig's extra delay
        (labbench.analysis.loopfit), and the force noise the loop commanded
        (labbench.analysis.force_noise)."""
        from labbench.model import device_friction
        from labbench.model import predictions
        from labbench.analysis import compare, force_noise, friction
        from labbench.model.noise import FELT_BAND_HZ
        from labbench.analysis.dataio import recording_from_arrays
        from labbench.analysis.etfe import etfe
        from labbench.analysis.loopfit import fit_loop
        from labbench.analysis.rendered import rendered_impedance

        n = self.n_level
        levels = [{k: v[i * n:(i + 1) * n] for k, v in data.items()} for i in range(len(self.levels))]
        data = levels[0]
        rec = recording_from_arrays(data["t"], data["excitation"], data["position"],
                                    {**meta, "protocol": self.name})
        asked = self.analysis_band()
        est = etfe(rec, estimator=self.config.estimator, window=self.config.window, band_rad_s=asked)
        plant = Plant(**meta["plant"]) if "plant" in meta else self.plant()
        ve = self.ve
        w = np.asarray(est.w)
        Z = np.asarray(est.Z)
        latency = device_delay.from_meta(meta)
        curves = compare.theory_curves(plant, ve, w, latency)
        z_s, z_p = curves["sampled"], curves["paper"]
        try:
            # the protocol renders the VE itself, so its VE-path delay is known: only the
            # device's latency on the whole command is the record's to find
            loop_fit = fit_loop(est, ve, plant, delay_model="common").as_dict()
        except UserError as exc:  # too few coherent frequencies: say so in the results
            loop_fit = {"error": str(exc)}
        fr, rendered = friction.analyse(est, rendered_impedance(est, ve, plant, latency, asked),
                                        plant, ve, device_friction.from_meta(meta), rec, latency)
        loop_fit = friction.separate(loop_fit, fr, ve, rec.force)
        theory = {"sampled": {"Z_re": z_s.real, "Z_im": z_s.imag},
                  "paper": {"Z_re": z_p.real, "Z_im": z_p.imag}}
        extra = {}
        if fr.plant is not None:
            z_f = compare.theory_curves(fr.plant, ve, w, latency)["Z"]
            theory["friction"] = {"Z_re": z_f.real, "Z_im": z_f.imag}
            extra["deviation_vs_friction"] = compare.deviation(est, z_f, asked)
        # the bandwidths of the model compared with: ED falls towards b + b_eq, not b
        felt = fr.plant if friction.compared_model(rendered) == "friction" else plant
        try:  # the command's noise in the felt band (docs/design.md)
            noise = force_noise.measure(data["command"], data["excitation"], ve.T,
                                        FELT_BAND_HZ).as_dict()
        except UserError as exc:  # a record too short for the band
            noise = {"error": str(exc)}
        more = {}
        if len(self.levels) > 1:  # the same analysis at each level: does the response follow?
            more["levels"] = friction.levels(
                [rendered] + [self._level(block, meta, plant, ve, latency, asked) for block in levels[1:]],
                self.levels)
        return {
            **more,
            "force_noise": noise,
            "etfe": est.as_dict(),
            "loop_fit": loop_fit,
            "plant": {"m": plant.m, "b": plant.b},
            "friction": fr.as_dict(),
            "rendered": rendered,
            "theory": theory,
            "deviation_vs_sampled": compare.deviation(est, z_s, asked),
            **extra,
            # measured as the rendered K, B are read; predicted off the exact sampled model's
            # curves, which the data follow, the paper's closed forms (eq. 5, w0) beside them
            "bandwidths": predictions.read(w, Z, felt, ve, latency, rendered),
        }

    def _level(self, data: dict, meta: dict, plant: Plant, ve, latency: float, asked) -> dict | None:
        """The rendered K, B of one further excitation level against the theories (None: too
        short a record for the VE's bandwidths)."""
        from labbench.model import device_friction
        from labbench.analysis import friction
        from labbench.analysis.dataio import recording_from_arrays
        from labbench.analysis.etfe import etfe
        from labbench.analysis.rendered import rendered_impedance

        rec = recording_from_arrays(data["t"], data["excitation"], data["position"],
                                    {**meta, "protocol": self.name})
        est = etfe(rec, estimator=self.config.estimator, window=self.config.window, band_rad_s=asked)
        fr, rendered = friction.analyse(est, rendered_impedance(est, ve, plant, latency, asked),
                                        plant, ve, device_friction.from_meta(meta), rec, latency)
        return None if rendered is None else {**rendered, "friction_used": fr.as_dict()}

    def report_sections(self, session):
        """Page 1: the rendered impedance against the exact sampled theory (deviation,
        bandwidths measured and predicted by that theory) and this run's curves for the
        overlay figure; details: the paper-style figure and the numbers behind it."""
        return _report_sections(self, session)


def _report_sections(protocol: WhiteNoiseEtfe, session):
    import math

    from labbench.readout.figures import Curve, paper_figure
    from labbench.report.blocks import Figure, Markup, ReportSections, Table, fmt, fmt_ci, percent
    from labbench.report.content import nyquist_band, overlay_color

    from labbench.sessions.session_content import analysis_meta

    plant = session.plant or protocol.plant()
    # the session's own metadata: its device delay is the run's theory too (the run's
    # results and the window give w_b* with it; without it the report's was another)
    full = protocol.analyze(session.ch, {**analysis_meta(session.start, session.desc),
                                         "plant": {"m": plant.m, "b": plant.b}})
    e, th, dev, bw = full["etfe"], full["theory"], full["deviation_vs_sampled"], full["bandwidths"]
    ve = protocol.ve
    w = np.asarray(e["w"])
    keep = nyquist_band(w, session.T)
    Z = (np.asarray(e["Z_re"]) + 1j * np.asarray(e["Z_im"]))[keep]
    err = np.asarray(e["Z_err"])[keep]
    z_s = (np.asarray(th["sampled"]["Z_re"]) + 1j * np.asarray(th["sampled"]["Z_im"]))[keep]
    z_p = (np.asarray(th["paper"]["Z_re"]) + 1j * np.asarray(th["paper"]["Z_im"]))[keep]
    z_f = (np.asarray(th["friction"]["Z_re"]) + 1j * np.asarray(th["friction"]["Z_im"]))[keep] \
        if "friction" in th else None
    w = w[keep]
    w0 = f"{ve.w0:g} rad/s" if math.isfinite(ve.w0) else "none"
    band = dev.get("band_rad_s") or [None, None]
    color = overlay_color(session)
    name = f"{session.tag} K {ve.K:g}, B {ve.B:g}, td {1e3 * ve.td:g} ms"
    low = w <= SUMMARY_W_MAX_NYQUIST * math.pi / session.T
    curves = [Curve(f"{name}: sampled theory", w[low], z_s[low], color=color),
              Curve(f"{name}: measured", w[low], Z[low], "points", color=color)]
    marks = {"ws*": bw.get("ws_star_measured"), "wb*": bw.get("wb_star_measured")}
    with_friction = [] if z_f is None else [
        Curve(f"sampled theory with Coulomb friction {full['friction']['n']:.2g} N", w, z_f)]
    fig = paper_figure([Curve("exact sampled theory", w, z_s), *with_friction, Curve("paper eq. 2", w, z_p),
                        Curve("measured (ETFE)", w, Z, "points", err)],
                       title=f"{session.tag} {ve.kind} K = {ve.K:g} N/m, B = {ve.B:g} N s/m, "
                             f"w0 = {w0}, td = {1e3 * ve.td:g} ms", marks=marks)
    details = [
        Figure("Closed-loop impedance and effective impedances: data (points, 95 % band) against "
               "the exact sampled theory (with the device's Coulomb friction as the damper it acts "
               "as at this excitation, where known) and the paper's eq. 2; dashed: measured "
               "bandwidths", fig),
        Table("Accuracy against the exact sampled theory",
              ["band (rad/s)", "frequencies", "median deviation", "max deviation"],
              [[f"{fmt(band[0])} to {fmt(band[1])}", str(dev.get("n_points")),
                percent(dev.get("median_rel"), 3), percent(dev.get("max_rel"), 3)]]),
        Table("Bandwidths", ["", "measured (rad/s)", "exact sampled theory (rad/s)",
                             "continuous closed form (rad/s)"],
              [[Markup("ω<sub>s</sub>* (ES crosses zero)"), fmt(bw.get("ws_star_measured")),
                fmt(bw.get("ws_star_predicted")), fmt(bw.get("ws_star_eq5"))],
               [Markup("ω<sub>b</sub>* (ED half-way to b)"), fmt(bw.get("wb_star_measured")),
                fmt(bw.get("wb_star_predicted")), fmt(bw.get("wb_star_w0"))]],
              note="Closed forms: sqrt(K/m) (paper eq. 5) and w0 (sec. 3.2). The sampled theory "
                   "is read off its own curves with the rules applied to the measurement."),
    ]
    fit, delay = full.get("loop_fit") or {}, None
    if "td_s" in fit:
        ci = fit["ci95"]
        lo, hi = ci["td_s"]
        loop = fit["loop_delay_s"]  # td plus the VE's own delay: td's interval, shifted
        delay = (f"{fmt_ci(1e3 * loop, 1e3 * (loop - fit['td_s'] + lo), 1e3 * (loop - fit['td_s'] + hi), 'ms', scale=1.0)}"
                 f", fitted to Z (VE's own {1e3 * fit['td_meta_s']:g} ms included)")
        rows = [[name, fmt_ci(k * fit[key], *(k * v for v in ci[key]), scale=scale), unit]
                for name, key, unit, k, scale in (("m", "m", "kg", 1.0, None), ("b", "b", "N s/m", 1.0, None),
                                                  ("extra delay td", "td_s", "ms", 1e3, 1.0))]
        details.append(Table("Closed-loop fit of the measured Z (exact sampled model; "
                             "labbench analyze etfe --fit)", ["", "value (95 % interval)", "unit"], rows,
                             note=f"{fit['n_freq']} coherent frequencies, "
                                  f"{fmt(fit['band_rad_s'][0])}-{fmt(fit['band_rad_s'][1])} rad/s; "
                                  f"residual rms {percent(fit['residual_rms'])} of |Z|."))
    return ReportSections(curves=curves, details=details, delay=delay)

