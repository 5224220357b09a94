"""Stability probe: step K (or td) up until the loop grows or the safety envelope trips.

Each step renders the VE for a few oscillation periods after a small half-sine
force pulse and measures the growth rate sigma [1/s] of the free response
(least-squares line through the log of its half-cycle peaks). The first step
with sigma > 0, or ended by a safety trip (energy observer), is unstable; the
measured boundary is where sigma crosses zero, interpolated linearly between
the last stable and the first unstable step. It is compared with the exact
sampled boundary ``labbench.theory.k_max`` and the paper's ``k_max_approx``
(b = K (T/2 + td) for the spring).

Steps beyond the exact boundary are the point of this protocol: the starting
VE must be stable (precheck), and the highest step is capped at ``max_over``
times the exact boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from labbench.errors import UserError
from labbench.ve import Plant, VirtualEnvironment
from labbench.protocols import excitation
from labbench.protocol import (
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

VARIABLES = ("K", "td")
HOME_K_MAX = 20.0  # N/m, stiffest homing spring
HOME_W0 = 200.0  # rad/s, velocity filter of the homing damper
PROBE_KINDS = ("spring", "spring-damper")


@dataclass(frozen=True)
class StabilityConfig(Config):
    """Stability probe: step K (or td) up until growth or a trip; vs exact boundary."""

    ve: str = setting("spring", "the virtual environment probed", choices=PROBE_KINDS)
    K: float = setting(20.0, "virtual stiffness: the first step's (variable K) or every "
                       "step's (variable td)", "N/m")
    B: float = 0.0
    w0_rad_s: float | None = None
    td_s: float = setting(0.0, "extra delay of the VE force, whole sample times: the first "
                          "step's (variable td) or every step's (variable K)", "s")
    variable: str = setting("K", "what grows from step to step", choices=VARIABLES)
    ratio: float = setting(1.1, "factor from one step's K to the next's (above 1, at most 10)")
    K_stop: float | None = setting(None, "last K tried; none: max_over times the exact "
                                   "boundary K_max", "N/m")
    td_stop_s: float = setting(0.02, "last td tried (variable td)", "s")
    max_over: float = setting(1.5, "highest K tried as a multiple of the exact boundary K_max "
                              "(above 1)")
    cycles: float = setting(15.0, "length of a step in oscillation periods 2 pi sqrt(m/K), "
                            "at least 2, within min_step_s to max_step_s")
    min_step_s: float = setting(1.0, "shortest step", "s")
    max_step_s: float = setting(10.0, "longest step (at most 60 s)", "s")
    pulse_n: float = setting(0.5, "peak of the half-sine force pulse that starts each step",
                             "N")
    pulse_s: float = setting(0.02, "duration of that pulse", "s")
    sample_time_s: float = 0.001
    plant_m_kg: float | None = None
    plant_b: float | None = None
    allow_unstable: bool = False

    def check(self):
        choice("ve", self.ve, PROBE_KINDS)
        check_ve_fields(self)
        choice("variable", self.variable, VARIABLES)
        self._set("sample_time_s", number("sample_time_s", self.sample_time_s, "s", lo=0, lo_open=True))
        self._set("ratio", number("ratio", self.ratio, "1", lo=1, lo_open=True, hi=10))
        self._set("K_stop", number("K_stop", self.K_stop, "N/m", lo=0, lo_open=True, none_ok=True))
        self._set("td_stop_s", number("td_stop_s", self.td_stop_s, "s", lo=0))
        self._set("max_over", number("max_over", self.max_over, "1", lo=1, lo_open=True))
        self._set("cycles", number("cycles", self.cycles, "1", lo=2))
        self._set("min_step_s", number("min_step_s", self.min_step_s, "s", lo=0, lo_open=True,
                                              hi=60.0))
        self._set("max_step_s", number("max_step_s", self.max_step_s, "s", lo=self.min_step_s,
                                              hi=60.0))
        self._set("pulse_n", number("pulse_n", self.pulse_n, "N", lo=0, lo_open=True))
        self._set("pulse_s", number("pulse_s", self.pulse_s, "s", lo=self.sample_time_s))
        if self.K <= 0:
            raise UserError(f"K must be > 0 N/m for a stability probe, got {self.K:g}")
        if self.K_stop is not None and self.K_stop <= self.K:
            raise UserError(f"K_stop ({self.K_stop:g}) must be above K ({self.K:g}) N/m")
        check_plant_fields(self)
        if not isinstance(self.allow_unstable, bool):
            raise UserError(f"allow_unstable must be true or false, got {self.allow_unstable!r}")
        self.make_ve()
        if self.variable == "td":
            integer("td_stop_s in samples", round(self.td_stop_s / self.sample_time_s), lo=0)
            make_ve(self.ve, self.K, self.B, self.w0_rad_s, self.sample_time_s, self.td_stop_s)

    def make_ve(self, **changes) -> VirtualEnvironment:
        return make_ve(self.ve, self.K, self.B, self.w0_rad_s, self.sample_time_s,
                       self.td_s).with_(**changes)


def growth_rate(t: np.ndarray, x: np.ndarray, floor_m: float = 0.0,
                rel_floor: float = 0.02) -> float | None:
    """Growth rate sigma [1/s] of an oscillation: slope of the log of its half-cycle peaks.

    The offset (friction, quantisation) is the mean of the last fifth: a decay has
    settled there and a growth is a near zero-mean oscillation. Between
    consecutive zero crossings of x - offset the largest |x - offset| is one
    peak; for e^(sigma t) sin(w t + phi) the sums of consecutive peaks lie
    exactly on a line in log scale, slope sigma. Peaks at or below ``floor_m`` (a few encoder counts)
    or ``rel_floor`` of the largest are dropped (a decay that reached the noise
    floor would bias sigma towards zero), and so are the partial first and last
    half-cycles. None with fewer than 3 peaks.
    """
    x = np.asarray(x, float)
    t = np.asarray(t, float)
    if x.size < 10:
        return None
    y = x - x[-max(x.size // 5, 1):].mean()
    edges = np.flatnonzero(np.signbit(y[1:]) != np.signbit(y[:-1])) + 1
    if edges.size < 3:
        return None
    tp, yp = [], []
    for a, b in pairwise(edges):
        i = a + int(np.argmax(np.abs(y[a:b])))
        tp.append(t[i])
        yp.append(abs(y[i]))
    # Consecutive peaks have opposite signs: their sum (peak to peak) is free of any
    # error in the offset, and for the exponential it is A0 e^(sigma t_k) (1 + e^(sigma h)).
    tp, yp = np.array(tp[:-1]), np.array(yp[:-1]) + np.array(yp[1:])
    ok = yp > max(2 * floor_m, rel_floor * yp.max(), 1e-12)
    if ok.sum() < 3:
        return None
    slope, _ = np.polyfit(tp[ok], np.log(yp[ok]), 1)
    return float(slope)


class StabilityProbe(ProtocolBase):
    name = "stability"

    Config = StabilityConfig
    config: StabilityConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return self.config.make_ve()

    def k_ceiling(self, plant: Plant) -> float:
        from labbench import theory

        km = theory.k_max(plant, self.ve)
        ceiling = self.config.max_over * km if km is not None else math.inf
        stop = self.config.K_stop if self.config.K_stop is not None else ceiling
        if stop > ceiling and not self.allow_unstable:
            raise UserError(f"K_stop {stop:g} N/m is above {self.config.max_over:g} x the exact "
                            f"boundary K_max = {km:.4g} N/m")
        if not math.isfinite(stop):
            raise UserError("no finite K_stop: give K_stop")
        return stop

    def plan(self, plant: Plant) -> list[VirtualEnvironment]:
        """The VEs of every step, in order (the probe stops at the first unstable one)."""
        c = self.config
        if c.variable == "K":
            stop = self.k_ceiling(plant)
            n = math.floor(math.log(stop / c.K) / math.log(c.ratio) + 1e-9) + 1
            return [c.make_ve(K=c.K * c.ratio**i) for i in range(n)]
        n0 = round(c.td_s / c.sample_time_s)
        n1 = round(c.td_stop_s / c.sample_time_s)
        return [c.make_ve(td=i * c.sample_time_s) for i in range(n0, n1 + 1)]

    def step_samples(self, ve: VirtualEnvironment, plant: Plant) -> int:
        c = self.config
        period = 2 * math.pi / math.sqrt(ve.K / plant.m)
        dur = min(max(c.cycles * period, c.min_step_s), c.max_step_s)
        return round(dur / c.sample_time_s)

    @property
    def n_samples(self) -> int:
        plant = self.plant()
        return sum(self.step_samples(ve, plant) for ve in self.plan(plant))

    def check_plan(self, plant: Plant, rig=None) -> dict:
        if rig is not None:
            self._floor = 3 * rig.metres_per_count
        ves = self.plan(plant)
        return {"plan": {"steps": len(ves), "first": ves[0].as_dict(), "last": ves[-1].as_dict()}}

    def pulse(self, n: int) -> np.ndarray:
        c = self.config
        return excitation.pulse(n, c.sample_time_s, c.pulse_n, c.pulse_s, at_s=0.05)

    def segments(self, plant: Plant):
        self._last = None
        for ve in self.plan(plant):
            yield from self._home(plant, ve)
            label = f"K={ve.K:.6g}" if self.config.variable == "K" else f"td={ve.td:.6g}"
            out = yield Segment(label, ve, self.pulse(self.step_samples(ve, plant)),
                                trip_expected=True)
            self._last = out.data
            if self._unstable(out.status, self._sigma(out.data)):
                return

    _last: dict | None = None  # data of the last segment (where the handle was left)

    def _home(self, plant: Plant, next_ve: VirtualEnvironment):
        """Bring the handle back to rest near x = 0 before a step.

        The loop disables the device between segments, so the handle coasts; a
        step's spring would then start far off centre and its enable gate
        (|command| small) would never open. Each homing stage renders a
        critically damped spring-damper soft enough to enable where the handle
        is (K_h |x| <= 0.1 N), until K_next |x| <= 0.05 N.
        """
        from labbench import theory

        T = self.config.sample_time_s
        for _ in range(8):
            if self._last is None or len(self._last["position"]) == 0:
                return
            x = float(self._last["position"][-1])
            v = float(self._last["velocity"][-1])
            if abs(next_ve.K * x) <= 0.05 and abs(v) <= 0.01:
                return
            K_h = min(HOME_K_MAX, 0.1 / max(abs(x), 1e-6))
            B_h = max(2 * math.sqrt(K_h * plant.m) - plant.b, 0.0)
            ve = VirtualEnvironment("spring-damper", K_h, B_h, HOME_W0, T, 0.0)
            if not theory.stability(plant, ve).stable:
                raise UserError(f"homing VE K = {K_h:.3g} N/m, B = {B_h:.3g} N s/m is unstable "
                                f"on m = {plant.m:g} kg, b = {plant.b:g} N s/m")
            dur = min(max(6.0 / math.sqrt(K_h / plant.m), 0.3), 3.0)
            out = yield Segment("home", ve, np.zeros(round(dur / T)), role="home")
            self._last = out.data

    def _sigma(self, data: dict) -> float | None:
        start = 0.05 + self.config.pulse_s + 0.05
        t = np.asarray(data["t"], float)
        if t.size == 0:
            return None
        keep = t - t[0] >= start
        return growth_rate(t[keep], np.asarray(data["position"])[keep], self._floor)

    _floor = 0.0  # envelope floor [m]: 3 encoder counts once the rig is known

    @staticmethod
    def _unstable(status: str, sigma: float | None) -> bool:
        return status == "tripped" or (sigma is not None and sigma > 0)

    def analyze(self, data: dict, meta: dict) -> dict:
        """Per-step growth rates from the recorded position, the measured boundary
        (zero crossing of sigma), and the exact and approximate predictions."""
        from labbench import theory

        plant = Plant(**meta["plant"]) if "plant" in meta else self.plant()
        self._floor = 3 * float(meta.get("metres_per_count", 0.0))
        var = self.config.variable
        steps = []
        for seg in meta.get("segments", []):
            if seg.get("role", "probe") != "probe":
                continue
            part = {k: np.asarray(v)[seg["start"]:seg["stop"]] for k, v in data.items()}
            sigma = self._sigma(part)
            ve = VirtualEnvironment.from_dict(seg["ve"])
            steps.append({"K": ve.K, "td_s": ve.td, "status": seg["status"], "sigma_per_s": sigma,
                          "unstable": self._unstable(seg["status"], sigma)})
        crossing = _crossing(steps, "K" if var == "K" else "td_s")
        # K is continuous: the zero crossing of sigma is the boundary. td exists in whole
        # samples only: the boundary is the first unstable step (the crossing is kept too).
        measured = crossing if var == "K" else next(
            (s["td_s"] for s in steps if s["unstable"]), None)
        base = self.ve
        if var == "K":
            exact = theory.k_max(plant, base)
            approx = theory.k_max_approx(plant, base)
        else:
            exact, approx = _td_boundaries(plant, base, self.config)
        return {
            "variable": var,
            "steps": steps,
            "plant": {"m": plant.m, "b": plant.b},
            "measured_boundary": measured,
            "measured_crossing": crossing,
            "exact_boundary": exact,
            "approx_boundary": approx,
            "rel_error_vs_exact": _rel(measured, exact),
            "rel_error_approx_vs_measured": _rel(approx, measured),
        }

    def report_sections(self, session):
        """Page 1: the measured stability boundary against the exact sampled and the paper's
        predictions; details: every step's growth rate."""
        return _report_sections(self, session)


def _rel(a, b):
    return None if a is None or b is None or b == 0 else float((a - b) / b)


def _crossing(steps: list[dict], key: str) -> float | None:
    """Where sigma crosses zero between the last stable and first unstable step."""
    for prev, cur in pairwise(steps):
        if not prev["unstable"] and cur["unstable"]:
            s0, s1 = prev["sigma_per_s"], cur["sigma_per_s"]
            if s0 is not None and s1 is not None and s1 > s0:
                return float(prev[key] + (cur[key] - prev[key]) * (-s0) / (s1 - s0))
            return float(0.5 * (prev[key] + cur[key]))
    return None


def _td_boundaries(plant: Plant, ve: VirtualEnvironment, cfg: StabilityConfig):
    """Smallest td (whole samples) the exact sampled model calls unstable at this K, and the
    paper's continuous estimate td = b/K - T/2 (spring: b = K (T/2 + td))."""
    from labbench import theory

    exact = None
    n1 = round(cfg.td_stop_s / cfg.sample_time_s)
    for n in range(n1 + 1):
        if not theory.stability(plant, ve.with_(td=n * cfg.sample_time_s)).stable:
            exact = n * cfg.sample_time_s
            break
    approx = plant.b / ve.K - ve.T / 2 if ve.kind == "spring" else None
    return exact, approx


def _report_sections(protocol: StabilityProbe, session):
    from labbench.report.blocks import Figure, ReportSections, Table, fmt, new_figure

    res = session.results
    var = res.get("variable", protocol.config.variable)
    steps = res.get("steps") or []
    details = []
    if steps:
        details.append(Table("Probe steps", ["K (N/m)", "td (ms)", "status", "growth rate (1/s)",
                                             "unstable"],
                             [[fmt(p.get("K")), fmt(1e3 * p.get("td_s", 0.0)), str(p.get("status")),
                               fmt(p.get("sigma_per_s")), fmt(p.get("unstable"))] for p in steps]))
        key = "K" if var == "K" else "td_s"
        x = np.array([p.get(key) for p in steps], float)
        sig = np.array([np.nan if p.get("sigma_per_s") is None else p["sigma_per_s"]
                        for p in steps])
        fig = new_figure((7.2, 3.4))
        ax = fig.add_subplot()
        ax.plot(x, sig, "o-", label="measured growth rate")
        for name, v, style in (("measured", res.get("measured_boundary"), "-"),
                               ("exact sampled", res.get("exact_boundary"), "--"),
                               ("paper approx.", res.get("approx_boundary"), ":")):
            if v is not None:
                ax.axvline(v, color="0.3", ls=style, label=f"{name} boundary {v:.4g}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("K (N/m)" if var == "K" else "td (s)", fontsize=8)
        ax.set_ylabel("growth rate σ (1/s)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        details.append(Figure("Stability probe: growth rate of each step against the boundaries",
                              fig))
    return ReportSections(details=details, margin=False)
