"""The three-way trade-off of a haptic display, as numbers: stability, accuracy and force noise
of a spring-damper on one identified device, for any K, B, filter cut-off w0 and loop period T.

Colonnese, Sketch & Okamura end on it (sec. 5): the velocity filter and the virtual damping
make design "a three-way trade-off between stability, noise rejection, and accuracy". Each
number here comes from one model, named in ``MODELS`` (and in every ``as_dict``):

* **stability**: ``k_max``, the largest stable K of the exact sampled loop with the device's
  delay (``labbench.model.linear.k_max``), and ``margin`` = k_max / K; beside it the passive
  bounds of ``labbench.model.passivity``: ``k_passive`` (Colgate & Schenkel's sampled-data
  condition for this filter and delay) and ``k_quantised``, Abbott & Okamura's K <= 2 f_c /
  Delta with the device's Coulomb friction and encoder step (None where no friction is known);
  and ``k_friction``, the stiffness up to which an oscillation of the stated amplitude decays
  on the rubbing device (``labbench.model.stability_friction``: friction's describing-function
  damping 4 f_c / (pi w X) covering the sampled loop's deficit; Diolaiti et al. 2006).
  ``stable`` stays the linear loop's: a rubbing device renders stably above ``k_max`` only
  for motions small enough. With a stated hand speed, ``b_friction`` is the damping friction
  adds to what is rendered (Booton's statistical linearisation, ``labbench.model.friction``).
* **accuracy**: ``ws_star`` and ``wb_star`` read off the exact sampled model's ES and ED as
  a measurement is read (``labbench.model.predictions``); the rendered stiffness and damping, the
  model's low-frequency limits ES(0) = K and ED(0) (``labbench.model.linear.low_frequency``);
  the ED error at a frequency the user names, |ED(w) - (b + B)| / (b + B), in the exact sampled
  model (what an ETFE on the rig measures: the hold's half-sample advance included) and in
  the paper's eq. 2 (what a hand at the handle feels, the hold as a delay of T/2).
* **noise**: the force noise in the felt band, ``labbench.model.noise`` (the encoder step
  and the amplifier's noise through the exact sampled loop; the held force a hand feels,
  ``noise_felt``, and the recorded command's, ``noise_command``). Where the device's Coulomb
  friction is known it is in them too (``noise_friction`` its part): its equivalent damper
  and the remnant stick-slip adds (Booton's linearisation, the arcsine law), under the
  motion the targets state (``Targets.excitation_n``, or the white force that moves the
  handle at ``Targets.motion_m_s``); ``stick_share`` says how often the handle sticks at a
  reversal, the Gaussian velocity's condition.

**The w0 to choose.** With a noise limit, the virtual damping a filter allows is bounded:
the force noise grows with B and with w0. The Z-width a device offers under that limit is
the area under its stable boundary K_max(B) from B = 0 to the largest B whose noise stays
within the limit (``zwidth``; Colgate & Brown's impedance range, measured as an area as
Chawda, Celik & O'Malley, J. Dyn. Syst. Meas. Control 137(2), 2015, do): a faster filter
raises K_max(B) but lowers that B, so one w0 maximises the area (``recommend``). The
accurate band (w_b*) at a stated B is the other objective: the fastest filter whose noise
stays within the limit.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from labbench.model import predictions
from labbench.errors import UserError
from labbench.model import friction, linear, noise, passivity, stability_friction
from labbench.model.ve import Plant, VirtualEnvironment

ACCURACY_W = 2 * math.pi * 10.0  # rad/s: the top of volitional motion (paper sec. 5)
EXCITATION_N = 0.5  # N: the white-noise ETFE's std_n (protocols/white_noise.py), what a campaign runs
OBJECTIVES = ("zwidth", "band")
NOISE_OF = ("command", "felt")

MODELS = {
    "k_max": "exact sampled loop, first loss of stability as K grows (labbench.model.linear)",
    "margin": "k_max / K (exact sampled loop)",
    "k_passive": "sampled-data passivity, Colgate & Schenkel 1997 (labbench.model.passivity)",
    "k_quantised": "passivity with Coulomb friction and encoder step, Abbott & Okamura 2005: "
                   "K <= 2 f_c / Delta",
    "k_friction": "stable for oscillations of the stated amplitude with Coulomb friction: its "
                  "describing-function damping 4 f_c / (pi w X) against the sampled loop's "
                  "deficit (labbench.model.stability_friction)",
    "b_friction": "Coulomb friction's equivalent damping at the stated hand speed, "
                  "f_c sqrt(2/pi) / sigma_v (Booton; labbench.model.friction)",
    "ws_star": "read off the exact sampled model's ES (labbench.model.predictions)",
    "wb_star": "read off the exact sampled model's ED (labbench.model.predictions)",
    "rendered_K": "ES(0) of the exact sampled model",
    "rendered_B": "ED(0) of the exact sampled model",
    "ed_error_sampled": "exact sampled model at the accuracy frequency (as an ETFE measures)",
    "ed_error_paper": "paper eq. 2 at the accuracy frequency (as a hand at the handle feels)",
    "noise_felt": "labbench.model.noise: held force at the actuator in the felt band "
                  "(with the device's Coulomb friction where known)",
    "noise_command": "labbench.model.noise: recorded command in the felt band (with the "
                     "device's Coulomb friction where known)",
    "noise_friction": "Coulomb friction's part of noise_felt: its remnant Fc sign(v) - b_eq v "
                      "after Booton's equivalent damper, spectrum by the arcsine law (Van Vleck "
                      "& Middleton 1966), under the stated excitation (labbench.model.noise)",
    "stick_share": "share of velocity reversals at which the handle sticks (Rice): above "
                   "1 % the Gaussian velocity friction's noise assumes fails",
    "zwidth": "area under the exact sampled K_max(B) up to the noise-limited B",
}


@dataclass(frozen=True)
class Device:
    """The device a design is for: its identified ``plant``, the device's delay ``latency``
    [s], encoder step ``quantum_m`` [m], the amplifier's white noise ``force_noise_n`` [N std],
    Coulomb friction ``coulomb_n`` [N] (None: not known), and ``sources``: where each came
    from, in words (``plant``, ``latency``, ``quantum``, ``force_noise``, ``coulomb``)."""

    plant: Plant
    latency: float = 0.0
    quantum_m: float = 0.0
    force_noise_n: float = 0.0
    coulomb_n: float | None = None
    sources: dict = field(default_factory=dict)

    def noise_sources(self) -> noise.NoiseSources:
        return noise.NoiseSources(self.quantum_m, self.force_noise_n, self.coulomb_n or 0.0)

    def as_dict(self) -> dict:
        return {"m": self.plant.m, "b": self.plant.b, "latency_s": self.latency,
                "quantum_m": self.quantum_m, "force_noise_n": self.force_noise_n,
                "coulomb_n": self.coulomb_n, "sources": dict(self.sources)}


@dataclass(frozen=True)
class Targets:
    """What the design is held to: ``noise_limit_n`` [N rms] on the force noise ``noise_of``
    ("command": the noise the loop commands, which a record shows and a campaign measures;
    "felt": the held force at the actuator, the amplifier's own noise included) in the felt
    band ``band_hz`` (None: no limit); the oscillation amplitude ``amplitude_m`` the
    friction-aware stability boundary is for (oscillations that large decay below it); the
    accuracy frequency ``at_w`` [rad/s]; the hand's rms speed ``motion_m_s`` (None: the
    quantisation error taken as white, and friction's equivalent damping not given); the std
    ``excitation_n`` [N] of the white force that moves the handle, for friction's noise
    (default the ETFE's; with ``motion_m_s`` the white force that moves it at that speed)."""

    noise_limit_n: float | None = None
    noise_of: str = "command"
    amplitude_m: float = 1e-3
    band_hz: tuple[float, float] = noise.FELT_BAND_HZ
    at_w: float = ACCURACY_W
    motion_m_s: float | None = None
    excitation_n: float = EXCITATION_N

    def __post_init__(self):
        if self.noise_of not in NOISE_OF:
            raise UserError(f"noise limit applies to one of {', '.join(NOISE_OF)}, "
                            f"got {self.noise_of!r}")
        if self.noise_limit_n is not None and not (math.isfinite(self.noise_limit_n)
                                                   and self.noise_limit_n > 0):
            raise UserError("noise limit must be a positive number of N, got "
                            f"{self.noise_limit_n!r}")
        if not (math.isfinite(self.at_w) and self.at_w > 0):
            raise UserError(f"accuracy frequency must be positive rad/s, got {self.at_w!r}")
        if not (math.isfinite(self.amplitude_m) and self.amplitude_m > 0):
            raise UserError(f"oscillation amplitude must be a positive number of m, got "
                            f"{self.amplitude_m!r}")
        if self.motion_m_s is not None and not (math.isfinite(self.motion_m_s)
                                                and self.motion_m_s > 0):
            raise UserError(f"hand speed must be a positive number of m/s, got {self.motion_m_s!r}")
        if not (math.isfinite(self.excitation_n) and self.excitation_n > 0):
            raise UserError(f"excitation must be a positive number of N, got {self.excitation_n!r}")


@dataclass(frozen=True)
class DesignPoint:
    """One setting (K, B, w0, T) and its numbers (module doc; ``MODELS`` names each one's
    model). ``stable``: K < k_max; ``within_limit``: stable, and the noise the targets limit
    within it (True without a limit; False where no noise is predicted: friction holds the
    handle under the stated motion)."""

    K: float
    B: float
    w0: float
    T: float
    stable: bool
    k_max: float | None
    margin: float | None
    k_passive: float | None
    k_quantised: float | None
    k_friction: float | None
    ws_star: float | None
    wb_star: float | None
    rendered_K: float | None
    rendered_B: float | None
    b_friction: float | None
    ed_error_sampled: float | None
    ed_error_paper: float | None
    noise_felt: float | None
    noise_command: float | None
    noise_white: bool | None
    within_limit: bool
    noise_friction: float | None = None
    stick_share: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


class Designer:
    """Evaluates settings for one device and targets, remembering what does not depend on K
    (K_max and the passive bounds depend on B, w0 and T only)."""

    def __init__(self, device: Device, targets: Targets | None = None):
        self.device = device
        self.targets = targets or Targets()
        self._bounds: dict = {}

    def retarget(self, targets: Targets) -> Designer:
        """The same device held to other targets, its bounds remembered (they depend on the
        device and B, w0, T only)."""
        other = Designer(self.device, targets)
        other._bounds = self._bounds
        return other

    def ve(self, K: float, B: float, w0: float, T: float) -> VirtualEnvironment:
        return VirtualEnvironment("spring-damper", K=K, B=B, w0=w0, T=T)

    def bounds(self, B: float, w0: float, T: float) -> tuple:
        """(k_max, k_passive, k_friction) for B, w0, T (cached; k_friction for the targets'
        amplitude, None where the device's friction is not known)."""
        d = self.device
        key = (B, w0, T, self.targets.amplitude_m if d.coulomb_n else None)
        if key not in self._bounds:
            ve = self.ve(1.0, B, w0, T)
            self._bounds[key] = (
                linear.k_max(d.plant, ve, latency=d.latency),
                passivity.passive_k_max(d.plant, ve, d.latency),
                stability_friction.friction_boundary(d.plant, ve, d.coulomb_n,
                                                     self.targets.amplitude_m, d.latency)
                if d.coulomb_n else None)
        return self._bounds[key]

    def evaluate(self, K: float, B: float, w0: float, T: float) -> DesignPoint:
        return self.detail(K, B, w0, T)[0]

    def detail(self, K: float, B: float, w0: float, T: float
               ) -> tuple[DesignPoint, noise.ForceNoise | None]:
        """The point and its force noise with the spectra (None where it is unstable)."""
        d, t = self.device, self.targets
        if not K > 0:
            raise UserError(f"K must be > 0 N/m for a spring-damper design, got {K!r}")
        ve = self.ve(K, B, w0, T)
        k_max, k_passive, k_friction = self.bounds(B, w0, T)
        stable = k_max is not None and K < k_max
        bw = predictions.bandwidths(d.plant, ve, d.latency)
        base = d.plant.b + B
        w = np.array([t.at_w])
        if t.at_w > math.pi / T:
            raise UserError(f"accuracy frequency {t.at_w:g} rad/s is above the Nyquist "
                            f"frequency pi/T = {math.pi / T:g} rad/s")
        ed_s = float(linear.z_sampled(d.plant, ve, w, d.latency).real[0])
        ed_p = float(linear.z_paper(d.plant, ve, w, d.latency).real[0])
        felt = command = white = fn = None
        if stable:
            inc = (None if t.motion_m_s is None else
                   noise.increments_from_speed(t.motion_m_s, T))
            try:
                fn = noise.force_noise(d.plant, ve, d.noise_sources(), t.band_hz, d.latency, inc,
                                       self.excitation(ve))
            except UserError:  # friction holds the handle: no noise to predict
                fn = None
            else:
                felt, command, white = fn.rms_felt, fn.rms_command, fn.white
        held = felt if t.noise_of == "felt" else command
        # no noise predicted (unstable, or friction holding the handle): not within a limit
        within = t.noise_limit_n is None or (held is not None and held <= t.noise_limit_n)
        return DesignPoint(
            K=K, B=B, w0=w0, T=T, stable=stable, k_max=k_max,
            margin=(k_max / K) if k_max is not None else None, k_passive=k_passive,
            k_quantised=passivity.quantisation_bound(d.coulomb_n, d.quantum_m),
            k_friction=k_friction,
            ws_star=bw.ws_star, wb_star=bw.wb_star, rendered_K=K if stable else None,
            rendered_B=(linear.low_frequency(d.plant, ve, "sampled", d.latency)[0] if stable
                        else None),
            b_friction=(friction.gaussian_equivalent_damping(d.coulomb_n, t.motion_m_s)
                        if d.coulomb_n and t.motion_m_s else None),
            ed_error_sampled=abs(ed_s - base) / base if base > 0 else None,
            ed_error_paper=abs(ed_p - base) / base if base > 0 else None,
            noise_felt=felt, noise_command=command, noise_white=white,
            within_limit=bool(stable and within),
            noise_friction=fn.parts["friction"] if fn is not None and fn.friction else None,
            stick_share=fn.friction.stick_share if fn is not None and fn.friction else None), fn

    def excitation(self, ve: VirtualEnvironment) -> noise.Excitation | None:
        """The motion friction's noise is predicted under (None without known friction): the
        white force of ``Targets.excitation_n``, or with a hand speed the white force that
        moves the linearised loop at it (``labbench.model.friction.excitation_for``)."""
        d, t = self.device, self.targets
        if not d.coulomb_n:
            return None
        if t.motion_m_s is None:
            return noise.Excitation(t.excitation_n)
        b_eq = friction.gaussian_equivalent_damping(d.coulomb_n, t.motion_m_s)
        return noise.Excitation(friction.excitation_for(d.plant, ve, d.coulomb_n, b_eq,
                                                        latency=d.latency))

    def sweep(self, Ks, Bs, w0s, Ts, progress=None) -> list[DesignPoint]:
        """Every combination, in the order K, B, w0, T vary slowest to fastest."""
        combos = [(K, B, w0, T) for K in Ks for B in Bs for w0 in w0s for T in Ts]
        out = []
        for i, c in enumerate(combos):
            out.append(self.evaluate(*c))
            if progress:
                progress(i + 1, len(combos))
        return out

    def limited_noise(self, p: DesignPoint) -> float:
        """The noise the targets limit, of point ``p`` (inf where it is unstable)."""
        v = p.noise_felt if self.targets.noise_of == "felt" else p.noise_command
        return math.inf if v is None else v

    def noise_limited_b(self, K: float, Bs, w0: float, T: float) -> tuple[np.ndarray, np.ndarray]:
        """(B, the limited noise) on the grid ``Bs`` (sorted) for this K, w0, T."""
        Bs = np.sort(np.asarray(Bs, float))
        return Bs, np.array([self.limited_noise(self.evaluate(K, B, w0, T)) for B in Bs])

    def recommend(self, K: float, Bs, w0s, T: float, objective: str = "zwidth",
                  B: float | None = None) -> dict:
        """The w0 of ``w0s`` that maximises the objective under the noise limit (module doc):
        ``zwidth`` over the B grid ``Bs`` at this K, or ``band`` (w_b*) at the given B.
        Returns ``{"w0", "objective", "by_w0": [{w0, value, b_limit}...], "model"}``."""
        if objective not in OBJECTIVES:
            raise UserError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
        rows = []
        limit = self.targets.noise_limit_n
        for w0 in w0s:
            if objective == "zwidth":
                Bg, nz = self.noise_limited_b(K, Bs, w0, T)
                kmax = np.array([self.bounds(b, w0, T)[0] or 0.0 for b in Bg])
                area, b_lim = zwidth(Bg, kmax, nz, limit)
                rows.append({"w0": w0, "value": area, "b_limit": b_lim})
            else:
                if B is None:
                    raise UserError("the band objective needs the B it is for")
                p = self.evaluate(K, B, w0, T)
                rows.append({"w0": w0, "value": p.wb_star if p.within_limit else None,
                             "noise_n": self.limited_noise(p)})
        usable = [r for r in rows if r["value"] is not None and r["value"] > 0]
        best = max(usable, key=lambda r: r["value"]) if usable else None
        return {"objective": objective, "w0": best["w0"] if best else None,
                "value": best["value"] if best else None, "by_w0": rows,
                "noise_limit_n": limit,
                "model": MODELS["zwidth"] if objective == "zwidth" else MODELS["wb_star"]}


def rig_noise(rig, simulated: bool, sim_options: dict | None = None
              ) -> tuple[noise.NoiseSources, dict]:
    """The noise sources a rig states, and where each came from: on hardware the encoder's
    step (``Rig.metres_per_count``) and no amplifier noise (a rig file states none); on a
    simulator its ``[sim]`` table with ``sim_options`` over it: the step when it quantises,
    its ``force_noise_n``."""
    if not simulated:
        return (noise.NoiseSources(rig.metres_per_count, 0.0),
                {"quantum": "the rig's encoder (counts_per_rev, lever_arm_m)",
                 "force_noise": "none stated"})
    o = {**rig.section("sim"), **(sim_options or {})}
    q = rig.metres_per_count if o.get("quantize") else 0.0
    amp = float(o.get("force_noise_n", 0.0) or 0.0)
    return (noise.NoiseSources(q, amp),
            {"quantum": "the simulator's encoder (quantize = true)" if q else
             "none: the simulator does not quantise",
             "force_noise": f"the simulator's force_noise_n = {amp:g} N" if amp else "none"})


def device_for(rig, simulated: bool, identified: dict | None = None,
               commission: dict | None = None) -> Device:
    """The device of ``rig`` as the rig and its sessions describe it: the chirp-ID's plant
    and Coulomb term (``labbench.sessions.session_catalogue.last_identified``'s dict; None: the rig's
    nominal model), else the commissioning's Coulomb estimate (``commission_facts``), else a
    simulator's own ``[sim] coulomb_n`` (the truth, as ``labbench.model.device_friction``), the
    rig's delay (``labbench.model.device_delay``) and its noise sources (``rig_noise``); ``sources``
    says where each came from."""
    from labbench.model import device_delay

    found = identified or {}
    plant = Plant(found["m"], found["b"]) if found else rig.nominal_plant
    coulomb, coulomb_src = None, "unknown (no chirp-ID with a Coulomb term, no commissioning)"
    if found.get("coulomb_n") is not None:
        coulomb, coulomb_src = found["coulomb_n"], f"chirp-ID {found['session']}"
    elif (commission or {}).get("coulomb_n") is not None:
        coulomb, coulomb_src = commission["coulomb_n"], f"commissioning {commission['session']}"
    elif simulated and rig.section("sim").get("coulomb_n"):
        coulomb = float(rig.section("sim")["coulomb_n"])
        coulomb_src = f"the simulator's coulomb_n = {coulomb:g} N"
    delay = device_delay.resolve(rig)
    sources, where = rig_noise(rig, simulated)
    return Device(plant, delay.s, sources.quantum_m, sources.force_noise_n, coulomb,
                  {"plant": f"chirp-ID {found['session']}" if found else
                   "the rig's nominal model", "latency": f"{delay.origin}: {delay.source}",
                   "coulomb": coulomb_src, **where})


def zwidth(Bs, k_max, noise_n, limit: float | None) -> tuple[float, float | None]:
    """(area [N^2 s/m^2], B_limit): the area under K_max(B), piecewise linear on the grid
    ``Bs`` (sorted), from the first B to the largest B whose noise is within ``limit``, the
    crossing placed by linear interpolation of the noise between grid points (no limit: the
    whole grid). The same rule reads a campaign's measurements and the model's predictions.
    (0, None) when even the first B is over the limit."""
    Bs, k, nz = (np.asarray(a, float) for a in (Bs, k_max, noise_n))
    if limit is None:
        return float(np.trapezoid(k, Bs)), float(Bs[-1])
    if not nz[0] <= limit:
        return 0.0, None
    over = np.flatnonzero(~(nz <= limit))
    if not len(over):
        return float(np.trapezoid(k, Bs)), float(Bs[-1])
    j = over[0]  # first grid point over the limit; j - 1 within
    a = (limit - nz[j - 1]) / (nz[j] - nz[j - 1]) if math.isfinite(nz[j]) else 0.0
    b_lim = Bs[j - 1] + a * (Bs[j] - Bs[j - 1])
    k_lim = k[j - 1] + a * (k[j] - k[j - 1])
    area = float(np.trapezoid(k[:j], Bs[:j])) + 0.5 * (k[j - 1] + k_lim) * (b_lim - Bs[j - 1])
    return area, float(b_lim)


def pareto(points: list[DesignPoint]) -> list[DesignPoint]:
    """The stable points no other stable point beats on all three corners at once and on one
    strictly: a larger stability margin, a wider accurate band (w_b*) and less felt noise."""
    cand = [p for p in points if p.stable and p.noise_felt is not None]

    def key(p):
        return (p.margin or 0.0, p.wb_star or 0.0, -p.noise_felt)

    front = []
    for p in cand:
        kp = key(p)
        if not any(all(a >= b for a, b in zip(key(q), kp)) and key(q) != kp for q in cand):
            front.append(p)
    return front
