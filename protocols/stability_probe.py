"""Stability probe: step K (or td) up until the loop grows or the safety envelope trips.

Each step renders the VE for a few oscillation periods after a half-sine force
pulse and measures the growth rate sigma [1/s] of the free response
(least-squares line through the log of its half-cycle peaks). The first step
with sigma > 0, or ended by a safety trip (energy observer), is unstable and
ends the bracketing; the bracket crossing is where sigma crosses zero,
interpolated linearly between the last stable and the first unstable step.

Probing K, ``refine`` long steps (``refine_s`` each) then sit at the bracket
crossing times ``1 - refine_span`` .. ``1 + refine_span``, and the measured
boundary is the zero of the line through their growth rates, weighted by their
standard errors, with a 95 % interval from those errors (delta method). Near
the boundary sigma is small (a 1 % error in K is about 0.005 /s for the paper's
spring), so the bracket's short steps, whose sigma a quantised encoder or
torque blurs by as much, cannot place it within 1 %; the long steps can.

The pulse is sized (``swing``) so that the free response uses a fixed share of
the rig's tightest limit: force, position window or velocity. A fixed small
pulse left the response a few tens of encoder counts high at the boundary,
where the quantisation of position and force biased sigma by up to 2 % of K.

Everything is compared with the exact sampled boundary ``labbench.model.linear.k_max``
of the plant *with the device's own delay* (``device_delay_s``: the run's
``labbench.model.device_delay``) and the paper's ``k_max_approx`` (b = K (T/2 + td)
for the spring). Each step also keeps the peak energy the loop's passivity
observer saw (``labbench.loop.chain``: the energy the VE generated beyond what its
spring stores and the rig's nominal damping dissipates).

Steps beyond the exact boundary are the point of this protocol: the starting
VE must be stable (precheck), and the highest step is capped at ``max_over``
times the exact boundary.

**Friction.** On a device with Coulomb friction f_c (``plant_coulomb_n``: the rig's
commissioning or chirp-ID estimate) whether an oscillation grows depends on its size:
friction takes 4 f_c X a cycle out of an oscillation of amplitude X, a damper 4 f_c /
(pi w X) strong (``labbench.model.stability_friction``). A step's oscillation starts at the
pulse's swing, so the boundary this probe measures is the one for motions of that size,
beyond the linear one. With ``plant_coulomb_n`` given the probe predicts it before the run
(the swing each step's pulse is planned to give) and lets its steps go up to ``max_over``
times that prediction, never above ``friction_cap`` times the linear boundary (a safety
cap: the loop is unstable there for larger motions); afterwards it compares its measurement
with the prediction at the swing the steps near the boundary actually started from. Near a
boundary set by friction a step either dies out or runs away, so the growth rate is not
linear in K there: the measured interval is then the bracket [largest stable step, smallest
unstable step], not the refining line's. The result says where the probe stopped and why
(``stopped``).

**Homing on a sticking handle.** Friction holds a handle wherever a homing spring's pull is
below f_c, and a step's spring cannot be enabled off centre (the enable gate), so a homing
round that leaves the handle at rest short of centre stiffens the next round's spring
(x ``HOME_STIFFEN``, always a stable homing VE, its pull still at most 0.1 N). A step the gate
kept shut for most of its length measured nothing: it is neither stable nor unstable, and the
probe stops there and says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from labbench.errors import UserError
from labbench.model.pulse import PulsePlan
from labbench.rig import Rig
from labbench.loop.safety import CLAMP, FADE, GATED, RATE, TRIPPED
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.protocols import excitation
from labbench.readout.numfmt import fmt
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
HOME_ROUNDS = 12  # homing rounds before a step at most
HOME_STIFFEN = 4.0  # after a round that left the handle stuck off centre, the next is this stiffer
HOME_MARGIN = 2.0  # a stiffened homing VE stays stable at this many times its K
UNRENDERED = 0.5  # a step gated for this share of its samples or more measured nothing
PROBE_KINDS = ("spring", "spring-damper")
PULSE_AT_S = 0.05  # the pulse starts this long into a step
LOOK_S = 0.05  # zero force this long before the first step: where the handle is
GROWTH = 2.0  # an unstable step's oscillation may grow by this factor at most
NONLINEAR = CLAMP | RATE | FADE | TRIPPED  # flags after which a step's loop is not linear
Z95 = 1.959963984540054  # two-sided 95 % point of the normal distribution


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
    pulse_n: float | None = setting(None, "peak of the half-sine force pulse that starts each "
                                    "step; none: sized by swing", "N")
    pulse_s: float = setting(0.02, "duration of that pulse", "s")
    swing: float = setting(0.5, "share of the rig's tightest limit (force, position window, "
                           "velocity) the free response after the pulse uses (pulse_n none; "
                           "at most 0.8)")
    refine: int = setting(2, "long steps placed around the bracket's zero crossing of the "
                          "growth rate (variable K; 0: none, else 2 to 10)")
    refine_s: float = setting(10.0, "length of each refining step (min_step_s to 60 s)", "s")
    refine_span: float = setting(0.02, "the refining steps sit at the crossing times "
                                 "1 - refine_span .. 1 + refine_span (at most 0.2)")
    sample_time_s: float = 0.001
    plant_coulomb_n: float | None = setting(
        None, "the device's Coulomb friction: the friction-aware boundary beside the linear "
        "one, and how far beyond the linear one the steps may go; none: the chirp-ID's with "
        "--plant-from last-id, else not known (the linear boundary alone)", "N")
    plant_coulomb_ci95: tuple | None = None
    friction_cap: float = setting(
        3.0, "with plant_coulomb_n: highest K tried as a multiple of the exact (linear) K_max, "
        "however far the friction-aware boundary lies (a safety cap, at least max_over)")
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
        self._set("friction_cap", number("friction_cap", self.friction_cap, "1",
                                         lo=self.max_over, hi=100.0))
        self._set("cycles", number("cycles", self.cycles, "1", lo=2))
        self._set("min_step_s", number("min_step_s", self.min_step_s, "s", lo=0, lo_open=True,
                                              hi=60.0))
        self._set("max_step_s", number("max_step_s", self.max_step_s, "s", lo=self.min_step_s,
                                              hi=60.0))
        self._set("pulse_n", number("pulse_n", self.pulse_n, "N", lo=0, lo_open=True,
                                    none_ok=True))
        self._set("pulse_s", number("pulse_s", self.pulse_s, "s", lo=self.sample_time_s))
        self._set("swing", number("swing", self.swing, "1", lo=0, lo_open=True, hi=0.8))
        self._set("refine", integer("refine", self.refine, lo=0))
        if self.refine == 1:
            raise UserError("refine must be 0 or at least 2 (a line needs two steps)")
        if self.refine > 10:
            raise UserError(f"refine must be at most 10, got {self.refine}")
        self._set("refine_s", number("refine_s", self.refine_s, "s", lo=self.min_step_s,
                                     hi=60.0))
        self._set("refine_span", number("refine_span", self.refine_span, "1", lo=0,
                                        lo_open=True, hi=0.2))
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
    """Growth rate sigma [1/s] of an oscillation (``growth_fit`` without its error)."""
    fit = growth_fit(t, x, floor_m, rel_floor)
    return None if fit is None else fit[0]


def growth_fit(t: np.ndarray, x: np.ndarray, floor_m: float = 0.0,
               rel_floor: float = 0.02) -> tuple[float, float | None] | None:
    """Growth rate sigma [1/s] of an oscillation and its standard error: slope of the log
    of its half-cycle peaks.

    The offset (friction, quantisation) is the mean of the last fifth: a decay has
    settled there and a growth is a near zero-mean oscillation. Between
    consecutive zero crossings of x - offset the largest |x - offset| is one
    peak; for e^(sigma t) sin(w t + phi) the sums of consecutive peaks lie
    exactly on a line in log scale, slope sigma. Peaks at or below ``floor_m`` (a few encoder counts)
    or ``rel_floor`` of the largest are dropped (a decay that reached the noise
    floor would bias sigma towards zero), and so are the partial first and last
    half-cycles. None with fewer than 3 peaks.

    The error is the least-squares slope's standard error from the residuals, times
    sqrt(2): each peak enters two neighbouring sums, so neighbouring residuals share
    half their noise (correlation 1/2), which doubles the slope's variance against
    independent residuals (sum over lags of the correlation: 1 + 2 x 1/2). None with
    fewer than 4 sums (no residual left to judge).
    """
    sums = peak_sums(t, x, floor_m, rel_floor)
    if sums is None:
        return None
    tk, ly = sums[0], np.log(sums[1])
    slope, icept = np.polyfit(tk, ly, 1)
    se = None
    if tk.size >= 4:
        resid = ly - (slope * tk + icept)
        spread = np.sum((tk - tk.mean()) ** 2)
        if spread > 0:
            se = float(math.sqrt(2.0 * np.sum(resid**2) / (tk.size - 2) / spread))
    return float(slope), se


def peak_sums(t: np.ndarray, x: np.ndarray, floor_m: float = 0.0,
              rel_floor: float = 0.02) -> tuple[np.ndarray, np.ndarray] | None:
    """(times, sums of consecutive half-cycle peaks) of an oscillation, those ``growth_fit``
    fits (its doc says which are kept); half a sum is the oscillation's amplitude there.
    None with fewer than 3."""
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
    return tp[ok], yp[ok]


def rendered(data: dict) -> bool:
    """Whether a step rendered its VE: the enable gate was open for more than
    1 - ``UNRENDERED`` of its samples (a handle friction held off centre keeps it shut)."""
    flags = data.get("flags")
    if flags is None or len(flags) == 0:
        return True
    return float(np.mean((np.asarray(flags) & GATED) > 0)) < UNRENDERED


class StabilityProbe(ProtocolBase):
    name = "stability"

    Config = StabilityConfig
    config: StabilityConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return self.config.make_ve()

    def k_exact(self, plant: Plant) -> float | None:
        """The exact sampled K_max of the starting VE on ``plant`` with the device's delay."""
        from labbench.model import linear

        return linear.k_max(plant, self.ve, latency=self.device_delay_s)

    def k_friction(self, plant: Plant) -> float | None:
        """The friction-aware boundary the plan expects (``plant_coulomb_n`` given, variable K):
        where an oscillation of the swing each step's pulse is planned to start neither grows nor
        decays (``labbench.model.stability_friction.planned_boundary``); ``math.inf`` beyond
        ``friction_cap`` x the linear boundary; None without friction or a linear boundary."""
        from labbench.model.stability_friction import planned_boundary

        c = self.config
        km = self.k_exact(plant)
        if not c.plant_coulomb_n or c.variable != "K" or km is None or not 0 < km < math.inf:
            return None
        key = (plant.m, plant.b, self.device_delay_s, self._limits)
        if key not in self._k_friction:
            self._k_friction[key] = planned_boundary(plant, self.ve, c.plant_coulomb_n,
                                                     self.pulse_plan(), c.friction_cap,
                                                     self.device_delay_s)
        return self._k_friction[key]

    def friction_plan(self) -> dict | None:
        """What ``k_friction`` follows from besides the plant, the VE and the delay: the
        friction believed, ``friction_cap`` and the pulse plan (None where it has none), so
        that it can be computed again at any B (``labbench.model.stability_friction
        .planned_boundary``; a campaign's chart draws it over B)."""
        c = self.config
        if not c.plant_coulomb_n or c.variable != "K":
            return None
        return {"coulomb_n": c.plant_coulomb_n, "friction_cap": c.friction_cap,
                "pulse": self.pulse_plan().as_dict()}

    def k_ceiling(self, plant: Plant) -> float:
        """The last K tried: ``K_stop``, else ``max_over`` x the exact boundary, or with
        friction known ``max_over`` x the friction-aware one, at most ``friction_cap`` x the
        exact boundary (module doc)."""
        return self.ceiling(plant)[0]

    def ceiling(self, plant: Plant) -> tuple[float, str]:
        """(``k_ceiling``, which rule set it, in words)."""
        c = self.config
        km = self.k_exact(plant)
        ceiling = c.max_over * km if km is not None else math.inf
        why = f"max_over {c.max_over:g} x the linear boundary"
        kf = self.k_friction(plant)
        if kf is not None:
            if c.max_over * kf > ceiling:
                ceiling, why = c.max_over * kf, (f"max_over {c.max_over:g} x the friction-aware "
                                                 f"boundary {kf:.4g} N/m planned")
            if ceiling > c.friction_cap * km:
                ceiling, why = c.friction_cap * km, (f"the safety cap friction_cap "
                                                     f"{c.friction_cap:g} x the linear boundary")
        stop = c.K_stop if c.K_stop is not None else ceiling
        if stop > ceiling and not self.allow_unstable:
            allowed = (f"{c.max_over:g} x the exact boundary K_max = {km:.4g} N/m" if kf is None
                       else f"the ceiling {ceiling:.4g} N/m ({why}; exact K_max {km:.4g} N/m)")
            raise UserError(f"K_stop {stop:g} N/m is above {allowed}")
        if not math.isfinite(stop):
            raise UserError("no finite K_stop: give K_stop")
        return stop, why if c.K_stop is None else "K_stop"

    _k_friction: dict  # k_friction's results by plant, delay and limits (set in __init__)

    def __init__(self, config):
        super().__init__(config)
        self._k_friction = {}

    def plan(self, plant: Plant) -> list[VirtualEnvironment]:
        """The VEs of the bracketing steps, in order (it stops at the first unstable one;
        the refining steps follow from what the bracket found)."""
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
        n = sum(self.step_samples(ve, plant) for ve in self.plan(plant))
        if self.config.variable == "K":
            n += self.config.refine * round(self.config.refine_s / self.config.sample_time_s)
        return n

    def check_plan(self, plant: Plant, rig=None) -> dict:
        if rig is not None:
            self._floor = 3 * rig.metres_per_count
            self._limits = _limits(rig)
        ves = self.plan(plant)
        pulses = [self.pulse_n(ve, plant) for ve in ves]
        plan = {"steps": len(ves), "refine": self.config.refine
                if self.config.variable == "K" else 0,
                "first": ves[0].as_dict(), "last": ves[-1].as_dict(),
                "pulse_n": [min(pulses), max(pulses)]}
        kf = self.k_friction(plant)
        if kf is not None:
            plan["friction"] = {"coulomb_n": self.config.plant_coulomb_n, "k_max": kf,
                                "k_max_linear": self.k_exact(plant),
                                "swing_m": self.planned_amplitude(
                                    self.ve.with_(K=min(kf, ves[-1].K)), plant)}
        return {"plan": plan}

    def pulse_plan(self) -> PulsePlan:
        """What each step's pulse and the swing it starts follow from: this probe's
        ``swing``, ``pulse_s`` and ``pulse_n`` with the rig's limits
        (``labbench.model.pulse``)."""
        c = self.config
        f_lim, x_lim, v_lim = self._limits or _limits(Rig())
        return PulsePlan(c.swing, c.pulse_s, f_lim, x_lim, v_lim, c.pulse_n)

    def pulse_n(self, ve: VirtualEnvironment, plant: Plant) -> float:
        """Peak of the step's half-sine pulse [N]: ``pulse_n`` when given, else sized so the
        free response spends ``swing`` of the tightest limit of the rig
        (``labbench.model.pulse.PulsePlan.peak``)."""
        return self.pulse_plan().peak(plant.m, ve.K, ve.B)

    def planned_amplitude(self, ve: VirtualEnvironment, plant: Plant) -> float:
        """Position amplitude [m] the step's pulse is planned to start
        (``labbench.model.pulse.PulsePlan.swing``): a plan, not the measurement (``analyze``
        uses the swing measured)."""
        return self.pulse_plan().swing(plant.m, ve.K, ve.B)

    def pulse(self, n: int, peak_n: float | None = None) -> np.ndarray:
        c = self.config
        peak = c.pulse_n if peak_n is None else peak_n
        return excitation.pulse(n, c.sample_time_s, peak, c.pulse_s, at_s=PULSE_AT_S)

    def segments(self, plant: Plant):
        c = self.config
        # where is the handle, and is it moving? (a real one is where the last run left it,
        # perhaps still swinging): a moment of zero force tells, and the first step homes
        look = yield Segment("home", VirtualEnvironment("none", 0.0, 0.0, math.inf,
                                                        c.sample_time_s, 0.0),
                             np.zeros(max(round(LOOK_S / c.sample_time_s), 2)), role="home")
        self._last = look.data
        bracket = []
        for ve in self.plan(plant):
            label = f"K={ve.K:.6g}" if c.variable == "K" else f"td={ve.td:.6g}"
            n = self.step_samples(ve, plant)
            if c.variable == "K" and len(bracket) >= 2:
                n = self._growth_capped(n, _line_at(bracket[-2], bracket[-1], ve.K))
            sigma, unstable = yield from self._step(plant, ve, label, n, _shown(ve, c.variable))
            if unstable is None:  # never rendered: a stiffer step would not be either
                return
            bracket.append({"K": ve.K, "sigma_per_s": sigma, "unstable": unstable})
            if unstable:
                break
        if c.variable != "K" or not c.refine:
            return
        crossing = _crossing(bracket, "K")
        if crossing is None:
            return
        top = self.k_ceiling(plant)
        below, above = bracket[-2], bracket[-1]
        for K in refine_points(crossing, c.refine, c.refine_span):
            K = min(K, top)
            n = self._growth_capped(round(c.refine_s / c.sample_time_s), _line_at(below, above, K))
            ve = c.make_ve(K=K)
            yield from self._step(plant, ve, f"{REFINE}K={K:.6g}", n, REFINE + _shown(ve, "K"))

    def _growth_capped(self, n: int, sigma: float | None) -> int:
        """``n`` samples, or fewer for a step expected to grow (``sigma`` > 0, from the steps
        before it): its oscillation may at most double (from ``swing`` of the rig's limit to
        the limit at the default 0.5), so it ends before the force clamps or the energy
        observer fades and trips it, and the handle is left with no more than that to coast
        with before the next step's homing catches it; never below ``min_step_s``."""
        if sigma is None or not sigma > 0:
            return n
        c = self.config
        return max(min(n, round(math.log(GROWTH) / sigma / c.sample_time_s)),
                   round(c.min_step_s / c.sample_time_s))

    def _step(self, plant: Plant, ve: VirtualEnvironment, label: str, n: int, shown: str = ""):
        """Home, then one probe step; returns (sigma, unstable), unstable None for a step
        the enable gate kept shut (``rendered``). ``label`` is recorded (6 digits, so the
        refining steps 2 % apart stay apart); ``shown`` is the progress line's."""
        yield from self._home(plant, ve)
        out = yield Segment(label, ve, self.pulse(n, self.pulse_n(ve, plant)),
                            trip_expected=True, shown=shown)
        self._last = out.data
        if not rendered(out.data):
            return None, None
        sigma = self._sigma(out.data)
        return sigma, self._unstable(out.status, sigma)

    _last: dict | None = None  # data of the last segment (where the handle was left)
    _limits = None  # (force, position, velocity) limits of the rig, set by check_plan

    def _home(self, plant: Plant, next_ve: VirtualEnvironment):
        """Bring the handle back to rest near x = 0 before a step.

        The loop disables the device between segments, so the handle coasts (and
        before the first step it is where the last run left it: the probe looks first); a
        step's spring would then start far off centre and its enable gate
        (|command| small) would never open. Each homing stage renders a
        critically damped spring-damper soft enough to enable where the handle
        is (K_h |x| <= 0.1 N, and B_h |v| <= 0.1 N: a handle still coasting fast gets
        less than critical damping), until K_next |x| <= 0.05 N and |v| <= 0.01 m/s. A round
        that leaves the handle at rest short of that (friction holds it where the spring's
        pull is below f_c) makes the next round's spring ``HOME_STIFFEN`` times stiffer, as
        long as the homing VE stays stable with a ``HOME_MARGIN`` (module doc).
        """
        from labbench.model import linear

        T = self.config.sample_time_s
        stiff = HOME_K_MAX
        for _ in range(HOME_ROUNDS):
            if self._last is None or len(self._last["position"]) == 0:
                return
            x = float(self._last["position"][-1])
            v = float(self._last["velocity"][-1])
            if abs(next_ve.K * x) <= 0.05 and abs(v) <= 0.01:
                return
            # soft enough that the enable gate opens here: |K_h x| and |B_h v| each <= 0.1 N
            # (a fast coasting handle gets less than critical damping at first)
            K_h = min(stiff, 0.1 / max(abs(x), 1e-6))
            ve = self._homing_ve(plant, K_h, v)
            while K_h > HOME_K_MAX and not linear.stability(
                    plant, ve.with_(K=HOME_MARGIN * K_h), self.device_delay_s).stable:
                K_h = max(K_h / HOME_STIFFEN, HOME_K_MAX)
                ve = self._homing_ve(plant, K_h, v)
            if not linear.stability(plant, ve, self.device_delay_s).stable:
                raise UserError(f"homing VE K = {K_h:.3g} N/m, B = {ve.B:.3g} N s/m is unstable "
                                f"on m = {plant.m:g} kg, b = {plant.b:g} N s/m")
            dur = min(max(6.0 / math.sqrt(K_h / plant.m), 0.3), 3.0)
            out = yield Segment("home", ve, np.zeros(round(dur / T)), role="home")
            self._last = out.data
            if len(out.data["velocity"]) and abs(float(out.data["velocity"][-1])) <= 0.01:
                stiff = K_h * HOME_STIFFEN  # at rest and not home yet: held by friction

    def _homing_ve(self, plant: Plant, K_h: float, v: float) -> VirtualEnvironment:
        """Critically damped homing spring-damper of stiffness ``K_h`` (less damping for a
        handle still moving at ``v``, so |B_h v| <= 0.1 N)."""
        B_h = min(max(2 * math.sqrt(K_h * plant.m) - plant.b, 0.0), 0.1 / max(abs(v), 1e-6))
        return VirtualEnvironment("spring-damper", K_h, B_h, HOME_W0, self.config.sample_time_s,
                                  0.0)

    def _window(self, data: dict) -> tuple[np.ndarray, np.ndarray]:
        """(t, x) of the step's fitted stretch: from after the pulse to the first sample at
        which the envelope bent the force (clamp, rate limit, energy fade, trip): past it the
        loop is no longer the linear one whose growth is asked (a clamped growth looks
        slower)."""
        start = PULSE_AT_S + self.config.pulse_s + 0.05
        t = np.asarray(data["t"], float)
        if t.size == 0:
            return t, t
        keep = t - t[0] >= start
        flags = data.get("flags")
        if flags is not None:
            bent = np.flatnonzero(np.asarray(flags) & NONLINEAR)
            if bent.size:
                keep[bent[0]:] = False
        return t[keep], np.asarray(data["position"], float)[keep]

    def _fit(self, data: dict) -> tuple[float, float | None] | None:
        return growth_fit(*self._window(data), self._floor)

    def _swing(self, data: dict) -> list[float] | None:
        """[first, smallest, largest] amplitude [m] of the oscillation over the fitted
        stretch (half its peak-to-peak sums, ``peak_sums``), or None. The first is the
        swing the step's growth or decay starts from: with friction, what decides which."""
        sums = peak_sums(*self._window(data), self._floor)
        if sums is None:
            return None
        half = 0.5 * sums[1]
        return [float(half[0]), float(half.min()), float(half.max())]

    def _sigma(self, data: dict) -> float | None:
        fit = self._fit(data)
        return None if fit is None else fit[0]

    _floor = 0.0  # envelope floor [m]: 3 encoder counts once the rig is known

    @staticmethod
    def _unstable(status: str, sigma: float | None) -> bool:
        return status == "tripped" or (sigma is not None and sigma > 0)

    def analyze(self, data: dict, meta: dict) -> dict:
        """Per-step growth rates (with errors), swing and observer energy from the recording,
        the measured boundary (refined: the zero of the long steps' line; else the bracket's
        crossing), the exact and approximate predictions with the device's delay, with
        ``plant_coulomb_n`` the friction-aware one at the swing measured (``friction``), and where
        the probe stopped and why (``stopped``). A step the enable gate kept shut
        (``rendered`` false) is neither stable nor unstable."""
        from labbench.model import device_delay
        from labbench.model import linear

        plant = Plant(**meta["plant"]) if "plant" in meta else self.plant()
        latency = device_delay.from_meta(meta)
        self._floor = 3 * float(meta.get("metres_per_count", 0.0))
        self.device_delay_s = latency
        if isinstance(meta.get("rig"), dict):
            self._limits = _limits(meta["rig"])
        var = self.config.variable
        steps = []
        for seg in meta.get("segments", []):
            if seg.get("role", "probe") != "probe":
                continue
            part = {k: np.asarray(v)[seg["start"]:seg["stop"]] for k, v in data.items()}
            fit = self._fit(part)
            sigma, se = (None, None) if fit is None else fit
            ve = VirtualEnvironment.from_dict(seg["ve"])
            shown = rendered(part)
            steps.append({"K": ve.K, "td_s": ve.td, "status": seg["status"], "sigma_per_s": sigma,
                          "sigma_se_per_s": se, "rendered": shown,
                          "unstable": self._unstable(seg["status"], sigma) if shown else None,
                          "swing_m": self._swing(part) if shown else None,
                          "phase": "refine" if str(seg.get("label", "")).startswith(REFINE)
                          else "bracket", "energy_max_j": seg.get("energy_max_j"),
                          "x_start_m": float(part["position"][0]) if len(part["position"])
                          else None})
        judged = [s for s in steps if s["rendered"]]
        bracket = [s for s in judged if s["phase"] == "bracket"]
        crossing = _crossing(bracket, "K" if var == "K" else "td_s")
        refined = _refined(judged) if var == "K" else None
        # K is continuous: the zero crossing of sigma is the boundary. td exists in whole
        # samples only: the boundary is the first unstable step (the crossing is kept too).
        basis = "refined" if refined else "crossing"
        interval = refined["ci95"] if refined else None
        if var == "K":
            measured = refined["k"] if refined else crossing
            pair = _bracket(judged, "K")
            outside = refined is not None and not pair[0] <= refined["k"] <= pair[1] if pair \
                else False
            if pair and (self.config.plant_coulomb_n or outside):
                # with friction the growth rate is not linear in K near the boundary (a step
                # either dies out or runs away): a line through two steps, and its interval,
                # claim more than the steps show; what they show is the bracket
                measured, interval, basis = _pair_crossing(judged, pair), pair, "bracket"
        else:
            measured = next((s["td_s"] for s in judged if s["unstable"]), None)
        base = self.ve
        if var == "K":
            exact = linear.k_max(plant, base, latency=latency)
            approx = linear.k_max_approx(plant, base, latency)
        else:
            exact, approx = _td_boundaries(plant, base, self.config, latency)
        friction = None
        if var == "K" and self.config.plant_coulomb_n:
            friction = _friction(plant, base, self.config.plant_coulomb_n, latency, judged,
                                 measured, interval, float(meta.get("metres_per_count", 0.0)))
        return {
            "variable": var,
            "steps": steps,
            "plant": {"m": plant.m, "b": plant.b},
            "device_delay_s": latency,
            "measured_boundary": measured,
            "measured_ci95": interval,
            "measured_basis": basis,
            "measured_crossing": crossing,
            "bracket": _bracket(judged, "K" if var == "K" else "td_s"),
            "exact_boundary": exact,
            "approx_boundary": approx,
            "rel_error_vs_exact": _rel(measured, exact),
            "rel_error_approx_vs_measured": _rel(approx, measured),
            "energy": _energy(judged, "K" if var == "K" else "td_s"),
            "friction": friction,
            "stopped": _stopped(steps, var, measured, exact, friction, self._ceiling_text(plant)),
        }

    def _ceiling_text(self, plant: Plant) -> str | None:
        """The K ceiling and the rule that set it, in words (None for variable td)."""
        if self.config.variable != "K":
            return None
        try:
            top, why = self.ceiling(plant)
        except UserError:
            return None
        return f"the probe's ceiling {top:.4g} N/m ({why})"

    def report_sections(self, session):
        """Page 1: the measured stability boundary against the exact sampled and the paper's
        predictions; details: every step's growth rate."""
        return _report_sections(self, session)


REFINE = "refine "  # label prefix of the refining steps


def _shown(ve: VirtualEnvironment, variable: str) -> str:
    """A step as the progress line says it: 4 digits and the unit (the default refining
    steps lie 4 % apart; the label recorded in the session keeps 6)."""
    return f"K = {fmt(ve.K, 4)} N/m" if variable == "K" else f"td = {fmt(ve.td * 1e3, 4)} ms"


def _friction(plant: Plant, ve: VirtualEnvironment, fc: float, latency: float, steps: list[dict],
              measured: float | None, measured_interval: list | None,
              metres_per_count: float) -> dict:
    """The friction-aware boundary at the swing this probe's steps had
    (``labbench.model.stability_friction``): the steps that place the boundary (the
    refining ones, else the last stable and first unstable, else the last two) give the
    swing their oscillation started from (their median, and the range between them), hence
    the prediction and its range; beside it Abbott & Okamura's 2 f_c / Delta and, at the
    stiffest step, the amplitude below which oscillations die out (X*). ``agrees``: the
    prediction's range, widened by its ``tolerance`` f_c / (K X), meets the measured
    interval."""
    from labbench.model.passivity import quantisation_bound
    from labbench.model.stability_friction import friction_boundary, limit_cycle_amplitude

    near = [s for s in steps if s["phase"] == "refine" and s.get("swing_m")]
    if not near:
        bracket = [s for s in steps if s["phase"] == "bracket"]
        pair = next(([a, b] for a, b in pairwise(bracket) if not a["unstable"] and b["unstable"]),
                    bracket[-2:])
        near = [s for s in pair if s.get("swing_m")]
    out = {"coulomb_n": fc, "quantisation_bound": quantisation_bound(fc, metres_per_count),
           "swing_m": None, "swing_range_m": None, "k_max": None, "k_range": None,
           "tolerance": None, "rel_error": None, "agrees": None}
    if steps:
        top = max(steps, key=lambda s: s["K"])
        out["top_k"] = top["K"]
        out["limit_cycle_amplitude_m"] = limit_cycle_amplitude(plant, ve.with_(K=top["K"]), fc,
                                                               latency)
    if not near:
        return out
    starts = [s["swing_m"][0] for s in near]
    swing, lo, hi = float(np.median(starts)), min(starts), max(starts)
    k = friction_boundary(plant, ve, fc, swing, latency)
    k_range = [friction_boundary(plant, ve, fc, hi, latency),
               friction_boundary(plant, ve, fc, lo, latency)]
    # the describing function takes the motion for a sinusoid; friction's square wave bends
    # it by about f_c against the spring's K X: that share is the prediction's own tolerance
    tol = fc / (k * swing) if math.isfinite(k) and k > 0 else 0.0
    out.update(swing_m=swing, swing_range_m=[lo, hi], k_max=k, k_range=k_range, tolerance=tol,
               rel_error=_rel(measured, k),
               agrees=None if measured_interval is None or not math.isfinite(k_range[1]) else bool(
                   k_range[0] * (1 - tol) <= measured_interval[1]
                   and measured_interval[0] <= k_range[1] * (1 + tol)))
    return out


def _stopped(steps: list[dict], var: str, measured, exact, friction: dict | None,
             ceiling: str | None) -> str:
    """Where the probe stopped and why, in one line (``ceiling``: the K ceiling and its rule,
    in words)."""
    if not steps:
        return "no step ran"
    unit, key = ("N/m", "K") if var == "K" else ("s", "td_s")
    last = steps[-1]
    if not last["rendered"]:
        x = last.get("x_start_m")
        held = f" (the handle stood at {1e3 * x:.3g} mm, K x = {abs(last['K'] * x):.3g} N)" \
            if x is not None else ""
        return (f"stopped at the step {key} = {last[key]:.4g} {unit}: the enable gate stayed shut "
                f"for most of it{held}, so it rendered nothing and no boundary was measured "
                "beyond the steps before it")
    judged = [s for s in steps if s["rendered"]]
    top = max(s[key] for s in judged)
    ratio = f" ({top / exact:.3g} x the linear boundary {exact:.4g} {unit})" \
        if exact and var == "K" else ""
    fr = ""
    if friction and friction.get("k_max"):
        kf, lo, hi = friction["k_max"], *friction["k_range"]
        fr = (f"; friction {friction['coulomb_n']:.3g} N at this probe's "
              f"{1e3 * friction['swing_m']:.3g} mm swing predicts {kf:.4g} {unit} "
              f"(range {lo:.4g} to {hi:.4g} over the steps' swings)")
    if measured is not None:
        times = f" ({measured / exact:.3g} x the linear boundary {exact:.4g} {unit})" \
            if exact and var == "K" else ""
        return f"boundary measured at {key} = {measured:.4g} {unit}{times}: the growth rate " \
               f"crossed zero{fr}"
    if any(s["unstable"] for s in judged):
        return f"a step grew but no crossing could be placed (growth rates missing){fr}"
    why = ("friction takes out what the sampled loop feeds the probe's oscillations"
           if friction else "the device dissipates more than the linear model says "
           "(friction? give plant_coulomb_n for the friction-aware boundary)")
    if ceiling:
        ratio = f"{ratio}, the last step below {ceiling}"
    beyond = ""
    if friction and friction.get("limit_cycle_amplitude_m") is not None and var == "K":
        x_star = friction["limit_cycle_amplitude_m"]
        beyond = (f"; at the stiffest step oscillations below {1e3 * x_star:.3g} mm die out, "
                  "larger ones grow" if math.isfinite(x_star) else "")
    return f"no sustained oscillation up to {key} = {top:.4g} {unit}{ratio}: {why}{fr}{beyond}"


def _limits(rig) -> tuple[float, float, float]:
    """(force, position, velocity) limits the free response must stay inside: the force
    limit, the nearer edge of the position window from x = 0, the velocity limit. ``rig``: a
    Rig, or its ``as_dict()`` (a run's meta)."""
    get = rig.get if isinstance(rig, dict) else (lambda name: getattr(rig, name))
    lo, hi = get("position_limits_m")
    reach = min(abs(lo), abs(hi)) if lo < 0 < hi else max(abs(lo), abs(hi))
    return float(get("force_limit_n")), float(reach), float(get("velocity_limit_m_s"))


def refine_points(crossing: float, n: int, span: float) -> list[float]:
    """``n`` values of K spread evenly over crossing x [1 - span, 1 + span], lowest first
    (the unstable ones last)."""
    return [crossing * (1 - span + 2 * span * i / (n - 1)) for i in range(n)]


def _refined(steps: list[dict]) -> dict | None:
    """The zero of sigma(K) from the refining steps: weighted least-squares line through
    (K_i, sigma_i) with weights 1 / se_i^2 (equal weights when an error is missing), K* =
    -a / b for sigma = a + b K; its 95 % interval by the delta method (the line's
    covariance from the errors, so the interval is as honest as they are). None with fewer
    than two fitted steps or a slope that is not positive (noise larger than the span)."""
    pts = [s for s in steps if s["phase"] == "refine" and s["sigma_per_s"] is not None]
    if len({s["K"] for s in pts}) < 2:
        return None
    K = np.array([s["K"] for s in pts])
    sig = np.array([s["sigma_per_s"] for s in pts])
    se = np.array([s["sigma_se_per_s"] or np.nan for s in pts])
    known = np.isfinite(se) & (se > 0)
    w = 1.0 / se**2 if known.all() else np.ones_like(K)
    X = np.column_stack([np.ones_like(K), K])
    cov = np.linalg.inv(X.T @ (X * w[:, None]))
    a, b = cov @ (X.T @ (w * sig))
    if not (b > 0 and math.isfinite(a) and math.isfinite(-a / b)):
        return None
    k = float(-a / b)
    if not known.all():
        return {"k": k, "ci95": None}
    grad = np.array([-1.0 / b, a / b**2])  # d(-a/b)/d(a, b)
    half = Z95 * math.sqrt(float(grad @ cov @ grad))
    return {"k": k, "ci95": [k - half, k + half]}


def _line_at(a: dict, b: dict, K: float) -> float | None:
    """sigma at ``K`` on the line through two steps (None when either has no sigma)."""
    s0, s1 = a["sigma_per_s"], b["sigma_per_s"]
    if s0 is None or s1 is None or a["K"] == b["K"]:
        return None
    return s0 + (s1 - s0) * (K - a["K"]) / (b["K"] - a["K"])


def _bracket(steps: list[dict], key: str) -> list[float] | None:
    """[largest stable, smallest unstable] value of ``key`` among every step, when both
    exist in that order: what the steps alone say about the boundary."""
    stable = [s[key] for s in steps if not s["unstable"]]
    unstable = [s[key] for s in steps if s["unstable"]]
    if not stable or not unstable:
        return None
    lo, hi = max(stable), min(unstable)
    return [lo, hi] if lo < hi else None


def _energy(steps: list[dict], key: str) -> dict:
    """What the passivity observer saw: its largest energy in a stable step, and the first
    step (by ``key``) in which it exceeded 10 % of the most any step reached (the VE
    generating energy there: not passive), or None."""
    e = [(s[key], s["energy_max_j"]) for s in steps if s.get("energy_max_j") is not None]
    if not e:
        return {"max_stable_j": None, "first_generating": None}
    top = max(v for _, v in e)
    stable = [s["energy_max_j"] for s in steps
              if not s["unstable"] and s.get("energy_max_j") is not None]
    first = min((k for k, v in e if top > 0 and v > 0.1 * top), default=None)
    return {"max_stable_j": max(stable) if stable else None, "first_generating": first}



def _rel(a, b):
    return None if a is None or b is None or b == 0 else float((a - b) / b)


def _pair_crossing(steps: list[dict], pair: list[float]) -> float:
    """Where sigma crosses zero on the line through the two steps that bracket the boundary
    (``pair``: the largest stable K and the smallest unstable one); the midpoint when either
    has no growth rate."""
    lo = next(s for s in steps if s["K"] == pair[0] and not s["unstable"])
    hi = next(s for s in steps if s["K"] == pair[1] and s["unstable"])
    return _crossing([lo, hi], "K")


def _crossing(steps: list[dict], key: str) -> float | None:
    """Where sigma crosses zero between the last stable and first unstable step."""
    for prev, cur in pairwise(steps):
        if not prev["unstable"] and cur["unstable"]:
            s0, s1 = prev["sigma_per_s"], cur["sigma_per_s"]
            if s0 is not None and s1 is not None and s1 > s0:
                return float(prev[key] + (cur[key] - prev[key]) * (-s0) / (s1 - s0))
            return float(0.5 * (prev[key] + cur[key]))
    return None


def _td_boundaries(plant: Plant, ve: VirtualEnvironment, cfg: StabilityConfig,
                   latency: float = 0.0):
    """Smallest td (whole samples) the exact sampled model calls unstable at this K with the
    device's delay ``latency``, and the paper's continuous estimate td = b/K - T/2 - latency
    (spring: b = K (T/2 + td + latency))."""
    from labbench.model import linear

    exact = None
    n1 = round(cfg.td_stop_s / cfg.sample_time_s)
    for n in range(n1 + 1):
        if not linear.stability(plant, ve.with_(td=n * cfg.sample_time_s), latency).stable:
            exact = n * cfg.sample_time_s
            break
    approx = plant.b / ve.K - ve.T / 2 - latency if ve.kind == "spring" else None
    return exact, approx


def _report_sections(protocol: StabilityProbe, session):
    from labbench.report.blocks import Figure, ReportSections, Table, fmt, new_figure

    res = session.results
    var = res.get("variable", protocol.config.variable)
    steps = res.get("steps") or []
    details = []  # where the probe stopped is the readout's row (labbench.readout.wording)
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
        friction = res.get("friction") if isinstance(res.get("friction"), dict) else {}
        for name, v, style in (("measured", res.get("measured_boundary"), "-"),
                               ("exact sampled", res.get("exact_boundary"), "--"),
                               ("paper approx.", res.get("approx_boundary"), ":"),
                               ("friction-aware", friction.get("k_max"), "-.")):
            if isinstance(v, (int, float)) and math.isfinite(v):
                ax.axvline(v, color="0.3", ls=style, label=f"{name} boundary {v:.4g}")
        k_range = friction.get("k_range")
        if isinstance(k_range, list) and all(isinstance(k, (int, float)) and math.isfinite(k)
                                             for k in k_range):
            ax.axvspan(*k_range, color="tab:orange", alpha=0.2,
                       label="friction-aware, over the steps' swings")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("K (N/m)" if var == "K" else "td (s)", fontsize=8)
        ax.set_ylabel("growth rate σ (1/s)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        details.append(Figure("Stability probe: growth rate of each step against the boundaries",
                              fig))
    return ReportSections(details=details, margin=False)
